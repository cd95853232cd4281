"""The relighting oracle: the ground truth itself shaded with the product BSDF under the novel lights.

For each test view of a scene (``gt/dtu_test`` cameras, ``gt/arrays_test.npz`` maps) and each light
of ``gt/relight/lights.json`` (world frame):

* position ``x`` of a pixel from the GT z-depth: ``x_cam = z K^{-1} [i + 0.5, j + 0.5, 1]``
  (world units), mapped to the world by the camera;
* GT ``normal_world``, ``albedo``, ``roughness``, ``metallic``;
* ``L = f(l, v) I max(n.l, 0) / d^2 V``, ``f`` the project's BSDF of the chosen kind
  (:mod:`nepf_core.relight.shade`), ``V`` a ray cast against ``gt/mesh.ply`` from
  ``x + eps n`` towards the light (:class:`bench.mesh_shadows.MeshShadows`; ``eps`` = :data:`SHADOW_OFFSET` x the scene's scale);
* composited by the GT alpha, and scored with the relight PSNR
  (:func:`nepf_core.relight.metrics.relight_psnr`) against ``gt/relight/arrays.npz``.

No recovered asset can beat it with the same BSDF: what is left is the BSDF mismatch (ours
against Mitsuba's principled BSDF) and the missing interreflections.

``python -m bench oracle SCENE_DIR... [--bsdf paper gltf] [--out DIR]`` prints a table;
``--out`` also writes each oracle's ``arrays.npz`` / ``lights.json`` (the gt/relight format).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from bench.mesh_shadows import MeshShadows

SHADOW_OFFSET = 5e-3
"""Shadow rays start this far (times the scene's world scale) off the surface, along the normal.
The GT depth is a pixel average (Mitsuba, 32 spp), so on curved parts a point can lie a fraction
of a pixel footprint (~0.02 world units at 128 px) inside the mesh: at 1e-3 the shadow rays hit
the surface they leave (acne; spot_textured's oracle drops from 24.3 to 17.9 dB); 5e-3 and 2e-2
agree within 0.2 dB."""


def depth_to_world(depth_z: np.ndarray, intrinsics: np.ndarray, c2w_world: np.ndarray) -> np.ndarray:
    """World points ``[H, W, 3]`` of a z-depth map ``[H, W]`` (camera z, world units), pinhole
    ``K [3, 3]`` with pixel centres at +0.5 and ``c2w_world [4, 4]`` (a rigid camera-to-world)."""
    H, W = depth_z.shape
    jj, ii = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    d_cam = np.stack([ii, jj, np.ones_like(ii)], -1) @ np.linalg.inv(intrinsics).T  # z = 1
    x_cam = d_cam * depth_z[..., None]
    return x_cam @ c2w_world[:3, :3].T + c2w_world[:3, 3]


def world_cameras(scene) -> np.ndarray:
    """``[V, 4, 4]`` rigid camera-to-world (input world frame) of a loaded Scene: the rotation of
    ``world_from_norm @ c2w`` divided by the scale, its translation as it is."""
    M = np.asarray(scene.world_from_norm, np.float64)
    c2w = np.einsum("ij,njk->nik", M, scene.c2w.astype(np.float64))
    c2w[:, :3, :3] /= scene.world_scale()
    return c2w


def oracle_render(scene_dir, lights, bsdf_kind: str = "paper", shadows: bool = True,
                  maps: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The ground truth of ``scene_dir`` (``gt/dtu_test``, ``gt/arrays_test.npz``, ``gt/mesh.ply``)
    shaded under ``lights`` (:class:`nepf_core.relight.lights.PointLights`, world frame): returns
    ``rgb [K, V, H, W, 3]`` float32 (composited by the GT alpha) and ``alpha [V, H, W]``.

    ``maps``: per-view maps that replace the GT's of the same key (:func:`oracle_renders`)."""
    rgbs, alpha = oracle_renders(scene_dir, lights, bsdf_kind, shadows, [maps or {}])
    return rgbs[0], alpha


def oracle_renders(scene_dir, lights, bsdf_kind: str, shadows: bool,
                   map_sets: list[dict]) -> tuple[list[np.ndarray], np.ndarray]:
    """:func:`oracle_render` once per entry of ``map_sets``, each a dict of per-view maps that
    replace the GT's of the same key (``albedo [V, H, W, 3]``, ``roughness``, ``metallic
    [V, H, W]``, ``normal_world [V, H, W, 3]``, world frame; ``{}``: the GT itself), all shaded
    at the GT's points with the GT's shadows: one mesh ray cast per view and light from the GT
    point along the GT normal, shared by every set (:mod:`bench.relight_attribution`)."""
    import trimesh

    from nepf_core.data.detect import load_scene
    from nepf_core.relight.shade import ShadeOptions, SurfaceSamples, shade_under_lights
    gt_dir = Path(scene_dir) / "gt"
    scene = load_scene(gt_dir / "dtu_test")
    gt_maps = dict(np.load(gt_dir / "arrays_test.npz"))
    mesh = trimesh.load(gt_dir / "mesh.ply", force="mesh")
    cast = MeshShadows(mesh.vertices, mesh.faces).visibility(SHADOW_OFFSET * scene.world_scale()) if shadows else None
    c2w = world_cameras(scene)
    P = torch.from_numpy(lights.positions).float()
    I = torch.from_numpy(lights.intensities).float()
    alpha = gt_maps["alpha"].astype(np.float32)
    V, H, W = alpha.shape
    rgbs = [np.zeros((len(lights), V, H, W, 3), np.float32) for _ in map_sets]

    def t(a):
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    def unit(n):
        n = n.astype(np.float64)
        return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    for v in range(V):
        fg = alpha[v] > 0
        x = depth_to_world(gt_maps["depth_z"][v].astype(np.float64), scene.intrinsics[v].astype(np.float64), c2w[v])[fg]
        view = x - c2w[v][:3, 3]
        view /= np.linalg.norm(view, axis=-1, keepdims=True)
        n_gt = t(unit(gt_maps["normal_world"][v][fg]))
        seen = None if cast is None else [cast(t(x), n_gt, P[k]) for k in range(len(lights))]
        vis = None if seen is None else (lambda _x, _n, p: seen[int((P == p).all(-1).nonzero()[0, 0])])
        for rgb, replaced in zip(rgbs, map_sets):
            m = {**gt_maps, **replaced}
            n = t(unit(m["normal_world"][v][fg])) if "normal_world" in replaced else n_gt
            s = SurfaceSamples(t(x), n, t(view), t(m["albedo"][v][fg]),
                               t(m["roughness"][v][fg]), t(m["metallic"][v][fg]))
            L = shade_under_lights(s, P, I, ShadeOptions(kind=bsdf_kind), vis).numpy()
            rgb[:, v][:, fg] = L * alpha[v][fg][None, :, None]
    return rgbs, alpha


def oracle_scene(scene_dir, bsdf_kind: str = "paper", shadows: bool = True) -> dict:
    """:func:`oracle_render` under ``gt/relight/lights.json``, scored against ``gt/relight/arrays.npz``.

    Returns ``{"relight_psnr", "relight_scale", "rgb_linear" [K, V, H, W, 3] float32,
    "alpha" [V, H, W], "lights" (the lights.json dict)}``."""
    from nepf_core.relight.lights import load_lights
    from nepf_core.relight.metrics import relight_psnr
    relight = Path(scene_dir) / "gt" / "relight"
    lights = load_lights(relight / "lights.json")
    truth = np.load(relight / "arrays.npz")
    rgb, alpha = oracle_render(scene_dir, lights, bsdf_kind, shadows)
    value, scale = relight_psnr(rgb, truth["rgb_linear"].astype(np.float32), truth["alpha"].astype(np.float32))
    return {"relight_psnr": value, "relight_scale": [float(c) for c in scale], "rgb_linear": rgb,
            "alpha": alpha, "lights": lights.to_json()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench oracle", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", help="scene folders (each with gt/relight)")
    ap.add_argument("--bsdf", nargs="+", default=["paper", "gltf"], choices=["paper", "gltf"])
    ap.add_argument("--no-shadows", action="store_true", help="skip the shadow rays (for comparison)")
    ap.add_argument("--out", default=None, help="write OUT/<scene>/<bsdf>/{arrays.npz,lights.json}")
    ap.add_argument("--json", default=None, help="write the table as JSON here")
    a = ap.parse_args(argv)
    rows = []
    print("| scene | " + " | ".join(f"oracle {k} (dB) | scale {k}" for k in a.bsdf) + " |")
    print("|---|" + "---|---|" * len(a.bsdf))
    for sd in a.scenes:
        sd = Path(sd)
        if not (sd / "gt" / "relight" / "lights.json").is_file():
            print(f"{sd.name}: no gt/relight, skipped", file=sys.stderr)
            continue
        row = {"scene": sd.name}
        for kind in a.bsdf:
            r = oracle_scene(sd, kind, shadows=not a.no_shadows)
            row[kind] = {"relight_psnr": r["relight_psnr"], "relight_scale": r["relight_scale"]}
            if a.out:
                od = Path(a.out) / sd.name / kind
                od.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(od / "arrays.npz", rgb_linear=r["rgb_linear"], alpha=r["alpha"])
                (od / "lights.json").write_text(json.dumps(r["lights"], indent=1))
        rows.append(row)
        print(f"| {sd.name} | " + " | ".join(
            f"{row[k]['relight_psnr']:.2f} | {' / '.join(f'{c:.2f}' for c in row[k]['relight_scale'])}"
            for k in a.bsdf) + " |", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
