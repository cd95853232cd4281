"""COLMAP sparse models: read and write ``cameras``, ``images``, ``points3D`` (``.bin`` or ``.txt``).

Why our own reader and not ``pycolmap.Reconstruction``: pycolmap bundles COLMAP itself (a
large native wheel tied to one CPU architecture and Python version) while we need three small,
documented record layouts; this subpackage must also stay light and torch-free, because the
service validates uploads with it in a subprocess. The reader is bounded: every count is checked
against the bytes left before anything is allocated, so a truncated or hostile file is a
``DatasetError`` naming it, never a ``MemoryError`` or a traceback. The writer exists for the tests
and the converters (a synthetic scene written as a COLMAP model).

Formats (colmap.github.io/format.html; little-endian binary, ``#`` comments in text):
    cameras:  ``camera_id model width height params[]``;
              binary ``u64 n`` then per camera ``i32 id, i32 model_id, u64 width, u64 height,
              f64 params[n_params(model)]``.
    images:   ``image_id qw qx qy qz tx ty tz camera_id name`` then one line of ``x y point3D_id``
              triples (possibly empty); binary ``u64 n`` then ``i32 id, f64 q[4], f64 t[3],
              i32 camera_id, name\\0, u64 n2d, (f64 x, f64 y, i64 point3D_id)[n2d]``.
              The pose is world-to-camera, ``x_cam = R(q) x_world + t``, OpenCV camera axes
              (x right, y down, z forward), ``q = (w, x, y, z)`` a unit quaternion.
    points3D: ``point3D_id x y z r g b error (image_id point2D_idx)[]``; binary ``u64 n`` then
              ``u64 id, f64 xyz[3], u8 rgb[3], f64 error, u64 track_length, (i32, i32)[track_length]``.

Quaternion to rotation (Hamilton, scalar first):
    ``R = [[1 - 2(y^2 + z^2), 2(xy - wz), 2(xz + wy)], [2(xy + wz), 1 - 2(x^2 + z^2), 2(yz - wx)],
    [2(xz - wy), 2(yz + wx), 1 - 2(x^2 + y^2)]]`` (after normalising ``q``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nepf_core.data.camera_models import COLMAP_MODEL_IDS, COLMAP_MODELS, colmap_params_count
from nepf_core.data.errors import DatasetError
from nepf_core.data.paths import dataset_path, rel

FILES = ("cameras", "images", "points3D")


@dataclass
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: list[float]


@dataclass
class ColmapImage:
    id: int
    qvec: np.ndarray
    """``[4]`` (w, x, y, z), world-to-camera rotation."""
    tvec: np.ndarray
    """``[3]`` world-to-camera translation."""
    camera_id: int
    name: str


@dataclass
class ColmapModel:
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points: np.ndarray | None = None
    """``[P, 3]`` float64 world positions (None: no points3D file)."""
    colors: np.ndarray | None = None
    errors: np.ndarray | None = None
    """``[P]`` mean reprojection error in pixels."""
    ext: str = ".bin"


def qvec_to_rotmat(q) -> np.ndarray:
    """``[4]`` (w, x, y, z) -> ``[3, 3]`` rotation (module docstring); ``q`` is normalised first."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def rotmat_to_qvec(R) -> np.ndarray:
    """Inverse of :func:`qvec_to_rotmat` (w >= 0): the eigenvector of the largest eigenvalue of
    the symmetric 4x4 matrix of Bar-Itzhack's method (robust for any rotation)."""
    (a, b, c), (d, e, f), (g, h, i) = np.asarray(R, np.float64)
    Kq = np.array([[a - e - i, d + b, g + c, h - f], [d + b, e - a - i, h + f, c - g],
                   [g + c, h + f, i - a - e, d - b], [h - f, c - g, d - b, a + e + i]]) / 3.0
    vals, vecs = np.linalg.eigh(Kq)
    x, y, z, w = vecs[:, np.argmax(vals)]
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


class _Bytes:
    """Bounded little-endian reader over a file's bytes (errors name the file)."""

    def __init__(self, data: bytes, label: str):
        self.data, self.pos, self.label = data, 0, label

    def fail(self, what: str):
        raise DatasetError(f"malformed COLMAP binary file: {what} at byte {self.pos}", file=self.label,
                           code="unreadable_cameras")

    def take(self, fmt: str) -> tuple:
        n = struct.calcsize("<" + fmt)
        if self.pos + n > len(self.data):
            self.fail("file ends early")
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += n
        return out

    def count(self, min_record: int) -> int:
        (n,) = self.take("Q")
        if n * min_record > len(self.data) - self.pos:
            self.fail(f"{n} records do not fit in the file")
        return n

    def name(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            self.fail("image name has no terminating NUL")
        raw, self.pos = self.data[self.pos:end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            self.fail("image name is not UTF-8")

    def skip(self, n: int):
        if n < 0 or self.pos + n > len(self.data):
            self.fail("file ends early")
        self.pos += n


def _inside(path: Path, root: Path) -> Path:
    """``path`` once it resolves inside ``root`` (a model file may be a link out of the folder)."""
    label = rel(path, root)
    return dataset_path(root, label, file=label)


def _read_bytes(path: Path, root: Path) -> _Bytes:
    path = _inside(path, root)
    try:
        return _Bytes(path.read_bytes(), rel(path, root))
    except OSError as e:
        raise DatasetError(f"cannot read COLMAP file: {e.strerror}", file=rel(path, root),
                           code="unreadable_cameras") from None


def _cameras_bin(b: _Bytes) -> dict[int, ColmapCamera]:
    out = {}
    for _ in range(b.count(24)):
        cid, mid, w, h = b.take("iiQQ")
        if mid not in COLMAP_MODELS:
            b.fail(f"unknown camera model id {mid} (camera {cid}; known ids 0-{max(COLMAP_MODELS)})")
        name, n = COLMAP_MODELS[mid]
        out[cid] = ColmapCamera(cid, name, int(w), int(h), list(b.take("d" * n)))
    return out


def _images_bin(b: _Bytes) -> dict[int, ColmapImage]:
    out = {}
    for _ in range(b.count(73)):
        iid, qw, qx, qy, qz, tx, ty, tz, cid = b.take("i7di")
        name = b.name()
        (n2d,) = b.take("Q")
        b.skip(24 * n2d)
        out[iid] = ColmapImage(iid, np.array([qw, qx, qy, qz]), np.array([tx, ty, tz]), cid, name)
    return out


def _points_bin(b: _Bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = b.count(51)
    xyz, rgb, err = np.empty((n, 3)), np.empty((n, 3), np.uint8), np.empty(n)
    for k in range(n):
        _, x, y, z, r, g, bl, e, track = b.take("QdddBBBdQ")
        b.skip(8 * track)
        xyz[k], rgb[k], err[k] = (x, y, z), (r, g, bl), e
    return xyz, rgb, err


def _text_lines(path: Path, root: Path) -> list[str]:
    path = _inside(path, root)
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        why = e.strerror if isinstance(e, OSError) else "not UTF-8 text"
        raise DatasetError(f"cannot read COLMAP file: {why}", file=rel(path, root),
                           code="unreadable_cameras") from None


def _bad_line(label: str, k: int, what: str):
    raise DatasetError(f"line {k + 1}: {what}", file=label, code="unreadable_cameras")


def _cameras_txt(lines: list[str], label: str) -> dict[int, ColmapCamera]:
    out = {}
    for k, line in enumerate(lines):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        e = line.split()
        try:
            cid, model, w, h, params = int(e[0]), e[1], int(e[2]), int(e[3]), [float(v) for v in e[4:]]
        except (IndexError, ValueError):
            _bad_line(label, k, "expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]'")
        out[cid] = ColmapCamera(cid, model, w, h, params)
    return out


def _images_txt(lines: list[str], label: str) -> dict[int, ColmapImage]:
    """Two lines per image; the second (its 2D points) may be empty, so it is consumed as is."""
    out, k = {}, 0
    while k < len(lines):
        line = lines[k]
        k += 1
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        e = line.strip().split(None, 9)
        try:
            iid, q, t, cid = int(e[0]), [float(v) for v in e[1:5]], [float(v) for v in e[5:8]], int(e[8])
            name = e[9]
        except (IndexError, ValueError):
            _bad_line(label, k - 1, "expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'")
        out[iid] = ColmapImage(iid, np.array(q), np.array(t), cid, name)
        k += 1  # the POINTS2D line
    return out


def _points_txt(lines: list[str], label: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xyz, rgb, err = [], [], []
    for k, line in enumerate(lines):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        e = line.split()
        try:
            xyz.append([float(v) for v in e[1:4]])
            rgb.append([int(v) for v in e[4:7]])
            err.append(float(e[7]))
        except (IndexError, ValueError):
            _bad_line(label, k, "expected 'POINT3D_ID X Y Z R G B ERROR TRACK[]'")
    return (np.array(xyz, np.float64).reshape(-1, 3), np.array(rgb, np.uint8).reshape(-1, 3),
            np.array(err, np.float64))


def model_ext(folder: Path) -> str | None:
    """``".bin"`` or ``".txt"`` when ``folder`` holds ``cameras`` and ``images`` in that form (binary first)."""
    for ext in (".bin", ".txt"):
        if (folder / f"cameras{ext}").is_file() and (folder / f"images{ext}").is_file():
            return ext
    return None


def read_model(folder: Path, root: Path) -> ColmapModel:
    """Read a sparse model folder (``.bin`` preferred over ``.txt``); ``points3D`` is optional."""
    folder, root = Path(folder), Path(root)
    ext = model_ext(folder)
    if ext is None:
        raise DatasetError("no cameras.bin + images.bin (or .txt) in the COLMAP model folder",
                           file=rel(folder, root), code="unknown_layout")
    pts = folder / f"points3D{ext}"
    if ext == ".bin":
        cams = _cameras_bin(_read_bytes(folder / "cameras.bin", root))
        imgs = _images_bin(_read_bytes(folder / "images.bin", root))
        points = _points_bin(_read_bytes(pts, root)) if pts.is_file() else None
    else:
        lab = lambda n: rel(folder / n, root)  # noqa: E731
        cams = _cameras_txt(_text_lines(folder / "cameras.txt", root), lab("cameras.txt"))
        imgs = _images_txt(_text_lines(folder / "images.txt", root), lab("images.txt"))
        points = _points_txt(_text_lines(pts, root), lab("points3D.txt")) if pts.is_file() else None
    model = ColmapModel(cams, imgs, ext=ext)
    if points is not None:
        model.points, model.colors, model.errors = points
    return model


def write_model(folder: Path, model: ColmapModel, binary: bool = True) -> None:
    """Write ``model`` as ``cameras``, ``images``, ``points3D`` (``.bin`` or ``.txt``), with no 2D
    points per image and empty tracks (what the loader reads is complete)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    pts = np.zeros((0, 3)) if model.points is None else np.asarray(model.points, np.float64)
    rgb = np.full((len(pts), 3), 128, np.uint8) if model.colors is None else np.asarray(model.colors, np.uint8)
    err = np.zeros(len(pts)) if model.errors is None else np.asarray(model.errors, np.float64)
    cams, imgs = sorted(model.cameras.values(), key=lambda c: c.id), sorted(model.images.values(), key=lambda i: i.id)
    if binary:
        b = [struct.pack("<Q", len(cams))]
        for c in cams:
            assert len(c.params) == colmap_params_count(c.model)
            b.append(struct.pack(f"<iiQQ{len(c.params)}d", c.id, COLMAP_MODEL_IDS[c.model], c.width, c.height,
                                 *c.params))
        (folder / "cameras.bin").write_bytes(b"".join(b))
        b = [struct.pack("<Q", len(imgs))]
        for i in imgs:
            b.append(struct.pack("<i7di", i.id, *i.qvec, *i.tvec, i.camera_id) + i.name.encode() + b"\0"
                     + struct.pack("<Q", 0))
        (folder / "images.bin").write_bytes(b"".join(b))
        b = [struct.pack("<Q", len(pts))]
        for k in range(len(pts)):
            b.append(struct.pack("<QdddBBBdQ", k + 1, *pts[k], *rgb[k], err[k], 0))
        (folder / "points3D.bin").write_bytes(b"".join(b))
        return
    (folder / "cameras.txt").write_text("# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "".join(
        f"{c.id} {c.model} {c.width} {c.height} {' '.join(repr(float(p)) for p in c.params)}\n" for c in cams))
    (folder / "images.txt").write_text("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME / POINTS2D[]\n"
                                       + "".join(f"{i.id} {' '.join(repr(float(v)) for v in (*i.qvec, *i.tvec))} "
                                                 f"{i.camera_id} {i.name}\n\n" for i in imgs))
    (folder / "points3D.txt").write_text("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n" + "".join(
        f"{k + 1} {' '.join(repr(float(v)) for v in pts[k])} {' '.join(str(int(v)) for v in rgb[k])} "
        f"{float(err[k])!r}\n" for k in range(len(pts))))
