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
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def evidence_rows(run: Path, scene_dir: Path, points_per_view: int = 250, seed: int = 0) -> dict:
    import torch

    from bench.shading_report import training_image
    from nepf_core.rays import PixelSampler, unlit_threshold
    from nepf_core.reframe import load_held_out
    from nepf_core.relight.metrics import FOREGROUND_ALPHA
    from nepf_core.render.material_evidence import MIN_VIEWS, VIEWS_PER_POINT, material_evidence, views_of_points
    from nepf_core.train import load_model

    torch.manual_seed(seed)
    model, _cfg, state = load_model(run, "cpu")
    wfn = np.asarray(state["extra"]["world_from_norm"], dtype=np.float64)
    test = load_held_out(scene_dir / "gt" / "dtu_test", wfn)
    cams = torch.as_tensor(np.asarray(load_held_out(scene_dir / "input" / "dtu", wfn).c2w)[:, :3, 3],
                           dtype=torch.float32)
    pred = np.load(run / "relight_eval" / "renders" / "arrays.npz")
    gt = np.load(scene_dir / "gt" / "arrays_test.npz")
    fg = gt["alpha"] > FOREGROUND_ALPHA
    img = training_image(gt)
    lit = fg & (img.max(-1) >= unlit_threshold(img, fg, 0.01))   # training gathers evidence on lit rays only
    rng = np.random.default_rng(seed)
    sampler = PixelSampler(test, "cpu")
    cols: dict[str, list] = {k: [] for k in ("x", "n", "l", "metallic", "roughness")}
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
    x, n, l = (torch.nn.functional.normalize(torch.tensor(np.concatenate(cols[k]), dtype=torch.float32), dim=-1)
               if k != "x" else torch.tensor(np.concatenate(cols[k]), dtype=torch.float32) for k in ("x", "n", "l"))
    with torch.no_grad():
        c, vdir, valid = views_of_points(model, x, n, cams, VIEWS_PER_POINT, torch.Generator().manual_seed(seed))
        ok = valid.sum(-1) >= MIN_VIEWS
        ev = material_evidence(c[ok], n[ok], l[ok], vdir[ok], valid[ok])
    m_gt = np.concatenate(cols["metallic"]).astype(np.float32)[ok.numpy()]
    r_gt = np.concatenate(cols["roughness"]).astype(np.float32)[ok.numpy()]
    m, q, rough = ev.metallic.numpy(), ev.metallic_confidence.numpy(), ev.roughness.numpy()
    metal = m_gt > 0.5

    def called(sel):
        if not sel.any():
            return None
        return {"points": int(sel.sum()), "called_metal": float((m[sel] > 0.5).mean()),
                "called_metal_confidently": float(((m > 0.5) & (q > 0.1))[sel].mean())}

    return {"points": int(ok.sum()), "on_metals": called(metal), "on_dielectrics": called(~metal),
            "metallic_error_confidence_weighted": float((q * np.abs(m - m_gt)).sum() / max(q.sum(), 1e-12)),
            "roughness_median": float(np.median(rough)), "roughness_gt_median": float(np.median(r_gt)),
            "roughness_mae": float(np.abs(rough - r_gt).mean())}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--points-per-view", type=int, default=250)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    print(json.dumps(evidence_rows(a.run, a.scene, a.points_per_view, a.seed), indent=1))


if __name__ == "__main__":
    main()
