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

Cameras: ``n_views`` training and ``n_test`` test cameras on Fibonacci spirals at
``camera_distance`` (object units) from the centre, elevation in [-25, 65] deg, looking at
the centre with +Z up; the test spiral is rotated by half a step so test views differ from
training views. Default field of view across the narrower image side:
``2.16 asin(min(0.95, 1 / distance))`` (the bounding ball's angular diameter plus 8 %), so
the object (bounding radius 1) fills the frame at any distance.

Light: one point light, ``L = shade(...) * I / d^2`` plus ``ambient * albedo``.
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
import math
import time
from pathlib import Path

import numpy as np
from PIL import Image

from nepf_core.color import linear_to_srgb
from nepf_core.data.images import to_uint8
from nepf_core.data.synth_render import Material, render_views
from nepf_core.data.synth_shapes import MATERIALS, SHAPES

SCALE_MAT_RADIUS = 1.1
ELEVATION_DEG = (-25.0, 65.0)

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


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV camera-to-world ``[4, 4]``: z forward to ``target``, x = z x up (right), y = z x x (down)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m


def spiral_positions(n: int, distance: float, phase: float) -> np.ndarray:
    """``[n, 3]`` points at ``distance`` on a Fibonacci spiral within :data:`ELEVATION_DEG`.

    ``z_k = sin(lo) + (k + 0.5)/n (sin(hi) - sin(lo))`` (equal-area), azimuth
    ``phi_k = (k + phase) * golden_angle``.
    """
    lo, hi = (math.radians(a) for a in ELEVATION_DEG)
    k = np.arange(n) + 0.5
    z = math.sin(lo) + k / n * (math.sin(hi) - math.sin(lo))
    phi = (np.arange(n) + phase) * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return distance * np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def intrinsics(w: int, h: int, fov_deg: float) -> np.ndarray:
    """Scene-convention ``K`` (pixel centres at +0.5), ``fov_deg`` across the narrower side:
    ``fx = fy = min(W, H) / (2 tan(fov/2))``, ``c = (W/2, H/2)``."""
    f = 0.5 * min(w, h) / math.tan(math.radians(fov_deg) / 2)
    return np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])


def auto_fov_deg(distance: float) -> float:
    """``2.16 asin(min(0.95, 1 / distance))`` in degrees: the unit ball's angular diameter + 8%."""
    return math.degrees(2.16 * math.asin(min(0.95, 1.0 / distance)))


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


def _srgb8(linear: np.ndarray) -> np.ndarray:
    """8-bit sRGB of linear values, encoded in float32 (what the PNGs hold)."""
    return to_uint8(linear_to_srgb(np.asarray(linear, dtype=np.float32)))


def _save_png(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path, compress_level=1)


def _world_mats(K: np.ndarray, c2w_obj: np.ndarray, s: float, off: np.ndarray) -> dict:
    """World-frame camera records for one view (DTU, OpenCV, OpenGL)."""
    c2w = c2w_obj.copy()
    c2w[:3, 3] = s * c2w_obj[:3, 3] + off
    w2c = np.linalg.inv(c2w)
    K_cv = K.copy()
    K_cv[0, 2] -= 0.5
    K_cv[1, 2] -= 0.5  # OpenCV: pixel centres at integers
    K4 = np.eye(4)
    K4[:3, :3] = K_cv
    return {"K_opencv": K_cv, "c2w_opencv": c2w, "w2c_opencv": w2c, "world_mat": K4 @ w2c,
            "c2w_opengl_blender": c2w @ np.diag([1.0, -1.0, -1.0, 1.0])}


def _write_dtu(folder: Path, cams: list[dict], scale_mat: np.ndarray, rgb8: np.ndarray,
               alpha: np.ndarray, masks: bool) -> None:
    arrays = {}
    for i, c in enumerate(cams):
        arrays[f"world_mat_{i}"] = c["world_mat"]
        arrays[f"world_mat_inv_{i}"] = np.linalg.inv(c["world_mat"])
        arrays[f"scale_mat_{i}"] = scale_mat
        arrays[f"scale_mat_inv_{i}"] = np.linalg.inv(scale_mat)
        _save_png(folder / "image" / f"{i:03d}.png", rgb8[i])
        if masks:
            m = np.where(alpha[i] >= 0.5, 255, 0).astype(np.uint8)
            _save_png(folder / "mask" / f"{i:03d}.png", np.repeat(m[..., None], 3, -1))
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(folder / "cameras.npz", **arrays)


def _write_blender(folder: Path, split: str, cams: list[dict], K: np.ndarray, w: int, h: int,
                   rgb_lin: np.ndarray, alpha: np.ndarray, masks: bool) -> None:
    frames = []
    for i, c in enumerate(cams):
        if masks:  # straight (un-premultiplied) colour + alpha
            straight = rgb_lin[i] / np.maximum(alpha[i], 1e-6)[..., None]
            rgba = np.concatenate([_srgb8(straight), to_uint8(alpha[i])[..., None]], -1)
            _save_png(folder / split / f"r_{i}.png", rgba)
        else:
            _save_png(folder / split / f"r_{i}.png", _srgb8(rgb_lin[i]))
        frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0,
                       "transform_matrix": c["c2w_opengl_blender"].tolist()})
    meta = {"camera_angle_x": 2.0 * math.atan(0.5 * w / K[0, 0]), "fl_x": K[0, 0], "fl_y": K[1, 1],
            "cx": K[0, 2], "cy": K[1, 2], "w": w, "h": h, "frames": frames}
    (folder / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))


def _write_mesh(gt: Path, shape: str, s: float, off: np.ndarray, res: int = 128) -> int:
    import torch
    import trimesh
    from skimage.measure import marching_cubes

    b = 1.1
    ax = np.linspace(-b, b, res)
    g = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1)
    f = SHAPES[shape](torch.from_numpy(g.reshape(-1, 3))).numpy().reshape(res, res, res)
    v, faces, _, _ = marching_cubes(f, 0.0, spacing=(ax[1] - ax[0],) * 3)
    v = v - b
    trimesh.Trimesh(v * s + off, faces[:, ::-1], process=False).export(gt / "mesh.ply")
    trimesh.Trimesh(v / SCALE_MAT_RADIUS, faces[:, ::-1], process=False).export(gt / "mesh_normalized.ply")
    return len(v)


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


def _write_split(out: Path, folder: Path, split: str, idx: np.ndarray, maps: dict, cams: list,
                 scale_mat: np.ndarray, K: np.ndarray, w: int, h: int, s: float, masks: bool) -> None:
    """The views ``idx`` of ``split`` as DTU (``folder``), Blender and the ground-truth arrays."""
    _write_dtu(folder, cams, scale_mat, _srgb8(maps["rgb"][idx]), maps["alpha"][idx], masks)
    _write_blender(out / "blender", split, cams, K, w, h, maps["rgb"][idx], maps["alpha"][idx], masks)
    np.savez_compressed(out / "gt" / f"arrays_{split}.npz", albedo=maps["albedo"][idx],
                        roughness=maps["roughness"][idx], metallic=maps["metallic"][idx],
                        alpha=maps["alpha"][idx], normal_world=maps["normal"][idx],
                        rgb_linear=maps["rgb"][idx], depth_z=maps["depth_z"][idx] * np.float32(s))


def _write_lights(gt: Path, light_position, light_intensity: float, ambient: float, exp: float, s: float,
                  off: np.ndarray) -> dict:
    """Write ``gt/lights.json`` (the light in world, normalised and object units, exposure
    included: ``I_world = I exp s^2``); returns the light's record."""
    lp_world = s * np.asarray(light_position, float) + off
    i_world = float(light_intensity) * exp * s * s
    light = {"type": "point", "position_world": lp_world.tolist(), "intensity_rgb": [i_world] * 3,
             "position_normalized": ((lp_world - off) / (SCALE_MAT_RADIUS * s)).tolist(),
             "intensity_rgb_normalized": [i_world / (SCALE_MAT_RADIUS * s) ** 2] * 3,
             "position_object": list(map(float, light_position)),
             "intensity_object_before_exposure": float(light_intensity)}
    lights = {"units": "radiant intensity, linear RGB image units (pixel value = radiance, exposure "
                       "included); irradiance E = I max(cos, 0) / d^2; 'normalized' values are for the "
                       "DTU unit-sphere space (positions through inv(scale_mat), intensity / (1.1 s)^2)",
              "lights": [light], "ambient": ambient * exp}
    (gt / "lights.json").write_text(json.dumps(lights, indent=1))
    return light


def _camera_record(cams: dict, scale_mat: np.ndarray, K: np.ndarray, w: int, h: int, distance: float) -> dict:
    """``scene.json["cameras"]``: the shared intrinsics and every split's world matrices."""
    def split_json(split):
        return [{"index": i, "width": w, "height": h, **{k: v.tolist() for k, v in c.items()},
                 "scale_mat": scale_mat.tolist(), "camera_angle_x": 2.0 * math.atan(0.5 * w / K[0, 0])}
                for i, c in enumerate(cams[split])]
    return {"distance_to_center": distance, "fov_x_deg": math.degrees(2.0 * math.atan(0.5 * w / K[0, 0])),
            "width": w, "height": h, "train": split_json("train"), "test": split_json("test")}


def _image_stats(maps: dict) -> dict:
    """``scene.json["stats"]``: the largest linear value, the share of foreground pixels that clip,
    and the 8-bit maximum and foreground median (the ``dark`` / ``clipped`` variants' checks)."""
    linear = maps["rgb"][maps["alpha"] > 0.99]
    fg8 = _srgb8(linear) if linear.size else np.zeros((0, 3), np.uint8)
    return {"linear_max": float(maps["rgb"].max()),
            "frac_fg_pixels_clipped": float((linear.max(-1) >= 1.0).mean()) if linear.size else 0.0,
            "png_max": int(_srgb8(maps["rgb"]).max()),
            "png_median_fg": float(np.median(fg8.max(-1))) if fg8.size else 0.0}


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
            (default :func:`auto_fov_deg`).
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
    fov = auto_fov_deg(camera_distance) if fov_deg is None else float(fov_deg)
    K = intrinsics(w, h, fov)
    phase = (seed * 0.61803398875) % 1.0
    pos = {"train": spiral_positions(n_views, camera_distance, phase),
           "test": spiral_positions(n_test, camera_distance, phase + 0.5) if n_test else np.zeros((0, 3))}
    c2w_obj = {k: [look_at(p, np.zeros(3)) for p in v] for k, v in pos.items()}
    maps = _render_one_thread(shape, mat, K, c2w_obj["train"] + c2w_obj["test"], w, h, supersample,
                              light_position, light_intensity, ambient)
    exp = _resolve_exposure(exposure, maps["rgb"], maps["alpha"])
    maps["rgb"] = maps["rgb"] * np.float32(exp)
    scale_mat = np.eye(4)
    scale_mat[:3, :3] *= SCALE_MAT_RADIUS * s
    scale_mat[:3, 3] = off
    (out / "gt").mkdir(parents=True, exist_ok=True)
    split_idx = {"train": np.arange(n_views), "test": np.arange(n_views, n_views + n_test)}
    cams = {k: [_world_mats(K, c, s, off) for c in v] for k, v in c2w_obj.items()}
    for split, folder in (("train", out / "dtu"), ("test", out / "gt" / "dtu_test")):
        if len(split_idx[split]):
            _write_split(out, folder, split, split_idx[split], maps, cams[split], scale_mat, K, w, h, s, masks)
    gt = out / "gt"
    gt.mkdir(parents=True, exist_ok=True)
    n_vertices = _write_mesh(gt, shape, s, off) if write_mesh else 0
    light = _write_lights(gt, light_position, light_intensity, ambient, exp, s, off)
    scene = {
        "scene": name or out.name, "note": "nepf synthetic scene (analytic SDF, nepf_core.bsdf)",
        "object": {"shape": shape, "center_world": off.tolist(), "bounding_radius_world": s,
                   "n_vertices": n_vertices,
                   "sdf": "see nepf_core/data/synth_shapes.py (object units, x_world = s x_obj + o)"},
        "material": mat.to_json(), "lights": [light],
        "world": {"up": "+Z", "world_scale": s, "world_offset": off.tolist(),
                  "units": "object bounding radius = world_scale", "background": "black, alpha 0"},
        "scale_mat": scale_mat.tolist(),
        "cameras": _camera_record(cams, scale_mat, K, w, h, camera_distance * s),
        "render": {"renderer": "nepf synth sphere tracer (direct light, hard shadows)",
                   "supersample": supersample, "exposure": exp, "exposure_mode": exposure,
                   "ambient": ambient, "seed": seed,
                   "png_encoding": "sRGB OETF, 8 bit, values clipped to [0,1]"},
        "stats": _image_stats(maps),
        "timing_s": {"total": time.time() - t_start},
    }
    (gt / "scene.json").write_text(json.dumps(scene, indent=1))
    if formats:
        from nepf_core.data.convert import write_formats
        write_formats(out, formats)
    return {**scene, "out_dir": str(out)}


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
