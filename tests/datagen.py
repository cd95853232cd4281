"""Test data made on the fly (no ../shared): cached synthetic scenes and small helpers.

``synth_dir(**kw)`` renders a scene once per test session (keyed by its arguments) into a
temporary folder removed at exit; tests copy it before corrupting anything.
"""

from __future__ import annotations

import atexit
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

_CACHE: dict = {}
_TMP = Path(tempfile.mkdtemp(prefix="nepf_datagen_"))
atexit.register(shutil.rmtree, _TMP, ignore_errors=True)

#: Small and fast: 8 train + 2 test views at 40x32 (non-square on purpose).
SMALL = dict(shape="torus", material="textured", n_views=8, n_test=2, resolution=(40, 32),
             supersample=1, write_mesh=True)


def synth_dir(**kw) -> Path:
    """Folder of a rendered synthetic scene (``make_scene`` arguments, :data:`SMALL` defaults)."""
    from nepf_core.data.synth import make_scene

    args = {**SMALL, **kw}
    key = json.dumps(args, sort_keys=True, default=str)
    if key not in _CACHE:
        out = _TMP / f"scene_{len(_CACHE)}"
        make_scene(out, **args)
        _CACHE[key] = out
    return _CACHE[key]


def copy_scene(tmp_path: Path, **kw) -> Path:
    """A private, writable copy of :func:`synth_dir` under ``tmp_path``."""
    dst = tmp_path / "scene"
    shutil.copytree(synth_dir(**kw), dst)
    return dst


def gt_scene(folder: Path) -> dict:
    """The ``gt/scene.json`` of a synthetic scene."""
    return json.loads((Path(folder) / "gt" / "scene.json").read_text())


def srgb_decode(v: np.ndarray) -> np.ndarray:
    """Reference sRGB EOTF written out independently of ``nepf_core`` (IEC 61966-2-1)."""
    v = np.asarray(v, np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def project_opencv(K: np.ndarray, w2c: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``[P, 2]`` of world points ``[P, 3]`` with OpenCV ``K`` (centres at integers)."""
    cam = X @ w2c[:3, :3].T + w2c[:3, 3]
    uvw = cam @ K.T
    return uvw[:, :2] / uvw[:, 2:3]


def project_scene(scene, i: int, X_norm: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``[P, 2]`` of normalised points in view ``i`` of a ``Scene``
    (Scene convention: pixel centres at +0.5)."""
    c2w = scene.c2w[i].astype(np.float64)
    cam = (X_norm - c2w[:3, 3]) @ c2w[:3, :3]
    uvw = cam @ scene.intrinsics[i].astype(np.float64).T
    return uvw[:, :2] / uvw[:, 2:3]


def to_norm(scene, X_world: np.ndarray) -> np.ndarray:
    """World points ``[P, 3]`` -> the scene's normalised frame."""
    A = np.linalg.inv(scene.world_from_norm)
    return X_world @ A[:3, :3].T + A[:3, 3]


def read_ply_vertices(path: Path) -> np.ndarray:
    """Vertices ``[V, 3]`` of a PLY mesh."""
    import trimesh

    return np.asarray(trimesh.load(path, process=False).vertices, np.float64)


def random_object_points(folder: Path, n: int = 200, seed: int = 0) -> np.ndarray:
    """World points inside the object's bounding ball (from ``scene.json``)."""
    sc = gt_scene(folder)
    c = np.asarray(sc["object"]["center_world"])
    r = sc["object"]["bounding_radius_world"]
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return c + r * p * rng.uniform(0, 1, (n, 1)) ** (1 / 3)
