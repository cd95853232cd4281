"""``nepf relight RUN --lights LIGHTS.json --cameras DATA --out DIR``: a run's asset under user lights.

Writes, for ``K`` lights and ``V`` views of ``DATA`` (at the size ``nepf render`` uses: full size,
or the working resolution ``max_side``):

* ``DIR/light_K/NNN.png``: 8-bit RGB, ``srgb(clip(rgb_linear, 0, 1))``, black background
  (K the 0-based light index, NNN the 0-based view index, as ``nepf render`` names its files);
* ``DIR/arrays.npz``: ``rgb_linear [K, V, H, W, 3]`` (float32 for at most
  :data:`FLOAT32_MAX_VIEWS` views, else float16; 0 where the asset does not cover the pixel) and
  ``alpha [V, H, W]`` (coverage in [0, 1], same dtype).

The BSDF is the run's (``cfg.render.bsdf_kind`` when the config has one, else ``"paper"``; its
``lambertian`` switch; the lobe off when the run dropped it), unless ``bsdf_kind`` overrides it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

FLOAT32_MAX_VIEWS = 64
"""Up to this many views ``arrays.npz`` holds float32, beyond it float16 (half the size)."""


def run_bsdf_kind(render_cfg) -> str:
    """The BSDF kind a run shades with: its render config's ``bsdf_kind``, ``"paper"`` when absent."""
    return str(getattr(render_cfg, "bsdf_kind", "paper"))


def write_relight_outputs(out, rgb: np.ndarray, alpha: np.ndarray) -> dict:
    """Write the PNGs and ``arrays.npz`` (module docstring) for ``rgb [K, V, H, W, 3]`` and
    ``alpha [V, H, W]``; returns ``{"lights": K, "views": V, "out": str(out)}``."""
    from PIL import Image

    from nepf_core.color import linear_to_srgb
    out = Path(out)
    K, V = rgb.shape[:2]
    for k in range(K):
        d = out / f"light_{k}"
        d.mkdir(parents=True, exist_ok=True)
        for v in range(V):
            img = (linear_to_srgb(np.clip(rgb[k, v], 0.0, 1.0)) * 255.0 + 0.5).astype(np.uint8)
            Image.fromarray(img).save(d / f"{v:03d}.png")
    dtype = np.float32 if V <= FLOAT32_MAX_VIEWS else np.float16
    np.savez_compressed(out / "arrays.npz", rgb_linear=rgb.astype(dtype), alpha=alpha.astype(dtype))
    return {"lights": int(K), "views": int(V), "out": str(out)}


def relight_run(run, lights_path, cameras, out, device: str = "auto", max_side: int = 0,
                bsdf_kind: str | None = None, shadows: bool = True, max_total_pixels: int | None = None) -> dict:
    """Relight every camera of the dataset ``cameras`` with the run's asset under the lights of
    ``lights_path`` (world frame) and write the outputs into ``out`` (module docstring). The
    lights file is checked before anything is loaded; ``max_total_pixels``: the decoded-pixel cap
    of the cameras' images (None: none). Returns :func:`write_relight_outputs`'
    dict plus ``rgb_linear`` and ``alpha`` (the arrays written)."""
    from nepf_core.rays import PixelSampler
    from nepf_core.reframe import load_held_out
    from nepf_core.relight.lights import lights_to_normalised, load_lights
    from nepf_core.relight.render import model_surfaces, relight_views
    from nepf_core.relight.shade import ShadeOptions
    from nepf_core.train import load_model

    lights = load_lights(lights_path)
    model, cfg, state = load_model(run, device)
    W = np.asarray(state["extra"]["world_from_norm"])
    scene = load_held_out(cameras, W, max_side=max_side, max_total_pixels=max_total_pixels)
    sampler = PixelSampler(scene, next(model.parameters()).device)
    shading = state["run_state"].shading()
    opts = ShadeOptions(kind=bsdf_kind or run_bsdf_kind(cfg.render), lambertian=bool(cfg.render.lambertian),
                        specular=bool(shading.specular))
    ln = lights_to_normalised(lights, W)
    was_training = model.training
    model.eval()
    rgb, alpha = relight_views(model_surfaces(model, cfg.render, shading), model.sdf.sdf, sampler,
                               ln.positions, ln.intensities, opts, shadows=shadows)
    model.train(was_training)
    Path(out).mkdir(parents=True, exist_ok=True)
    info = write_relight_outputs(out, rgb, alpha)
    info.update(rgb_linear=rgb, alpha=alpha, bsdf_kind=opts.kind, working_size=[scene.width, scene.height])
    return info
