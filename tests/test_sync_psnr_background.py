"""Sync-PSNR of L_surf over a background: composited like L_vol (``w L_surf + (1 - w) C_bg``)."""
import math

import numpy as np
import torch

from nepf_core.config import tiny
from nepf_core.data.scene import Scene
from nepf_core.rays import PixelSampler
from nepf_core.render.renderer import RenderOutput
from nepf_core.train import evaluation


def _scene(h=4, w=4, n=2):
    rng = np.random.default_rng(0)
    K = np.array([[4.0, 0, 2], [0, 4.0, 2], [0, 0, 1]], np.float32)
    c2w = np.tile(np.eye(4, dtype=np.float32), (n, 1, 1))
    c2w[:, 2, 3] = -3.0
    return Scene(images=rng.uniform(0.2, 0.8, (n, h, w, 3)).astype(np.float32), masks=None,
                 intrinsics=np.tile(K, (n, 1, 1)), c2w=c2w, world_from_norm=np.eye(4), names=[f"{i}" for i in range(n)])


def test_surface_psnr_composites_the_background(monkeypatch):
    """A ray that meets nothing (opacity 0) whose background volume shows exactly the pixel:
    composited, L_surf is perfect (100 dB, the PSNR's floor); scored bare it would be black."""
    def fake_render(model, rb, cfg, *, train, shading=None, **kw):
        n = len(rb)
        zero = torch.zeros(n, 3)
        return RenderOutput(rgb_r=rb.rgb, rgb_vol=rb.rgb, rgb_surf=torch.full((n, 3), 0.9), weight_sum=torch.zeros(n),
                            w_max=torch.zeros(n), depth=torch.zeros(n), eikonal=torch.zeros(0),
                            hessian=torch.zeros(0), surface=None, background=rb.rgb.clone())
    monkeypatch.setattr(evaluation, "render_rays", fake_render)
    scene = _scene()
    sampler = PixelSampler(scene, torch.device("cpu"))
    res = evaluation.sync_psnr(torch.nn.Module(), sampler, tiny(), [0, 1], 16, seed=0)
    assert res["psnr_surf"] == res["psnr_vol"] == res["psnr_r"]
    assert math.isclose(res["psnr_surf"], 100.0)

    def fake_render_half(model, rb, cfg, *, train, shading=None, **kw):
        out = fake_render(model, rb, cfg, train=train)
        out.weight_sum = torch.full((len(rb),), 0.5)
        out.rgb_surf = rb.rgb.clone()
        return out
    monkeypatch.setattr(evaluation, "render_rays", fake_render_half)
    res = evaluation.sync_psnr(torch.nn.Module(), sampler, tiny(), [0, 1], 16, seed=0)
    assert math.isclose(res["psnr_surf"], 100.0)   # 0.5 surface + 0.5 background, both the pixel
