"""The input world's up axis and the rotation into glTF's +Y-up frame (numpy only, torch-free).

glTF 2.0 is +Y up, right-handed (specification §3.4); our inputs are not (the synthetic and
Blender scenes are +Z up, DTU is roughly -Y up). The export writes the asset, ``lights.json``
and ``light_field.json`` in the **GLB frame** ``x_glb = R x_world`` with ``R`` a proper
rotation (``det R = +1``: no mirroring, so triangle windings and normals stay consistent)
that takes the world's up axis to +Y. One rotation per axis, chosen so that a +Z-up world
gets Blender's own convention (Blender's glTF exporter writes ``(x, z, -y)``; its importer
undoes it, so the asset lands in Blender at the input's world coordinates)::

    world up   R (rows)                         x_glb
    +y         identity                         ( x,  y,  z)
    -y         180 deg about Z                  (-x, -y,  z)
    +z         -90 deg about X                  ( x,  z, -y)
    -z         +90 deg about X                  ( x, -z,  y)
    +x         +90 deg about Z                  (-y,  x,  z)
    -x         -90 deg about Z                  ( y, -x,  z)

Detection (nerfstudio's auto-orientation, ``camera_utils.auto_orient_and_center_poses``): the
world up is the mean of the cameras' up vectors. Our cameras are OpenCV (x right, y down,
z forward), so a camera's up is ``-c2w[:3, 1]``; the mean is snapped to the nearest signed
axis (largest ``|component|``). Cameras that disagree (a mean shorter than
:data:`MIN_MEAN_UP`, e.g. views from all around a sphere) give no answer and the default
:data:`DEFAULT_UP` (+z) is used, recorded as such.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["UP_AXES", "UP_CHOICES", "DEFAULT_UP", "MIN_MEAN_UP", "parse_up_axis", "axis_vector",
           "axis_from_vector", "camera_up_world", "gltf_from_world", "UpFrame", "resolve_up_frame"]

UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
"""The signed axes an up axis may be (``--up``, the job config's ``up_axis``)."""
UP_CHOICES = ("auto",) + UP_AXES
"""``auto``: detect from the cameras."""
DEFAULT_UP = "+z"
"""Up axis when the cameras give none (the project's synthetic scenes are +Z up)."""
MIN_MEAN_UP = 0.05
"""A mean camera-up vector shorter than this says the cameras disagree on up: no detection."""

_ROTATIONS = {
    "+y": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "-y": ((-1, 0, 0), (0, -1, 0), (0, 0, 1)),
    "+z": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "-z": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
    "+x": ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
    "-x": ((0, 1, 0), (-1, 0, 0), (0, 0, 1)),
}


def parse_up_axis(value) -> str | None:
    """``"+x" | "-x" | ... | "-z"`` for a user's up axis (case and a missing ``+`` forgiven:
    ``"Z"`` is ``"+z"``), None for ``"auto"`` / None / ``""``. Raises ``ValueError`` naming the
    choices otherwise."""
    if value is None:
        return None
    s = str(value).strip().lower()
    if s in ("", "auto"):
        return None
    if len(s) == 1:
        s = "+" + s
    if s not in UP_AXES:
        raise ValueError(f"up axis must be one of {', '.join(UP_CHOICES)} (got {value!r})")
    return s


def axis_vector(axis: str) -> np.ndarray:
    """The unit vector ``[3]`` of a signed axis (``"-y"`` -> ``(0, -1, 0)``)."""
    a = parse_up_axis(axis)
    if a is None:
        raise ValueError("axis_vector needs a signed axis, not 'auto'")
    v = np.zeros(3)
    v["xyz".index(a[1])] = 1.0 if a[0] == "+" else -1.0
    return v


def axis_from_vector(v, min_norm: float = MIN_MEAN_UP) -> str | None:
    """The signed axis nearest to ``v`` (its largest ``|component|``), or None when
    ``|v| < min_norm``."""
    v = np.asarray(v, np.float64).reshape(3)
    if not np.all(np.isfinite(v)) or np.linalg.norm(v) < min_norm:
        return None
    i = int(np.argmax(np.abs(v)))
    return ("+" if v[i] > 0 else "-") + "xyz"[i]


def camera_up_world(c2w: np.ndarray, world_from_norm: np.ndarray | None = None) -> np.ndarray:
    """The mean up vector ``[3]`` of OpenCV cameras, in the input's world frame (not normalised).

    ``up_k = -c2w_k[:3, 1]`` (image y points down); with ``world_from_norm = [s Q | t]`` the
    cameras' ``c2w`` are in the normalised frame and ``up_world = Q mean_k(up_k)``.
    """
    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    up = -c2w[:, :3, 1].mean(axis=0)
    if world_from_norm is not None:
        a = np.asarray(world_from_norm, np.float64)[:3, :3]
        up = a @ up / np.cbrt(abs(np.linalg.det(a)))
    return up


def gltf_from_world(axis: str) -> np.ndarray:
    """``R [3,3]``: the proper rotation of the module's table, ``R @ axis_vector(axis) = +Y``."""
    a = parse_up_axis(axis)
    if a is None:
        raise ValueError("gltf_from_world needs a signed axis, not 'auto'")
    return np.asarray(_ROTATIONS[a], np.float64)


@dataclass(frozen=True)
class UpFrame:
    """The world's up axis and how it was chosen.

    Attributes:
        world_up: signed axis of the input world that is up (``"+z"``...).
        source: ``"override"`` (the user's ``--up`` / ``up_axis``), ``"cameras"`` (detected), or
            ``"default"`` (no cameras, or cameras that disagree).
        camera_up_mean: the cameras' mean up vector in world coordinates, when known.
    """

    world_up: str = DEFAULT_UP
    source: str = "default"
    camera_up_mean: tuple[float, float, float] | None = None

    @property
    def rotation(self) -> np.ndarray:
        """``gltf_from_world`` ``[3,3]``."""
        return gltf_from_world(self.world_up)

    @property
    def up_vector(self) -> np.ndarray:
        """The world up as a unit vector (turntable and relit previews orbit about it)."""
        return axis_vector(self.world_up)

    def to_json(self) -> dict:
        """The record written to ``RUN/frame.json`` and the manifest's ``frame``."""
        r = self.rotation
        return {
            "world_up": self.world_up, "up_source": self.source,
            "camera_up_mean": None if self.camera_up_mean is None else [round(float(c), 6) for c in self.camera_up_mean],
            "glb_up": "+y", "gltf_from_world": r.astype(int).tolist(),
            "convention": "x_glb = gltf_from_world @ x_world; a proper rotation (det +1), no scale or "
                          "translation; x_world = transpose(gltf_from_world) @ x_glb",
            "frames": {"asset.glb": "glb", "lights.json": "glb (its 'world' entry: input world)",
                       "light_field.json": "glb", "mesh.ply": "world",
                       "previews/relit_canonical.json": "world"},
        }


def resolve_up_frame(override=None, camera_up=None) -> UpFrame:
    """The :class:`UpFrame` of an export: the user's axis when given (``override``, anything
    :func:`parse_up_axis` reads; ``"auto"``/None: none), else the axis nearest the cameras' mean
    up ``camera_up`` (``[3]`` world, :func:`camera_up_world`), else :data:`DEFAULT_UP`."""
    mean = None if camera_up is None else tuple(float(c) for c in np.asarray(camera_up, np.float64).reshape(3))
    axis = parse_up_axis(override)
    if axis is not None:
        return UpFrame(axis, "override", mean)
    detected = None if mean is None else axis_from_vector(mean)
    if detected is not None:
        return UpFrame(detected, "cameras", mean)
    return UpFrame(DEFAULT_UP, "default", mean)
