"""What the scene maker writes: the views as DTU and Blender, and the ground truth (``gt/``).

Layouts: module docstring of :mod:`nepf_core.data.synth`. The DTU ``scale_mat`` is
``[[1.1 s I, o], [0, 1]]`` (normalised -> world, :func:`scale_mat`), as in the shared scenes.
PNGs hold 8-bit sRGB of the linear renders (:func:`srgb8`); Blender images with masks are RGBA
with straight (un-premultiplied) colour.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from PIL import Image

from nepf_core.color import linear_to_srgb
from nepf_core.data.images import to_uint8
from nepf_core.data.synth_shapes import SHAPES

SCALE_MAT_RADIUS = 1.1


def scale_mat(s: float, off: np.ndarray) -> np.ndarray:
    """DTU's ``scale_mat`` ``[4, 4]``: the unit sphere onto the world ball of radius ``1.1 s`` around ``off``."""
    m = np.eye(4)
    m[:3, :3] *= SCALE_MAT_RADIUS * s
    m[:3, 3] = off
    return m


def srgb8(linear: np.ndarray) -> np.ndarray:
    """8-bit sRGB of linear values, encoded in float32 (what the PNGs hold)."""
    return to_uint8(linear_to_srgb(np.asarray(linear, dtype=np.float32)))


def save_png(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path, compress_level=1)


def write_dtu(folder: Path, cams: list[dict], scale_mat: np.ndarray, rgb8: np.ndarray,
               alpha: np.ndarray, masks: bool) -> None:
    arrays = {}
    for i, c in enumerate(cams):
        arrays[f"world_mat_{i}"] = c["world_mat"]
        arrays[f"world_mat_inv_{i}"] = np.linalg.inv(c["world_mat"])
        arrays[f"scale_mat_{i}"] = scale_mat
        arrays[f"scale_mat_inv_{i}"] = np.linalg.inv(scale_mat)
        save_png(folder / "image" / f"{i:03d}.png", rgb8[i])
        if masks:
            m = np.where(alpha[i] >= 0.5, 255, 0).astype(np.uint8)
            save_png(folder / "mask" / f"{i:03d}.png", np.repeat(m[..., None], 3, -1))
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(folder / "cameras.npz", **arrays)


def write_blender(folder: Path, split: str, cams: list[dict], K: np.ndarray, w: int, h: int,
                   rgb_lin: np.ndarray, alpha: np.ndarray, masks: bool) -> None:
    frames = []
    for i, c in enumerate(cams):
        if masks:  # straight (un-premultiplied) colour + alpha
            straight = rgb_lin[i] / np.maximum(alpha[i], 1e-6)[..., None]
            rgba = np.concatenate([srgb8(straight), to_uint8(alpha[i])[..., None]], -1)
            save_png(folder / split / f"r_{i}.png", rgba)
        else:
            save_png(folder / split / f"r_{i}.png", srgb8(rgb_lin[i]))
        frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0,
                       "transform_matrix": c["c2w_opengl_blender"].tolist()})
    meta = {"camera_angle_x": 2.0 * math.atan(0.5 * w / K[0, 0]), "fl_x": K[0, 0], "fl_y": K[1, 1],
            "cx": K[0, 2], "cy": K[1, 2], "w": w, "h": h, "frames": frames}
    (folder / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))


def write_gt_mesh(gt: Path, shape: str, s: float, off: np.ndarray, res: int = 128) -> int:
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


def write_split(out: Path, folder: Path, split: str, idx: np.ndarray, maps: dict, cams: list,
                 scale_mat: np.ndarray, K: np.ndarray, w: int, h: int, s: float, masks: bool) -> None:
    """The views ``idx`` of ``split`` as DTU (``folder``), Blender and the ground-truth arrays."""
    write_dtu(folder, cams, scale_mat, srgb8(maps["rgb"][idx]), maps["alpha"][idx], masks)
    write_blender(out / "blender", split, cams, K, w, h, maps["rgb"][idx], maps["alpha"][idx], masks)
    np.savez_compressed(out / "gt" / f"arrays_{split}.npz", albedo=maps["albedo"][idx],
                        roughness=maps["roughness"][idx], metallic=maps["metallic"][idx],
                        alpha=maps["alpha"][idx], normal_world=maps["normal"][idx],
                        rgb_linear=maps["rgb"][idx], depth_z=maps["depth_z"][idx] * np.float32(s))


def write_lights(gt: Path, light_position, light_intensity: float, ambient: float, exp: float, s: float,
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


def image_stats(maps: dict) -> dict:
    """``scene.json["stats"]``: the largest linear value, the share of foreground pixels that clip,
    and the 8-bit maximum and foreground median (the ``dark`` / ``clipped`` variants' checks)."""
    linear = maps["rgb"][maps["alpha"] > 0.99]
    fg8 = srgb8(linear) if linear.size else np.zeros((0, 3), np.uint8)
    return {"linear_max": float(maps["rgb"].max()),
            "frac_fg_pixels_clipped": float((linear.max(-1) >= 1.0).mean()) if linear.size else 0.0,
            "png_max": int(srgb8(maps["rgb"]).max()),
            "png_median_fg": float(np.median(fg8.max(-1))) if fg8.size else 0.0}
