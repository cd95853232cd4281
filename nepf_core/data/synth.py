"""Synthetic scenes with known truth: analytic SDF shapes rendered with our BSDF.

``make_scene(OUT, shape=..., material=...)`` writes (layout of ``../shared/scenes/<name>/``,
with the inputs at ``OUT/dtu`` and ``OUT/blender`` instead of ``OUT/input/...``)::

    OUT/dtu/cameras.npz            world_mat_i = K_cv @ [R|t] (4x4), scale_mat_i, *_inv_i
    OUT/dtu/image/000.png ...      sRGB 8-bit, background black
    OUT/dtu/mask/000.png ...       RGB 0/255 (alpha >= 0.5), when masks=True
    OUT/blender/transforms_{train,test}.json, train/r_i.png, test/r_i.png  (RGBA when masks)
    OUT/gt/dtu_test/               held-out views, DTU layout
    OUT/gt/mesh.ply, mesh_normalized.ply   marching cubes of the SDF (world / unit sphere)
    OUT/gt/arrays_{train,test}.npz albedo [N,H,W,3], roughness, metallic, alpha [N,H,W],
                                   normal_world [N,H,W,3], rgb_linear [N,H,W,3], depth_z
    OUT/gt/lights.json, OUT/gt/scene.json
    OUT/colmap/, OUT/colmap_txt/, OUT/nerfstudio/   the DTU cameras and images again, with
                                   gt mesh vertices as sparse points, when asked (``formats``,
                                   ``--formats``; ``convert.py``)

Geometry: the object lives in *object units* (inside the unit ball, Z up) and
``x_world = world_scale * x_obj + world_offset``; the DTU ``scale_mat`` is
``[[1.1 s I, o], [0, 1]]`` (normalised -> world), as in the shared scenes. Rendering runs in
object units, so extreme ``world_scale`` values change only the files, not the pixels.

Cameras (:mod:`nepf_core.data.synth_cameras`): ``n_views`` training and ``n_test`` test cameras on
Fibonacci spirals at ``camera_distance`` (object units) from the centre, elevation in [-25, 65]
deg, looking at the centre with +Z up; the test spiral is rotated by half a step so test views
differ from training views. Default field of view across the narrower image side:
``2.16 asin(min(0.95, 1 / distance))`` (the bounding ball's angular diameter plus 8 %), so
the object (bounding radius 1) fills the frame at any distance.

Files: :mod:`nepf_core.data.synth_files`. Light: one point light, ``L = shade(...) * I / d^2`` plus ``ambient * albedo``.
``exposure`` scales linear radiance before sRGB encoding: a number, ``"dark"`` (the 99th
percentile of the foreground pixels' largest channel encodes to 8-bit 7, so 99 % of the
foreground is below 8 and only highlights exceed it) or ``"clipped"`` (the median foreground pixel's largest
channel becomes 1, so about half the foreground clips at 255). ``lights.json`` reports the
*effective* intensity ``I * exposure`` (what reproduces the images), in world units
(``I_world = I s^2`` keeps the irradiance at the object).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from nepf_core.data.synth_cameras import auto_fov_deg, camera_record, intrinsics, spiral_cameras, world_camera
from nepf_core.data.synth_files import image_stats, scale_mat, write_gt_mesh, write_lights, write_split
from nepf_core.data.synth_render import Material, render_views
from nepf_core.data.synth_shapes import MATERIALS, SHAPES

#: Named stress variants (keyword overrides of :func:`make_scene`).
SCENE_VARIANTS = {
    "mirror_grazing": {"material": "mirror", "light_position": (4.0, -1.5, 0.25), "light_intensity": 60.0},
    "dark": {"exposure": "dark"},
    "clipped": {"exposure": "clipped"},
    "tiny_world": {"world_scale": 1e-3, "world_offset": (2e-3, -1e-3, 5e-4)},
    "huge_world": {"world_scale": 1e3, "world_offset": (500.0, -200.0, 100.0)},
    "close": {"camera_distance": 1.3},
    "far": {"camera_distance": 50.0},
    "single_view": {"n_views": 1},
}


def make_scene(out_dir, *, shape: str = "sphere", material: str = "diffuse", albedo=None,
               roughness: float | None = None, metallic: float | None = None, n_views: int = 16,
               n_test: int = 4, resolution: int | tuple[int, int] = 64,
               light_position=(3.0, -2.0, 4.0), light_intensity: float = 70.0, ambient: float = 0.0,
               world_scale: float = 1.0, world_offset=(0.0, 0.0, 0.0), camera_distance: float = 3.0,
               fov_deg: float | None = None, exposure: float | str = 1.0, seed: int = 0,
               masks: bool = True, supersample: int = 2, write_mesh: bool = True,
               name: str | None = None, formats: tuple = ()) -> dict:
    """Render a synthetic scene and write it as DTU + Blender + ground truth (see module doc).

    Args:
        out_dir: output folder (created).
        shape: one of :data:`~nepf_core.data.synth_shapes.SHAPES`.
        material: preset of :data:`~nepf_core.data.synth_shapes.MATERIALS`; ``albedo``
            (linear RGB), ``roughness``, ``metallic`` override it.
        n_views, n_test: training / held-out view counts (``n_test`` may be 0).
        resolution: ``R`` (square) or ``(W, H)``.
        light_position: object units; light_intensity: radiant intensity in object units.
        world_scale, world_offset: ``x_world = s x_obj + o``.
        camera_distance: object units; fov_deg: FOV across the narrower image side
            (default :func:`~nepf_core.data.synth_cameras.auto_fov_deg`).
        exposure: number, ``"dark"`` or ``"clipped"``.
        seed: rotates the camera spirals (azimuth phase).
        masks: write DTU masks and RGBA Blender images.
        supersample: ``ss x ss`` samples per pixel.
        formats: also write the training views as these layouts (``convert.EXTRA_FORMATS``).
    Returns:
        the ``scene.json`` dict (plus ``"out_dir"``).
    """
    t_start = time.time()
    if shape not in SHAPES:
        raise ValueError(f"unknown shape '{shape}' (one of {sorted(SHAPES)})")
    if n_views < 1 or n_test < 0:
        raise ValueError("need n_views >= 1 and n_test >= 0")
    mat = Material.resolve(material, albedo, roughness, metallic)
    w, h = (resolution, resolution) if isinstance(resolution, int) else tuple(resolution)
    out = Path(out_dir)
    s = float(world_scale)
    off = np.asarray(world_offset, dtype=np.float64)
    K = intrinsics(w, h, auto_fov_deg(camera_distance) if fov_deg is None else float(fov_deg))
    c2w_obj = spiral_cameras(n_views, n_test, camera_distance, seed)
    maps = _render_one_thread(shape, mat, K, c2w_obj["train"] + c2w_obj["test"], w, h, supersample,
                              light_position, light_intensity, ambient)
    exp = _resolve_exposure(exposure, maps["rgb"], maps["alpha"])
    maps["rgb"] = maps["rgb"] * np.float32(exp)
    sm = scale_mat(s, off)
    cams = {k: [world_camera(K, c, s, off) for c in v] for k, v in c2w_obj.items()}
    _write_splits(out, maps, cams, sm, K, w, h, s, masks)
    gt = out / "gt"
    n_vertices = write_gt_mesh(gt, shape, s, off) if write_mesh else 0
    light = write_lights(gt, light_position, light_intensity, ambient, exp, s, off)
    scene = {
        "scene": name or out.name, "note": "nepf synthetic scene (analytic SDF, nepf_core.bsdf)",
        "object": {"shape": shape, "center_world": off.tolist(), "bounding_radius_world": s,
                   "n_vertices": n_vertices,
                   "sdf": "see nepf_core/data/synth_shapes.py (object units, x_world = s x_obj + o)"},
        "material": mat.to_json(), "lights": [light],
        "world": {"up": "+Z", "world_scale": s, "world_offset": off.tolist(),
                  "units": "object bounding radius = world_scale", "background": "black, alpha 0"},
        "scale_mat": sm.tolist(),
        "cameras": camera_record(cams, sm, K, w, h, camera_distance * s),
        "render": {"renderer": "nepf synth sphere tracer (direct light, hard shadows)",
                   "supersample": supersample, "exposure": exp, "exposure_mode": exposure,
                   "ambient": ambient, "seed": seed,
                   "png_encoding": "sRGB OETF, 8 bit, values clipped to [0,1]"},
        "stats": image_stats(maps),
        "timing_s": {"total": time.time() - t_start},
    }
    (gt / "scene.json").write_text(json.dumps(scene, indent=1))
    if formats:
        from nepf_core.data.convert import write_formats
        write_formats(out, formats)
    return {**scene, "out_dir": str(out)}


def _write_splits(out: Path, maps: dict, cams: dict, sm: np.ndarray, K: np.ndarray, w: int, h: int, s: float,
                  masks: bool) -> None:
    """The training views as ``dtu/``, the test views as ``gt/dtu_test/`` (each also as Blender and
    ground-truth arrays); ``maps`` holds the training views first."""
    (out / "gt").mkdir(parents=True, exist_ok=True)
    n_views, n_test = len(cams["train"]), len(cams["test"])
    split_idx = {"train": np.arange(n_views), "test": np.arange(n_views, n_views + n_test)}
    for split, folder in (("train", out / "dtu"), ("test", out / "gt" / "dtu_test")):
        if len(split_idx[split]):
            write_split(out, folder, split, split_idx[split], maps, cams[split], sm, K, w, h, s, masks)


def _resolve_exposure(exposure, rgb: np.ndarray, alpha: np.ndarray) -> float:
    if isinstance(exposure, (int, float)):
        return float(exposure)
    fg = rgb[alpha > 0.99].max(axis=-1)
    if not fg.size:
        return 1.0
    if exposure == "dark":
        target = 7.0 / 255.0 / 12.92  # linear value that encodes to 8-bit 7 (linear sRGB segment)
        return target / max(float(np.percentile(fg, 99.0)), 1e-12) * 0.999
    if exposure == "clipped":
        return 1.0 / max(float(np.median(fg)), 1e-12)
    raise ValueError(f"exposure must be a number, 'dark' or 'clipped', got {exposure!r}")


def _render_one_thread(shape, mat, K, c2w: list, w: int, h: int, supersample: int, light_position,
                       light_intensity: float, ambient: float) -> dict:
    """:func:`render_views` of every camera ``c2w`` with one torch thread (small tensors: one thread
    is faster and immune to oversubscription)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return render_views(shape, mat, np.stack([K] * len(c2w)), np.stack(c2w), w, h, supersample,
                            light_position, light_intensity, ambient)
    finally:
        torch.set_num_threads(threads)


def add_make_scene_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``make-scene`` on an argparse ``subparsers`` object (for the ``nepf`` CLI)."""
    p = subparsers.add_parser("make-scene", help="render a synthetic scene (DTU + Blender + ground truth)")
    _add_args(p)
    p.set_defaults(func=run_make_scene)
    return p


def _exposure(v: str):
    return v if v in ("dark", "clipped") else float(v)


def _add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="output folder")
    p.add_argument("--preset", action="append", default=[], choices=sorted(SCENE_VARIANTS),
                   help="stress variant (repeatable); explicit options override it")
    p.add_argument("--shape", choices=sorted(SHAPES))
    p.add_argument("--material", choices=sorted(MATERIALS))
    p.add_argument("--albedo", type=float, nargs=3)
    p.add_argument("--roughness", type=float)
    p.add_argument("--metallic", type=float)
    p.add_argument("--views", dest="n_views", type=int)
    p.add_argument("--test-views", dest="n_test", type=int)
    p.add_argument("--resolution", type=int)
    p.add_argument("--light-position", type=float, nargs=3)
    p.add_argument("--light-intensity", type=float)
    p.add_argument("--ambient", type=float)
    p.add_argument("--world-scale", type=float)
    p.add_argument("--world-offset", type=float, nargs=3)
    p.add_argument("--camera-distance", type=float)
    p.add_argument("--fov", dest="fov_deg", type=float)
    p.add_argument("--exposure", type=_exposure, help="number, 'dark' or 'clipped'")
    p.add_argument("--seed", type=int)
    p.add_argument("--supersample", type=int)
    p.add_argument("--no-masks", dest="masks", action="store_false", default=None)
    p.add_argument("--formats", type=lambda v: tuple(f for f in v.split(",") if f),
                   help="also write the training views as colmap,colmap_txt,nerfstudio (comma-separated)")


def run_make_scene(args: argparse.Namespace) -> int:
    """Run ``make-scene`` from parsed arguments; prints a one-line summary, returns 0."""
    kw = {}
    for pr in args.preset:
        kw.update(SCENE_VARIANTS[pr])
    skip = {"out", "preset", "func", "command"}
    kw.update({k: v for k, v in vars(args).items() if k not in skip and v is not None})
    info = make_scene(args.out, **kw)
    print(json.dumps({"out_dir": info["out_dir"], "shape": info["object"]["shape"],
                      "n_train": len(info["cameras"]["train"]), "n_test": len(info["cameras"]["test"]),
                      "exposure": info["render"]["exposure"], "seconds": round(info["timing_s"]["total"], 2)}))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m nepf_core.data.synth OUT [--shape ...]`` (same options as ``nepf make-scene``)."""
    p = argparse.ArgumentParser(prog="nepf make-scene", description=__doc__.split("\n")[0])
    _add_args(p)
    return run_make_scene(p.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
