"""Volume rendering: NeuS weights, samplers, and the NePF renderer (L_r, L_vol, L_surf)."""
