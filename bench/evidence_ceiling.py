"""What the material evidence could call with the geometry, the light and the materials right
(``python -m bench.evidence_ceiling RUN SCENE``): how far the images are from our shading model.

At up to ``--points-per-view`` lit GT-foreground pixels of each test view it takes the **true**
surface point (from the GT depth, :func:`bench.oracle.depth_to_world`) and
the true normal, picks up to ``--views`` training cameras that face and see it (as the training's
evidence does, :func:`~nepf_core.render.material_evidence.views_of_points`, occlusion by the run's
SDF) and compares three colours toward those cameras:

* the training **pixels** there (:mod:`bench.evidence_pixels`);
* the run's **radiance** network there;
* our glTF BSDF at the **true materials** under the scene's true point lights, no shadows:
  ``c_k = sum_j f(n, u_j, v_k) I_j max(n . u_j, 0) / d_j^2`` (:func:`shade_true_lights`).

It prints, on GT metals and dielectrics: the relative residual of the model against the pixels
after a per-point scale (``min_s sum |s c_model - c|^2 / sum |c|^2``, so the light's units do not
enter), its median per-view ratio ``pixel / model`` binned by the view's model brightness against
the point's median view, and the evidence's metal call at the true key light on each colour. The
evidence called on the model's own colours is its ceiling (the fit itself); on the pixels, what
the images allow; on the radiance, what the network keeps of them (bench/RESULTS.md v47).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

BRIGHTNESS_BINS = ((0.0, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, 5.0), (5.0, float("inf")))
"""Bins of a view's model brightness over the point's median view."""


def shade_true_lights(x_world: np.ndarray, n_world: Tensor, v_world: Tensor, albedo: Tensor,
                      roughness: Tensor, metallic: Tensor, lights: list[dict]) -> Tensor:
    """``[P, K, 3]``: the glTF BSDF's radiance toward ``v_world [P, K, 3]`` (unit, toward the
    cameras) at points ``x_world [P, 3]`` with unit normals ``n_world [P, 3]``, ``albedo [P, 3]``,
    ``roughness, metallic [P]``, summed over the point ``lights`` (``position_world``,
    ``intensity_rgb``) with the inverse-square law and no shadows."""
    from nepf_core import bsdf

    P, K = v_world.shape[:2]
    each = lambda t: t.to(v_world.dtype)[:, None].expand(P, K, *t.shape[1:])
    n, a = each(n_world), each(albedo)
    r, m = each(roughness)[..., None], each(metallic)[..., None]
    out = torch.zeros(P, K, 3, dtype=v_world.dtype)
    for li in lights:
        d = np.asarray(li["position_world"], dtype=np.float64)[None] - x_world
        dist = np.linalg.norm(d, axis=-1)
        u = torch.as_tensor(d / dist[:, None], dtype=v_world.dtype)[:, None].expand(P, K, 3)
        E = torch.as_tensor(li["intensity_rgb"], dtype=v_world.dtype) / torch.as_tensor(dist ** 2, dtype=v_world.dtype)[:, None, None]
        out = out + bsdf.shade(n, u, v_world, a, r, m, E, kind="gltf")
    return out


def scaled_relative_residual(model: Tensor, c: Tensor, valid: Tensor) -> Tensor:
    """``[P]``: ``min_s sum_k,ch |s model - c|^2 / sum |c|^2`` over the valid views
    (``model, c [P, K, 3]``, ``valid [P, K]``)."""
    w = valid.to(c.dtype)[..., None]
    mm, mc, cc = ((model * model * w).sum((1, 2)), (model * c * w).sum((1, 2)), (c * c * w).sum((1, 2)))
    return (cc - mc * mc / mm.clamp_min(1e-30)).clamp_min(0.0) / cc.clamp_min(1e-30)


def ratio_by_brightness(model: Tensor, c: Tensor, valid: Tensor) -> list[dict]:
    """Per :data:`BRIGHTNESS_BINS` bin of ``Y(model_k) / median_k Y(model_k)`` (``Y`` the channel
    mean, median over the point's valid views): the views in it and the quartiles of
    ``Y(c_k) / Y(model_k)`` there."""
    y_m, y_c = model.mean(-1), c.mean(-1)
    med = torch.stack([y_m[i][valid[i]].median() if valid[i].any() else y_m.new_tensor(1.0)
                       for i in range(y_m.shape[0])])[:, None]
    rel = y_m / med.clamp_min(1e-12)
    rows = []
    for lo, hi in BRIGHTNESS_BINS:
        sel = valid & (rel >= lo) & (rel < hi) & (y_m > 0)
        if not bool(sel.any()):
            continue
        q = np.percentile((y_c[sel] / y_m[sel]).numpy(), [25, 50, 75])
        rows.append({"model_over_median": [lo, hi], "views": int(sel.sum()),
                     "pixel_over_model_p25_p50_p75": [round(float(t), 3) for t in q]})
    return rows


def true_points(run: Path, scene_dir: Path, points_per_view: int, views: int, seed: int) -> dict:
    """The true surface points of the module docstring with their cameras and three colours."""
    from bench.evidence_lights import scene_lights
    from bench.evidence_pixels import pixels_toward
    from bench.evidence_report import lit_foreground
    from bench.oracle import depth_to_world, world_cameras
    from nepf_core.reframe import load_held_out
    from nepf_core.render.material_evidence import MIN_VIEWS, views_of_points
    from nepf_core.train import load_model

    model, _cfg, state = load_model(run, "cpu")
    wfn = np.asarray(state["extra"]["world_from_norm"], dtype=np.float64)
    test, train = load_held_out(scene_dir / "gt" / "dtu_test", wfn), load_held_out(scene_dir / "input" / "dtu", wfn)
    gt = np.load(scene_dir / "gt" / "arrays_test.npz")
    lit = lit_foreground(gt)
    lin = wfn[:3, :3]
    rot = lin / test.world_scale()                           # u_norm = u_world @ rot
    norm_from_world = np.linalg.inv(wfn)
    rng, c2w_world = np.random.default_rng(seed), world_cameras(test)
    cols: dict[str, list] = {k: [] for k in ("x", "n", "albedo", "roughness", "metallic")}
    for v in range(test.n_views):
        x_world = depth_to_world(gt["depth_z"][v].astype(np.float64), test.intrinsics[v].astype(np.float64),
                                 c2w_world[v]).reshape(-1, 3)
        keep = np.nonzero(lit[v].reshape(-1))[0]
        keep = rng.choice(keep, min(points_per_view, len(keep)), replace=False)
        cols["x"].append(x_world[keep] @ norm_from_world[:3, :3].T + norm_from_world[:3, 3])
        cols["n"].append(gt["normal_world"][v].reshape(-1, 3)[keep] @ rot)
        for k in ("albedo", "roughness", "metallic"):
            cols[k].append(gt[k][v].reshape(len(x_world), -1)[keep])
    x = torch.tensor(np.concatenate(cols["x"]), dtype=torch.float32)
    n = torch.nn.functional.normalize(torch.tensor(np.concatenate(cols["n"]), dtype=torch.float32), dim=-1)
    cams = torch.as_tensor(np.asarray(train.c2w)[:, :3, 3], dtype=torch.float32)
    with torch.no_grad():
        c_rad, vdir, valid = views_of_points(model, x, n, cams, views, torch.Generator().manual_seed(seed))
    c_pix, inside = pixels_toward(train, x, vdir)
    valid = valid & inside
    ok = valid.sum(-1) >= MIN_VIEWS
    keep = ok.numpy()
    mat = {k: torch.tensor(np.concatenate(cols[k]), dtype=torch.float64)[keep] for k in ("albedo", "roughness", "metallic")}
    x_world = x.double().numpy()[keep] @ lin.T + wfn[:3, 3]
    rot_t = torch.as_tensor(rot.T, dtype=torch.float64)
    v_world = torch.nn.functional.normalize(vdir[ok].double() @ rot_t, dim=-1)
    n_world = torch.nn.functional.normalize(n[ok].double() @ rot_t, dim=-1)
    lights = scene_lights(scene_dir)
    c_model = shade_true_lights(x_world, n_world, v_world, mat["albedo"], mat["roughness"].reshape(-1),
                                mat["metallic"].reshape(-1), lights)
    key = int(np.argmax([np.mean(li["intensity_rgb"]) for li in lights]))
    to_key = np.asarray(lights[key]["position_world"], dtype=np.float64)[None] - x_world
    l_key = torch.nn.functional.normalize(torch.as_tensor(to_key @ rot, dtype=torch.float32), dim=-1)
    return {"n": n[ok], "v": vdir[ok], "valid": valid[ok], "l_key": l_key, "metal": mat["metallic"].reshape(-1).numpy() > 0.5,
            "colours": {"pixels": c_pix[ok].double(), "radiance": c_rad[ok].double(), "model": c_model}}


def ceiling_rows(pts: dict) -> dict:
    """The report of the module docstring for :func:`true_points`'s ``pts``."""
    from bench.evidence_lights import call_rates
    from nepf_core.render.material_evidence import material_evidence

    metal, cs, valid = pts["metal"], pts["colours"], pts["valid"]
    out = {}
    for kind, sel in (("metals", metal), ("dielectrics", ~metal)):
        if not sel.any():
            continue
        s = torch.as_tensor(sel)
        row = {"points": int(sel.sum())}
        res = scaled_relative_residual(cs["model"][s], cs["pixels"][s], valid[s]).numpy()
        row["model_vs_pixels_scaled_residual_p25_p50_p75"] = [round(float(t), 4) for t in np.percentile(res, [25, 50, 75])]
        row["pixel_over_model_by_brightness"] = ratio_by_brightness(cs["model"][s], cs["pixels"][s], valid[s])
        out[kind] = row
    for name, c in cs.items():
        ev = material_evidence(c.float(), pts["n"], pts["l_key"], pts["v"], valid, search_light=False)
        out[f"evidence_on_{name}"] = call_rates(ev.metallic.numpy() > 0.5, metal, None)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--points-per-view", type=int, default=250)
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    print(json.dumps(ceiling_rows(true_points(a.run, a.scene, a.points_per_view, a.views, a.seed)), indent=1))


if __name__ == "__main__":
    main()
