"""Where a run's held-out PBR error comes from (used for the sphere_diffuse diagnosis in
docs/FAST.md, "The specular lobe on a diffuse scene").

    python -m bench.pbr_breakdown /work/shared/scenes/sphere_diffuse RUN_DIR [RUN_DIR ...]

For each finished run (``RUN/config.json`` + ``checkpoints/latest.pt``) it renders the scene's
held-out views (``gt/dtu_test``, every 2nd pixel) and prints, in sRGB PSNR over the GT mask:
the PBR inside the silhouette (mask eroded by 2 pixels) and on the 2-pixel rim, the radiance
network inside, the normal error against ``gt/arrays_test.npz`` ``normal_world`` (degrees),
and the mean metallic / roughness inside.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def breakdown(scene_dir: Path, run_dir: Path, stride: int = 2) -> dict:
    """Error breakdown of one run on ``scene_dir``'s held-out views (see the module docstring)."""
    import torch
    from scipy.ndimage import binary_erosion

    from nepf_core.data.detect import load_scene
    from nepf_core.evaluate import psnr, render_view, srgb_np
    from nepf_core.fit import load_model
    from nepf_core.rays import PixelSampler
    from nepf_core.reframe import load_held_out

    train = load_scene(scene_dir / "input" / "dtu")
    ts = load_held_out(scene_dir / "gt" / "dtu_test", train.world_from_norm)
    gt_arrays = np.load(scene_dir / "gt" / "arrays_test.npz")
    rot = train.world_from_norm[:3, :3] / train.world_scale()
    model, cfg, _ = load_model(run_dir, "cpu")
    sampler = PixelSampler(ts, "cpu")
    P, R, G, IN, RIM, nerr, metal, rough = [], [], [], [], [], [], [], []
    with torch.no_grad():
        for k in range(ts.n_views):
            r = render_view(model, sampler, k, cfg.render, stride=stride, rotation=rot)
            m = ts.masks[k, ::stride, ::stride] > 0.5
            inner = binary_erosion(m, iterations=2)
            n = r["normal"] / np.linalg.norm(r["normal"], axis=-1, keepdims=True).clip(1e-8)
            ng = gt_arrays["normal_world"][k, ::stride, ::stride]
            nerr.append(np.degrees(np.arccos(np.clip((n * ng).sum(-1), -1, 1)))[inner])
            metal.append(r["metallic"][inner]); rough.append(r["roughness"][inner])
            P.append(srgb_np(r["pbr"])); R.append(srgb_np(r["radiance"]))
            G.append(srgb_np(ts.images[k, ::stride, ::stride])); IN.append(inner); RIM.append(m & ~inner)
    P, R, G, IN, RIM = map(np.stack, (P, R, G, IN, RIM))
    ne = np.concatenate(nerr)
    return {"pbr_inside": psnr(P, G, IN), "pbr_rim": psnr(P, G, RIM), "radiance_inside": psnr(R, G, IN),
            "normal_err_mean_deg": float(ne.mean()), "normal_err_p95_deg": float(np.percentile(ne, 95)),
            "metallic_mean": float(np.concatenate(metal).mean()), "roughness_mean": float(np.concatenate(rough).mean())}


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2:
        raise SystemExit(__doc__)
    scene = Path(argv[0])
    for run in argv[1:]:
        b = breakdown(scene, Path(run))
        print(Path(run).name, " ".join(f"{k} {v:.3f}" for k, v in b.items()))


if __name__ == "__main__":
    main()
