"""Point lights for relighting: the ``lights.json`` format, the change of frame, the canonical set.

File format (that of ``gt/relight/lights.json`` of the synthetic scenes)::

    {"lights": [{"type": "point", "position_world": [x, y, z], "intensity_rgb": [r, g, b]}, ...]}

in the input's world coordinates; ``intensity_rgb`` is radiant intensity, so the irradiance at a
point at distance ``d`` is ``E = I max(cos, 0) / d^2``. Any other key (``position_normalized``,
``units``, ...) is ignored.

Change of frame. With ``x_world = M [x_norm, 1]`` and ``M = [s R | t]`` a similarity of scale
``s``, a light at ``p_w`` sits at ``p_n = M^{-1} [p_w, 1]``, and distances shrink by ``s``:
``d_w = s d_n``. Keeping the irradiance (hence the rendered radiance) unchanged,
``I_w / d_w^2 = I_n / d_n^2``, gives ``I_n = I_w / s^2``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nepf_json import DEFAULT_LIMITS, JsonInputError, load_file
from nepf_core.up_axis import axis_from_vector, axis_vector, gltf_from_world


class LightsError(ValueError):
    """A lights file that cannot be used (the message names the file and the light)."""


@dataclass
class PointLights:
    """``K`` point lights: ``positions [K, 3]`` and radiant ``intensities [K, 3]`` (float64),
    in one frame (world or normalised; the caller knows which)."""

    positions: np.ndarray
    intensities: np.ndarray

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def to_json(self) -> dict:
        """The ``lights.json`` dict of these lights (``position_world`` for world-frame lights)."""
        return {"lights": [{"type": "point", "position_world": [float(c) for c in p],
                            "intensity_rgb": [float(c) for c in i]}
                           for p, i in zip(self.positions, self.intensities)]}


def _vector(value, what: str, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise LightsError(f"{where}: '{what}' must be a list of 3 numbers, got {value!r}") from None
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise LightsError(f"{where}: '{what}' must be a list of 3 finite numbers, got {value!r}")
    return arr


def parse_lights(data, source: str = "lights.json") -> PointLights:
    """Validate a parsed ``lights.json`` (see the module docstring); ``source`` names the file in
    errors. Raises :class:`LightsError` for a missing or empty ``lights`` list, a light that is not
    an object, a ``type`` other than ``"point"``, or a position / intensity that is not 3 finite
    numbers (intensities must also be >= 0)."""
    if not isinstance(data, dict) or not isinstance(data.get("lights"), list):
        raise LightsError(f"{source}: expected an object with a 'lights' list")
    if not data["lights"]:
        raise LightsError(f"{source}: 'lights' is empty")
    pos, inten = [], []
    for k, light in enumerate(data["lights"]):
        where = f"{source}: light {k}"
        if not isinstance(light, dict):
            raise LightsError(f"{where}: expected an object, got {type(light).__name__}")
        if light.get("type") != "point":
            raise LightsError(f"{where}: 'type' must be \"point\", got {light.get('type')!r}")
        for key in ("position_world", "intensity_rgb"):
            if key not in light:
                raise LightsError(f"{where}: missing '{key}'")
        pos.append(_vector(light["position_world"], "position_world", where))
        i = _vector(light["intensity_rgb"], "intensity_rgb", where)
        if (i < 0).any():
            raise LightsError(f"{where}: 'intensity_rgb' must be >= 0, got {light['intensity_rgb']!r}")
        inten.append(i)
    return PointLights(np.stack(pos), np.stack(inten))


#: a lights file holds a few lights: 1 MiB is thousands of them
LIGHTS_JSON_LIMITS = dataclasses.replace(DEFAULT_LIMITS, max_bytes=1024 * 1024)


def load_lights(path) -> PointLights:
    """Read and validate a ``lights.json`` file (world frame). Errors name the file by its name
    only (never a server path)."""
    path = Path(path)
    if not path.is_file():
        raise LightsError(f"{path.name}: no such lights file")
    try:   # the parser every user JSON goes through: bounded nesting, numbers, strings; no duplicate keys
        data = load_file(path, source=path.name, limits=LIGHTS_JSON_LIMITS)
    except JsonInputError as e:
        what = e.reason if e.limit else f"not valid JSON ({e.reason})"
        raise LightsError(f"{path.name}: {what}") from None
    return parse_lights(data, path.name)


def world_scale(world_from_norm: np.ndarray) -> float:
    """Uniform scale ``s = |det M_3x3|^(1/3)`` of a similarity."""
    return float(np.cbrt(abs(np.linalg.det(np.asarray(world_from_norm, np.float64)[:3, :3]))))


def lights_to_normalised(lights: PointLights, world_from_norm: np.ndarray) -> PointLights:
    """World-frame lights in the normalised frame: ``p_n = M^{-1} [p_w, 1]``, ``I_n = I_w / s^2``
    (module docstring), so ``I_n cos / d_n^2 = I_w cos / d_w^2``."""
    M = np.asarray(world_from_norm, np.float64)
    inv = np.linalg.inv(M)
    p = lights.positions @ inv[:3, :3].T + inv[:3, 3]
    return PointLights(p, lights.intensities / world_scale(M) ** 2)


def horizontal_axes(up) -> tuple[np.ndarray, np.ndarray]:
    """The azimuth axes ``(a_x, a_y)`` (world frame) of the web viewer for a world up axis.

    The viewer shows the GLB, whose frame is ``x_glb = R x_world`` (:mod:`nepf_core.up_axis`),
    +Y up, with azimuth measured from +Z towards +X (web/src/viewer3d.js, ``UP_AXES.y``); in the
    world that is ``a_x = R^T e_z``, ``a_y = R^T e_x``: +Z up -> (-y, x), +Y up -> (z, x),
    -Y up -> (z, -x). Any other up vector gets a right-handed orthonormal pair orthogonal to it
    (``a_x x a_y = up`` in every case)."""
    u = np.asarray(up, np.float64)
    u = u / np.linalg.norm(u)
    axis = axis_from_vector(u)
    if axis is not None and np.allclose(u, axis_vector(axis), atol=1e-9):
        r = gltf_from_world(axis)
        return r.T @ np.array([0.0, 0.0, 1.0]), r.T @ np.array([1.0, 0.0, 0.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    ax = helper - u * (helper @ u)
    ax /= np.linalg.norm(ax)
    return ax, np.cross(u, ax)


CANONICAL_AZIMUTHS_DEG = (0.0, 120.0, 240.0)
CANONICAL_ELEVATION_DEG = 45.0
CANONICAL_DISTANCE = 3.0
"""Canonical preview lights: at ``3 R`` from the object's centre (R its radius)."""
CANONICAL_IRRADIANCE = 2.0
"""Irradiance ``I / (3 R)^2`` of each canonical light at the object's centre (radiance units):
a white Lambertian facing the light there renders ``2 / pi ~ 0.64``."""


def canonical_lights(center_world, radius_world: float, up=(0.0, 0.0, 1.0)) -> PointLights:
    """The three preview lights, world frame: at ``c + 3 R (cos(el)(cos(az) a_x + sin(az) a_y)
    + sin(el) u)`` for ``el = 45 deg``, ``az = 0, 120, 240 deg`` (``a_x, a_y`` from
    :func:`horizontal_axes`), white, with ``I = E_0 (3 R)^2`` (``E_0`` =
    :data:`CANONICAL_IRRADIANCE`)."""
    c = np.asarray(center_world, np.float64)
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    ax, ay = horizontal_axes(u)
    el = math.radians(CANONICAL_ELEVATION_DEG)
    dist = CANONICAL_DISTANCE * float(radius_world)
    pos = [c + dist * (math.cos(el) * (math.cos(math.radians(a)) * ax + math.sin(math.radians(a)) * ay)
                       + math.sin(el) * u) for a in CANONICAL_AZIMUTHS_DEG]
    inten = np.full((3, 3), CANONICAL_IRRADIANCE * dist * dist)
    return PointLights(np.stack(pos), inten)
