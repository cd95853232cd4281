"""Neural fields: SDF (MLP or grid), outgoing radiance, photon (light), material, background."""
