"""How right the material evidence is on a finished run, against the scene's true maps.

``python -m bench.evidence_report RUN SCENE [--points-per-view 250] [--seed 0]`` reads a bench run
(its model, and ``RUN/relight_eval/renders/arrays.npz``: depth, normal, light_dir of the test
views) and the scene's truth (``SCENE/gt/arrays_test.npz``: alpha, metallic, roughness; the
training cameras of ``SCENE/input/dtu``). At up to ``--points-per-view`` lit GT-foreground pixels of
each test view it takes the recovered surface point, gathers the radiance network's colours
from the training cameras that face and see it, and runs
:func:`nepf_core.render.material_evidence.material_evidence` with the learned light, as the
training term does. It prints:

* on GT metals and on GT dielectrics: the share called metal, and the share called metal with
  confidence > 0.1;
* the confidence-weighted metallic error ``sum q |m* - m_gt| / sum q``;
* the evidence's roughness against the truth (median of each, and the MAE).

So it says whether the evidence can be trusted on a kind of scene before a suite is run with it.
With ``--true-lights`` it also scores the same points at the scene's true light directions and
splits the metals' call rate by the fill light's share (:mod:`bench.evidence_lights`). Two
switches change what is fitted, to split the error: ``--pixels`` reads the training pixels at the
same points and cameras instead of the radiance network (:mod:`bench.evidence_pixels`), and
``--true-normals`` fits at the scene's normals instead of the run's.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def lit_foreground(gt) -> np.ndarray:
    """``[V, H, W]`` bool: the GT test views' foreground pixels the training would call lit (max
    channel over the unlit threshold of :func:`nepf_core.rays.unlit_threshold`; the training
    gathers evidence on lit rays only), from ``SCENE/gt/arrays_test.npz``."""
    from bench.shading_report import training_image
    from nepf_core.rays import unlit_threshold
    from nepf_core.relight.metrics import FOREGROUND_ALPHA

    fg = gt["alpha"] > FOREGROUND_ALPHA
    img = training_image(gt)
    return fg & (img.max(-1) >= unlit_threshold(img, fg, 0.01))


def lit_test_points(run: Path, scene_dir: Path, points_per_view: int = 250, seed: int = 0) -> dict:
    """Up to ``points_per_view`` lit GT-foreground pixels of each test view, at the run's surface
    point, with the radiance network's colours toward the training cameras that face and see it
    (points seen by fewer than ``MIN_VIEWS`` are left out). Returns tensors ``c, v, valid`` (as
    :func:`~nepf_core.render.material_evidence.views_of_points`), ``n, l [P, 3]`` (normalised
    frame; the run's normal and learned light), arrays ``metallic_gt, roughness_gt [P]``,
    ``x_world, n_gt_world [P, 3]`` (the run's point and the true normal, world frame) and
    ``rotation [3, 3]``, the normalised frame's axes in world (``u_norm = u_world @ rotation``)."""
    import torch

    from nepf_core.rays import PixelSampler
    from nepf_core.reframe import load_held_out
    from nepf_core.render.material_evidence import MIN_VIEWS, VIEWS_PER_POINT, views_of_points
    from nepf_core.train import load_model

    torch.manual_seed(seed)
    model, _cfg, state = load_model(run, "cpu")
    wfn = np.asarray(state["extra"]["world_from_norm"], dtype=np.float64)
    test = load_held_out(scene_dir / "gt" / "dtu_test", wfn)
    cams = torch.as_tensor(np.asarray(load_held_out(scene_dir / "input" / "dtu", wfn).c2w)[:, :3, 3],
                           dtype=torch.float32)
    pred = np.load(run / "relight_eval" / "renders" / "arrays.npz")
    gt = np.load(scene_dir / "gt" / "arrays_test.npz")
    lit = lit_foreground(gt)
    rng = np.random.default_rng(seed)
    sampler = PixelSampler(test, "cpu")
    cols: dict[str, list] = {k: [] for k in ("x", "n", "l", "metallic", "roughness", "n_gt")}
    for v in range(test.n_views):
        r = sampler.view_rays(v)
        x = r.origins.numpy() + r.directions.numpy() * pred["depth"][v].reshape(-1, 1).astype(np.float32)
        keep = np.nonzero(lit[v].reshape(-1))[0]
        keep = rng.choice(keep, min(points_per_view, len(keep)), replace=False)
        cols["x"].append(x[keep])
        cols["n"].append(pred["normal"][v].reshape(-1, 3)[keep])
        cols["l"].append(pred["light_dir"][v].reshape(-1, 3)[keep])
        cols["metallic"].append(gt["metallic"][v].reshape(-1)[keep])
        cols["roughness"].append(gt["roughness"][v].reshape(-1)[keep])
        cols["n_gt"].append(gt["normal_world"][v].reshape(-1, 3)[keep])
    x, n, l = (torch.nn.functional.normalize(torch.tensor(np.concatenate(cols[k]), dtype=torch.float32), dim=-1)
               if k != "x" else torch.tensor(np.concatenate(cols[k]), dtype=torch.float32) for k in ("x", "n", "l"))
    with torch.no_grad():
        c, vdir, valid = views_of_points(model, x, n, cams, VIEWS_PER_POINT, torch.Generator().manual_seed(seed))
    ok = valid.sum(-1) >= MIN_VIEWS
    keep = ok.numpy()
    lin = wfn[:3, :3]
    x_np = x.numpy().astype(np.float64)[keep]
    return {"c": c[ok], "v": vdir[ok], "valid": valid[ok], "n": n[ok], "l": l[ok],
            "metallic_gt": np.concatenate(cols["metallic"]).astype(np.float32)[keep],
            "roughness_gt": np.concatenate(cols["roughness"]).astype(np.float32)[keep],
            "x_norm": x_np, "world_from_norm": wfn, "x_world": x_np @ lin.T + wfn[:3, 3],
            "n_gt_world": np.concatenate(cols["n_gt"]).astype(np.float64)[keep],
            "rotation": lin / np.cbrt(abs(np.linalg.det(lin)))}


def evidence_rows(run: Path, scene_dir: Path, points_per_view: int = 250, seed: int = 0) -> dict:
    """The report of the module docstring (one dict)."""
    return rows_of_points(lit_test_points(run, scene_dir, points_per_view, seed))


def rows_of_points(pts: dict) -> dict:
    """The evidence with the learned light at :func:`lit_test_points`'s points, against the truth."""
    from nepf_core.render.material_evidence import material_evidence

    ev = material_evidence(pts["c"], pts["n"], pts["l"], pts["v"], pts["valid"])
    m_gt, r_gt = pts["metallic_gt"], pts["roughness_gt"]
    m, q, rough = ev.metallic.numpy(), ev.metallic_confidence.numpy(), ev.roughness.numpy()
    metal = m_gt > 0.5

    def called(sel):
        if not sel.any():
            return None
        return {"points": int(sel.sum()), "called_metal": float((m[sel] > 0.5).mean()),
                "called_metal_confidently": float(((m > 0.5) & (q > 0.1))[sel].mean())}

    return {"points": int(len(m_gt)), "on_metals": called(metal), "on_dielectrics": called(~metal),
            "metallic_error_confidence_weighted": float((q * np.abs(m - m_gt)).sum() / max(q.sum(), 1e-12)),
            "roughness_median": float(np.median(rough)), "roughness_gt_median": float(np.median(r_gt)),
            "roughness_mae": float(np.abs(rough - r_gt).mean())}


def main(argv: list[str] | None = None) -> None:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--points-per-view", type=int, default=250)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pixels", action="store_true",
                    help="read the training pixels instead of the radiance network (bench/evidence_pixels.py)")
    ap.add_argument("--true-normals", action="store_true",
                    help="fit at the scene's true normals instead of the run's (geometry's share of the error)")
    ap.add_argument("--true-lights", action="store_true",
                    help="also score the points with the scene's true lights (bench/evidence_lights.py)")
    ap.add_argument("--searched-fill", action="store_true",
                    help="also score with a second light searched per hypothesis (bench/evidence_lights.py)")
    a = ap.parse_args(argv)
    pts = lit_test_points(a.run, a.scene, a.points_per_view, a.seed)
    if a.true_normals:
        n_true = torch.tensor(pts["n_gt_world"] @ pts["rotation"], dtype=torch.float32)
        pts = {**pts, "n": torch.nn.functional.normalize(n_true, dim=-1)}
    if a.pixels:
        from bench.evidence_pixels import with_pixel_colours
        pts = with_pixel_colours(pts, a.scene)
    report = rows_of_points(pts)
    if a.true_lights:
        from bench.evidence_lights import true_light_rows
        report["true_lights"] = true_light_rows(pts, a.scene)
    if a.searched_fill:
        from bench.evidence_lights import searched_fill_rows
        report["searched_fill"] = searched_fill_rows(pts, a.scene)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
