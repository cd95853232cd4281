"""How much of the eikonal mean a thinned batch spends near the object.

``python -m bench.eikonal_share RUN SCENE_INPUT [--batches 5] [--rays 1024]`` loads a trained
``fast`` run (``RUN/checkpoints``), draws ``--batches`` training batches of ``--rays`` rays from
``SCENE_INPUT`` (the scene folder ``fit`` was given), and prints the share of the eikonal mean
that comes from rays meeting an occupied cell of the run's occupancy grid:

* the full drawn batch (every sample weighs 1; what `all_on` trains with),
* the batch after :meth:`Adaptivity.thin_empty_rays`, every sample weighing 1 (before the
  eikonal was weighted),
* the same thinned batch with each sample weighted by its ray's importance weight
  (``RenderOutput.eikonal_weight``, what ``compute_losses`` uses now).

The share is ``sum_{i on such rays} q_i / sum_i q_i`` over the eikonal samples ``i``.
"""

from __future__ import annotations

import argparse
import glob

import torch


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", help="a run folder (or a bench output folder holding runs/*)")
    p.add_argument("scene", help="the training scene folder, e.g. ../shared/scenes/spot_textured/input/dtu")
    p.add_argument("--batches", type=int, default=5)
    p.add_argument("--rays", type=int, default=1024)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    from nepf_core.adaptivity import Adaptivity
    from nepf_core.data.detect import load_scene
    from nepf_core.fit import load_model
    from nepf_core.rays import PixelSampler
    from nepf_core.render.renderer import render_rays
    from nepf_core.render.sampling import near_far_from_sphere

    runs = glob.glob(a.run + "/runs/*") or [a.run]
    model, cfg, _ = load_model(runs[0], "cpu")
    if model.occupancy is None:
        raise SystemExit(f"{runs[0]}: the run has no occupancy grid (not an adaptive fast run)")
    sampler = PixelSampler(load_scene(a.scene), device="cpu")
    adapt = Adaptivity(cfg, enabled=True, iters_fixed=False)
    shares = {"full batch": [], "thinned, unweighted": [], "thinned, weighted": []}
    for s in range(a.batches):
        g = torch.Generator().manual_seed(s)
        rays = sampler.sample(a.rays, generator=g)
        thin = adapt.thin_empty_rays(model, rays, step=0, generator=g)
        w = render_rays(model, thin, cfg.render, train=True).eikonal_weight
        on_hit = (w == 1.0).float()          # hits weigh 1, kept misses 1 / miss_keep
        shares["thinned, unweighted"].append(float(on_hit.mean()))
        shares["thinned, weighted"].append(float((on_hit * w).sum() / w.sum()))
        near, far, _ = near_far_from_sphere(rays.origins, rays.directions)
        rays.weight = model.occupancy.ray_hits(rays.origins, rays.directions, near, far).float()
        shares["full batch"].append(float(render_rays(model, rays, cfg.render, train=True).eikonal_weight.mean()))
    for k, v in shares.items():
        print(f"{k}: {sum(v) / len(v):.3f} of the eikonal mean on rays that meet an occupied cell")


if __name__ == "__main__":
    main()
