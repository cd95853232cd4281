"""Write a DTU folder's cameras and images as a COLMAP model or a nerfstudio folder.

For tests and benchmarks: the same cameras in three layouts, so that the loaders can be checked
against each other (``nepf make-scene --formats``, ``tests/test_colmap_nerfstudio.py``), and a
DTU capture can be trained from its COLMAP form. The cameras come from the DTU projection
matrices alone (``world_mat_i = K_cv [R | t]``, decomposed by :func:`~nepf_core.data.dtu.decompose_projection`),
in the world frame (``scale_mat`` is not applied):

* COLMAP: ``R, t`` as the image's pose (``q = rotmat_to_qvec(R)``) and ``K`` with the
  +0.5 pixel-centre shift (``cx = cx_cv + 0.5``: COLMAP's convention, ``camera_models.py``); one
  camera per distinct ``K``. Model PINHOLE, or a distorted model (``distortion=(model, params)``
  with the images distorted to match by :func:`~nepf_core.data.ingp.distort_image`).
* nerfstudio: ``transform_matrix = A c2w diag(1, -1, -1, 1)`` (OpenGL axes) with ``A`` the
  ``applied_transform`` that ``ns-process-data`` uses (y and z swapped, the new z negated) unless
  another is given; ``mask_path`` per frame when the DTU folder has masks; ``sparse_pc.ply``
  (ASCII, the points with ``A`` applied) when points are given.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from nepf_core.data.colmap_io import ColmapCamera, ColmapImage, ColmapModel, rotmat_to_qvec, write_model

#: ``ns-process-data``'s ``applied_transform``: rows (x, z, -y) of COLMAP's world.
NS_APPLIED_TRANSFORM = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0]])


def dtu_cameras(dtu_dir: Path) -> dict:
    """``{"images", "masks", "K" [N,3,3] (pixel centres at +0.5), "c2w" [N,4,4] world OpenCV, "wh"}``."""
    from nepf_core.data.dtu import parse_dtu

    specs, scale, _ = parse_dtu(dtu_dir)
    c2w = np.stack([s.c2w for s in specs])
    if scale is not None:  # parse_dtu gives the normalised frame: back to the world
        from nepf_core.data.normalize import c2w_to_normalized
        c2w = c2w_to_normalized(c2w, np.linalg.inv(scale))
    with Image.open(specs[0].image) as im:
        wh = im.size
    return {"images": [s.image for s in specs], "masks": [s.mask for s in specs],
            "K": np.stack([s.K for s in specs]), "c2w": c2w, "wh": wh}


def _copy_image(src: Path, dst: Path, K: np.ndarray, coeffs: tuple | None) -> None:
    """Copy ``src`` to ``dst``; with ``coeffs``, distort it as a lens with them records it."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if coeffs is None:
        shutil.copyfile(src, dst)
        return
    from nepf_core.color import linear_to_srgb, srgb_to_linear
    from nepf_core.data.images import read_image, to_uint8
    from nepf_core.data.ingp import distort_image

    rgb = srgb_to_linear(np.asarray(read_image(src)[..., :3], dtype=np.float32))
    Image.fromarray(to_uint8(linear_to_srgb(np.asarray(distort_image(rgb, K, coeffs), dtype=np.float32)))).save(dst)


def _colmap_params(model: str, K: np.ndarray, params: tuple) -> tuple[list[float], tuple]:
    """COLMAP parameter list of ``model`` for ``K`` and the distortion ``params`` (as COLMAP orders
    them after the focal lengths and centre), and the OpenCV ``(k1, k2, p1, p2)`` they mean."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    p = [float(v) for v in params]
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        return [fx, cx, cy, *p], tuple(p)   # k, or k1, k2: OpenCV's k1, k2 (camera_models.py)
    return [fx, fy, cx, cy, *p], tuple(p)


def write_colmap(dtu_dir: Path, out: Path, *, binary: bool = True, points: np.ndarray | None = None,
                 distortion: tuple[str, tuple] = ("PINHOLE", ()), sparse: str = "sparse/0") -> Path:
    """``out/images/`` + ``out/<sparse>/`` from a DTU folder (module docstring); returns ``out``.

    ``points`` ``[P, 3]`` world positions for ``points3D``; ``distortion`` ``(model, params)``,
    e.g. ``("OPENCV", (k1, k2, p1, p2))`` (SIMPLE_PINHOLE's fx must equal fy)."""
    out = Path(out)
    cams = dtu_cameras(Path(dtu_dir))
    w, h = cams["wh"]
    model, dparams = distortion
    cameras, images, key_to_id = {}, {}, {}
    for i, (src, K, c2w) in enumerate(zip(cams["images"], cams["K"], cams["c2w"])):
        key = K.round(6).tobytes()
        if key not in key_to_id:
            key_to_id[key] = len(key_to_id) + 1
            params, _ = _colmap_params(model, K, dparams)
            cameras[key_to_id[key]] = ColmapCamera(key_to_id[key], model, w, h, params)
        coeffs = _colmap_params(model, K, dparams)[1]
        name = f"frame_{i:05d}{Path(src).suffix}"
        _copy_image(Path(src), out / "images" / name, K, coeffs if any(coeffs) else None)
        w2c = np.linalg.inv(c2w)
        images[i + 1] = ColmapImage(i + 1, rotmat_to_qvec(w2c[:3, :3]), w2c[:3, 3], key_to_id[key], name)
    write_model(out / sparse, ColmapModel(cameras, images, points=points), binary=binary)
    return out


def write_ply_points(path: Path, points: np.ndarray) -> None:
    """ASCII PLY of points ``[P, 3]`` with grey colour, as ``ns-process-data``'s ``sparse_pc.ply``."""
    head = ("ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\nproperty float z\n"
            "property uint8 red\nproperty uint8 green\nproperty uint8 blue\nend_header\n" % len(points))
    path.write_text(head + "".join(f"{x:.8f} {y:.8f} {z:.8f} 128 128 128\n" for x, y, z in points))


def write_nerfstudio(dtu_dir: Path, out: Path, *, points: np.ndarray | None = None,
                     applied: np.ndarray | None = NS_APPLIED_TRANSFORM, masks: bool = True,
                     distortion: tuple | None = None) -> Path:
    """``out/transforms.json`` + ``images/`` (+ ``masks/``, ``sparse_pc.ply``) from a DTU folder.

    ``applied`` (3x4, or None: poses in the world as they are, no ``applied_transform`` key);
    ``distortion`` ``(k1, k2, p1, p2)`` writes ``camera_model: OPENCV`` and distorted images
    (else PINHOLE). Intrinsics are per frame when the views' ``K`` differ."""
    out = Path(out)
    cams = dtu_cameras(Path(dtu_dir))
    w, h = cams["wh"]
    A = np.eye(4)
    if applied is not None:
        A[:3] = np.asarray(applied, np.float64)[:3]
    gl = np.diag([1.0, -1.0, -1.0, 1.0])
    per_frame = not np.allclose(cams["K"], cams["K"][0])
    coeffs = tuple(distortion) if distortion is not None else None

    def intr(K):
        d = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
        return {k: float(v) for k, v in d.items()}

    frames = []
    for i, (src, K, c2w, m) in enumerate(zip(cams["images"], cams["K"], cams["c2w"], cams["masks"])):
        name = f"images/frame_{i + 1:05d}{Path(src).suffix}"
        _copy_image(Path(src), out / name, K, coeffs)
        fr = {"file_path": name, "transform_matrix": (A @ c2w @ gl).tolist(), "colmap_im_id": i + 1}
        if masks and m is not None:
            mask = np.array(Image.open(m).convert("L"))
            if coeffs is not None:   # the mask follows the lens too
                from nepf_core.data.ingp import distort_image
                mask = np.round(distort_image(mask[..., None] / 255.0, K, coeffs)[..., 0] * 255)
            (out / "masks").mkdir(parents=True, exist_ok=True)
            Image.fromarray(mask.astype(np.uint8)).save(out / f"masks/frame_{i + 1:05d}.png")
            fr["mask_path"] = f"masks/frame_{i + 1:05d}.png"
        if per_frame:
            fr.update(intr(K))
        frames.append(fr)
    meta = {"w": w, "h": h, "camera_model": "OPENCV" if coeffs else "PINHOLE"}
    if not per_frame:
        meta.update(intr(cams["K"][0]))
    if coeffs:
        meta.update({k: float(v) for k, v in zip(("k1", "k2", "p1", "p2"), coeffs)})
    meta["frames"] = frames
    if applied is not None:
        meta["applied_transform"] = A[:3].tolist()
    if points is not None:
        write_ply_points(out / "sparse_pc.ply", np.asarray(points, np.float64) @ A[:3, :3].T + A[:3, 3])
        meta["ply_file_path"] = "sparse_pc.ply"
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    return out


#: Layouts :func:`write_formats` can add beside a synthetic scene's ``dtu/`` (folder = name).
EXTRA_FORMATS = ("colmap", "colmap_txt", "nerfstudio")


def write_formats(scene_dir: Path, formats, max_points: int = 4000) -> None:
    """Write ``scene_dir/dtu`` again as each of ``formats`` (:data:`EXTRA_FORMATS`) beside it, with
    up to ``max_points`` vertices of ``gt/mesh.ply`` (evenly strided) as the sparse points."""
    scene_dir = Path(scene_dir)
    unknown = set(formats) - set(EXTRA_FORMATS)
    if unknown:
        raise ValueError(f"unknown formats {sorted(unknown)} (one of {EXTRA_FORMATS})")
    points = None
    mesh = scene_dir / "gt" / "mesh.ply"
    if mesh.is_file():
        from nepf_core.data.nerfstudio import read_ply_points
        v = read_ply_points(mesh, scene_dir)
        points = v[:: max(1, len(v) // max_points)]
    for fmt in formats:
        if fmt == "nerfstudio":
            write_nerfstudio(scene_dir / "dtu", scene_dir / fmt, points=points)
        else:
            write_colmap(scene_dir / "dtu", scene_dir / fmt, binary=fmt == "colmap", points=points)


def main(argv: list[str] | None = None) -> int:
    """``python -m nepf_core.data.convert DTU_DIR OUT --to colmap|colmap_txt|nerfstudio [--points PLY]``:
    a DTU folder (e.g. a shared scene's ``input/dtu``) as another layout, for round trips."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m nepf_core.data.convert", description=main.__doc__.split("\n")[0])
    ap.add_argument("dtu_dir")
    ap.add_argument("out")
    ap.add_argument("--to", choices=EXTRA_FORMATS, required=True)
    ap.add_argument("--points", help="PLY whose vertices (world) become the sparse points")
    a = ap.parse_args(argv)
    points = None
    if a.points:
        from nepf_core.data.nerfstudio import read_ply_points
        points = read_ply_points(Path(a.points), Path(a.points).parent)
    if a.to == "nerfstudio":
        write_nerfstudio(Path(a.dtu_dir), Path(a.out), points=points)
    else:
        write_colmap(Path(a.dtu_dir), Path(a.out), binary=a.to == "colmap", points=points)
    print(Path(a.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
