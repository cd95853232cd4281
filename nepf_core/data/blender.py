"""NeRF-synthetic / Blender layout, and the NeRF ``transforms*.json`` parser shared with instant-ngp.

Layout: ``transforms_{train,test,val}.json`` beside the image folders, with
    * intrinsics: ``fl_x``/``fl_y`` (pixels) or ``camera_angle_x`` (and optionally
      ``camera_angle_y``): ``fx = W / (2 tan(angle_x / 2))``, ``fy = fx`` unless given;
      ``cx``/``cy`` default to ``W/2``, ``H/2`` (pixel centres at +0.5, as Blender renders
      and instant-ngp assumes: ``Scene``'s convention, so no shift). Any of these keys may
      also appear per frame, overriding the top level (instant-ngp allows it).
    * ``frames[].file_path``: relative to the JSON file, extension optional
      (``./train/r_0`` -> tries ``.png``, ``.jpg``, ``.jpeg``). It must resolve inside the
      dataset folder (``paths.py``): an absolute path, a ``../..`` escape or a symbolic link
      out of the folder is ``path_outside_dataset``.
    * ``frames[].transform_matrix``: camera-to-world in the OpenGL convention
      (x right, y up, z backward); ``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)``.
    * OpenCV distortion ``k1, k2, p1, p2`` (``k3``) is undone while reading (see ``ingp.py``).
    * nerfstudio's keys, wherever they appear: ``camera_model`` (PINHOLE, SIMPLE_PINHOLE, OPENCV
      load, with ``k4`` as the ``r^8`` term; fisheye and equirectangular are refused by name,
      ``camera_models.py``) and ``frames[].mask_path`` (relative to the JSON, inside the folder,
      read like a DTU mask: luma > 127 is the object; every frame or none).

RGBA images: the alpha channel is the mask (``alpha >= 0.5``), and the colour is composited
onto black in linear space, ``rgb_linear = srgb_to_linear(rgb_stored) * alpha``, so the
background is black (a NeuS-style mask loss then sees the same thing as the images).

Normalisation (the JSON has none): :func:`nepf_core.data.normalize.normalization_from_cameras`
on the **train** split at a working resolution of at most 256 pixels on the long side,
whichever split is requested and whatever ``downscale``/``max_views`` are, so that every
split of a dataset shares one normalised frame. The visual hull of the alpha masks is used
when the images are RGBA, else the frustum rule.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from nepf_core.data.assemble import read_normalized_views, scene_from_views
from nepf_core.data.camera_models import check_nerfstudio_model
from nepf_core.data.errors import DatasetError
from nepf_core.data.budget import image_size
from nepf_core.data.images import (SUPPORTED_EXTS, box_downscale, decode_image, is_image_name,
                                   looks_like_image, mask_from_array, read_image)
from nepf_core.data.normalize import (Normalization, check_c2w,
                                      check_intrinsics, normalization_from_cameras,
                                      opengl_to_opencv)
from nepf_core.data.paths import dataset_path, existing_file, rel
from nepf_core.data.scene import Scene
from nepf_core.data.views import ViewSpec
from nepf_json import DEFAULT_LIMITS, JsonInputError, load_file

SPLITS = ("train", "test", "val")
#: Long side of the masks used to estimate the normalisation.
NORM_WORKING_SIZE = 256


def split_file(root: Path, split: str) -> Path:
    """``root / f"transforms_{split}.json"``."""
    return Path(root) / f"transforms_{split}.json"


def is_blender(root: Path) -> bool:
    """True when ``root`` holds any ``transforms_{train,test,val}.json`` (inside ``root``)."""
    return any(existing_file(root, split_file(root, s).name) is not None for s in SPLITS)


#: limits on a ``transforms*.json`` (docs/SERVICE.md, "Limits"): the parser's defaults and at most
#: 32 MiB, some 50,000 frames (a frame takes ~600 bytes)
TRANSFORMS_JSON_LIMITS = dataclasses.replace(DEFAULT_LIMITS, max_bytes=32 * 1024 * 1024)


def read_json(path: Path, root: Path) -> dict:
    """Parse a JSON object with :mod:`nepf_json` (nesting, number and string length bounded,
    duplicate keys refused, at most :data:`TRANSFORMS_JSON_LIMITS` ``max_bytes``); ``bad_json``
    naming the file, the line and the limit on failure."""
    label = rel(path, root)
    try:
        meta = load_file(path, source=label, limits=TRANSFORMS_JSON_LIMITS)
    except JsonInputError as e:
        raise DatasetError(str(e).removeprefix(f"{label}: "), file=label, code="bad_json") from None
    except OSError as e:
        why = e.strerror if e.filename else e  # never the server path
        raise DatasetError(f"cannot read JSON file: {why}", file=label, code="bad_json") from None
    if not isinstance(meta, dict):
        raise DatasetError("the JSON file must hold an object with a 'frames' list", file=label,
                           code="bad_json")
    return meta


def resolve_image(json_dir: Path, file_path: str, root: Path, view: int, json_label: str | None = None
                  ) -> Path:
    """Find a frame's image: the path as given, else with ``.png``/``.jpg``/``.jpeg`` appended.

    Every candidate must resolve inside ``root`` (checked before it is looked up, see
    ``paths.py``): else ``path_outside_dataset`` naming ``json_label``, the frame and
    ``file_path`` as written. Then ``unsupported_image`` for an existing non-PNG/JPEG image,
    ``missing_image`` otherwise; labels are relative to ``root``.
    """
    def candidate(written: str) -> Path:
        return dataset_path(root, written, base=json_dir, file=json_label, view=view)

    p = candidate(file_path)
    if p.is_file():
        if is_image_name(p.name):
            return p
        if looks_like_image(p.name):
            raise DatasetError(f"unsupported image format '{p.suffix}' (use PNG or JPEG)",
                               file=rel(p, root), view=view, code="unsupported_image")
    for ext in SUPPORTED_EXTS + tuple(e.upper() for e in SUPPORTED_EXTS):
        q = candidate(file_path + ext)
        if q.is_file():
            return q
    if looks_like_image(p.name) and not is_image_name(p.name):
        raise DatasetError(f"unsupported image format '{p.suffix}' (use PNG or JPEG)",
                           file=rel(p, root), view=view, code="unsupported_image")
    tried = "" if is_image_name(p.name) else " (also tried .png, .jpg, .jpeg)"
    raise DatasetError(f"image file not found{tried}", file=rel(p, root), view=view, code="missing_image")


def _num(d: dict, key: str, label: str, view: int | None) -> float | None:
    if key not in d:
        return None
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise DatasetError(f"'{key}' must be a number, got {v!r}", file=label, view=view, code="bad_json")
    if not math.isfinite(v):
        raise DatasetError(f"'{key}' is not finite", file=label, view=view, code="nonfinite_camera")
    return float(v)


def _image_size(path: Path, label: str, view: int) -> tuple[int, int]:
    wh = image_size(path)
    # unreadable headers: decode now, so the error carries its code, file and view
    return wh if wh is not None else read_image(path, label=label, view=view).shape[1::-1]


def frame_intrinsics(meta: dict, frame: dict, image: Path, label: str, img_label: str, view: int
                     ) -> tuple[np.ndarray, tuple[int, int] | None, tuple | None]:
    """``(K [3, 3] float64, declared (W, H) or None, distortion (k1, k2, p1, p2, k3[, k4]) or None)``.

    Frame keys override top-level keys; see the module docstring for the formulas. A nerfstudio
    ``camera_model`` is checked (:func:`~nepf_core.data.camera_models.check_nerfstudio_model`).
    """
    def get(key):
        v = _num(frame, key, label, view)
        return v if v is not None else _num(meta, key, label, view)

    model = frame.get("camera_model", meta.get("camera_model"))
    if model is not None:    # nerfstudio: the model is named, and k4 is OPENCV's r^8 term
        check_nerfstudio_model(model, label=label, view=view)
    elif meta.get("is_fisheye") or frame.get("is_fisheye") or get("k4"):
        raise DatasetError("fisheye cameras are not supported (pinhole + OpenCV radial-tangential only)",
                           file=label, view=view, code="unsupported_camera")
    w, h = get("w"), get("h")
    declared = None
    if w is not None and h is not None:
        declared = (int(round(w)), int(round(h)))
        W, H = declared
    else:
        W, H = _image_size(image, img_label, view)
    fx, fy = get("fl_x"), get("fl_y")
    ax, ay = get("camera_angle_x"), get("camera_angle_y")
    if fx is None:
        if ax is None:
            raise DatasetError("no focal length: need 'fl_x' or 'camera_angle_x'", file=label, view=view,
                               code="bad_json")
        if not 0 < ax < math.pi:
            raise DatasetError(f"camera_angle_x = {ax} is not in (0, pi)", file=label, view=view,
                               code="singular_camera")
        fx = 0.5 * W / math.tan(0.5 * ax)
    if fy is None:
        fy = 0.5 * H / math.tan(0.5 * ay) if ay is not None and 0 < ay < math.pi else fx
    cx, cy = get("cx"), get("cy")
    cx = 0.5 * W if cx is None else cx
    cy = 0.5 * H if cy is None else cy
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    check_intrinsics(K, label=label, view=view)
    keys = ("k1", "k2", "p1", "p2", "k3") + (("k4",) if model is not None else ())
    coeffs = tuple((get(k) or 0.0) for k in keys)
    distortion = coeffs if any(c != 0.0 for c in coeffs) else None
    return K, declared, distortion


def parse_transforms(json_path: Path, root: Path) -> list[ViewSpec]:
    """Parse one ``transforms*.json`` into :class:`ViewSpec` s (OpenCV c2w in the JSON's world)."""
    label = rel(json_path, root)
    dataset_path(root, label, file=label)     # the JSON itself may be a link out of the folder
    meta = read_json(json_path, root)
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise DatasetError("missing 'frames' list", file=label, code="bad_json")
    if not frames:
        raise DatasetError("'frames' is empty: the dataset has no views", file=label, code="no_views")
    specs = []
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str):
            raise DatasetError("frame has no 'file_path' string", file=label, view=i, code="bad_json")
        tm = fr.get("transform_matrix")
        try:
            m = np.array(tm, dtype=np.float64)
        except (TypeError, ValueError):
            m = None
        if m is None or m.shape not in ((4, 4), (3, 4)):
            raise DatasetError("'transform_matrix' must be a 4x4 list of numbers", file=label, view=i,
                               code="bad_json")
        c2w = check_c2w(opengl_to_opencv(check_c2w(m, label=label, view=i)), label=label, view=i)
        img = resolve_image(json_path.parent, fr["file_path"], root, i, label)
        img_label = rel(img, root)
        K, declared, dist = frame_intrinsics(meta, fr, img, label, img_label, i)
        mask = frame_mask(json_path.parent, fr, root, i, label)
        specs.append(ViewSpec(image=img, label=img_label, K=K, c2w=c2w, expected_wh=declared,
                              distortion=dist, mask=mask, mask_label=None if mask is None else rel(mask, root)))
    if len({s.mask is None for s in specs}) > 1:
        v = next(i for i, s in enumerate(specs) if s.mask is None)
        raise DatasetError("some frames have a 'mask_path' and others do not", file=label, view=v,
                           code="count_mismatch")
    return specs


def frame_mask(json_dir: Path, frame: dict, root: Path, view: int, label: str) -> Path | None:
    """A frame's ``mask_path`` (nerfstudio: relative to the JSON's folder, white = object), or None.

    It must resolve inside ``root`` (``path_outside_dataset``) and exist (``missing_image``)."""
    mp = frame.get("mask_path")
    if mp is None:
        return None
    if not isinstance(mp, str):
        raise DatasetError("'mask_path' must be a string", file=label, view=view, code="bad_json")
    p = dataset_path(root, mp, base=json_dir, file=label, view=view)
    if not p.is_file():
        raise DatasetError("mask file not found", file=rel(p, root), view=view, code="missing_image")
    return p


def alpha_masks(specs: list[ViewSpec], factor: int) -> np.ndarray | None:
    """Masks ``[N, H/f, W/f]`` bool (``box(m) >= 0.5``) from the mask files (``mask_path``) when the
    frames have them, else from the alpha channels; None if any image lacks both. They are not
    undistorted: the normalisation only needs the hull within its 1.1 margin."""
    out = []
    for i, s in enumerate(specs):
        if s.mask is not None:
            m = mask_from_array(decode_image(s.mask, label=s.mask_label, view=i)).astype(np.float32)
        else:
            a = read_image(s.image, label=s.label, view=i)
            if a.shape[-1] != 4:
                return None
            m = a[..., 3]
        out.append(box_downscale(m, factor) >= 0.5)
    if len({m.shape for m in out}) != 1:
        return None  # size errors are reported by the pixel pass
    return np.stack(out)


def normalization_for_specs(specs: list[ViewSpec], margin: float = 1.1) -> Normalization:
    """Normalisation from a full split at <= :data:`NORM_WORKING_SIZE` px (see module docstring)."""
    W, H = specs[0].expected_wh or _image_size(specs[0].image, specs[0].label, 0)
    f = max(1, math.ceil(max(W, H) / NORM_WORKING_SIZE))
    masks = alpha_masks(specs, f)
    S = np.diag([1.0 / f, 1.0 / f, 1.0])
    Ks = np.stack([S @ s.K for s in specs])
    c2w = np.stack([s.c2w for s in specs])
    return normalization_from_cameras(Ks, c2w, (W // f, H // f), masks, margin=margin)


def load_transforms(root: Path, json_path: Path, *, fmt: str, split: str, downscale: int = 1,
                    max_views: int | None = None, norm_json: Path | None = None,
                    max_side: int | None = None, max_total_pixels: int | None = None) -> Scene:
    """Load one transforms JSON as a :class:`Scene`; the normalisation comes from ``norm_json``
    (default: ``json_path`` itself). Undistorts when the JSON has distortion coefficients.

    ``max_side`` (0/None: full size) is the working resolution (``views.py``);
    ``max_total_pixels`` the decoded-pixel budget of the split (``budget.py``), checked
    from the headers before anything is decoded."""
    root = Path(root)
    specs = parse_transforms(json_path, root)
    views, c2w, norm = read_normalized_views(
        specs, lambda: normalization_for_specs(specs if norm_json is None or norm_json == json_path
                                               else parse_transforms(norm_json, root)),
        max_views=max_views, max_total_pixels=max_total_pixels, downscale=downscale, max_side=max_side)
    extras = {"normalization": norm.method, "transforms": rel(json_path, root),
              "normalization_from": rel(norm_json or json_path, root),
              "undistorted": any(s.distortion is not None for s in views.specs)}
    return scene_from_views(views, c2w, norm.world_from_norm, root=root, source_format=fmt, split=split,
                            extras=extras)


def load_blender(root: Path | str, split: str = "train", *, downscale: int = 1,
                 max_views: int | None = None, max_side: int | None = None,
                 max_total_pixels: int | None = None) -> Scene:
    """Load ``transforms_{split}.json`` of a NeRF-synthetic folder as a :class:`Scene`.

    ``split`` is ``"train"``, ``"test"`` or ``"val"``; the normalisation always comes from
    the train split when it exists (shared frame across splits). ``max_side`` and
    ``max_total_pixels``: see :func:`load_transforms`.
    """
    root = Path(root)
    if split not in SPLITS:
        raise DatasetError(f"unknown split '{split}' (train, test or val)", code="missing_split")
    path = split_file(root, split)
    if not path.is_file():
        raise DatasetError(f"no transforms_{split}.json in the folder", file=path.name,
                           code="missing_split")
    train = split_file(root, "train")
    return load_transforms(root, path, fmt="blender", split=split, downscale=downscale,
                           max_views=max_views, norm_json=train if train.is_file() else path,
                           max_side=max_side, max_total_pixels=max_total_pixels)
