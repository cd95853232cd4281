"""Camera models of COLMAP and nerfstudio: which we load (pinhole plus OpenCV distortion), which we refuse.

``Scene`` cameras are pinhole (``views.py`` undoes lens distortion while reading), so a model is
accepted when its projection is a pinhole followed by OpenCV's radial-tangential distortion on
normalised coordinates ``x = (u - cx) / fx`` (``ingp.py`` holds the formula and the remap):

    ``r^2 = x^2 + y^2``, ``g = 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8``
    ``x_d = x g + 2 p1 x y + p2 (r^2 + 2 x^2)``,  ``y_d = y g + p1 (r^2 + 2 y^2) + 2 p2 x y``

COLMAP's parameters (``src/colmap/sensor/models.h``, documented at colmap.github.io/cameras.html):

    ============== ==  ================================  ============================
    model          id  params                            distortion (k1, k2, p1, p2)
    ============== ==  ================================  ============================
    SIMPLE_PINHOLE  0  f, cx, cy                         none
    PINHOLE         1  fx, fy, cx, cy                    none
    SIMPLE_RADIAL   2  f, cx, cy, k                      (k, 0, 0, 0)
    RADIAL          3  f, cx, cy, k1, k2                 (k1, k2, 0, 0)
    OPENCV          4  fx, fy, cx, cy, k1, k2, p1, p2    (k1, k2, p1, p2)
    ============== ==  ================================  ============================

COLMAP's distortion functions are exactly the polynomial above with the missing terms at zero
(``du = u radial + 2 p1 u v + p2 (r^2 + 2 u^2)``, ``radial = k1 r^2 + k2 r^4``). Refused:
FULL_OPENCV (a rational radial term, ``(1 + k1 r^2 ...) / (1 + k4 r^2 ...)``), the fisheye models
(an angle ``theta = atan(r)`` in place of ``r``: OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE,
RADIAL_FISHEYE, THIN_PRISM_FISHEYE, RAD_TAN_THIN_PRISM_FISHEYE) and FOV. The refusal names the
model and the command that makes a pinhole model of the same capture
(``colmap image_undistorter``), whose output (``images/`` + ``sparse/``) loads directly.

Pixel centres: COLMAP puts the centre of pixel (0, 0) at (0.5, 0.5) (a centred camera has
``cx = W / 2``, e.g. ``1 SIMPLE_PINHOLE 3072 2304 2559.81 1536 1152`` in COLMAP's own example),
which is ``Scene``'s convention: ``K`` is taken as written.

nerfstudio's ``camera_model`` (``process_data_utils.CameraModel``): ``PINHOLE``, ``SIMPLE_PINHOLE``,
``OPENCV`` (``k1..k4`` radial as above, ``p1, p2``; nerfstudio's perspective undistortion uses
``k4`` as the ``r^8`` term) are loaded; ``OPENCV_FISHEYE`` and ``EQUIRECTANGULAR`` are refused.
"""

from __future__ import annotations

import numpy as np

from nepf_core.data.errors import DatasetError

#: COLMAP model id -> (name, number of parameters); ids 0..11 of COLMAP 3.x.
COLMAP_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
COLMAP_MODEL_IDS = {name: i for i, (name, _) in COLMAP_MODELS.items()}
#: The COLMAP models we load.
COLMAP_SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
#: The nerfstudio ``camera_model`` values we load.
NERFSTUDIO_SUPPORTED = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
UNDISTORT_HINT = ("make a pinhole model of the same capture with `colmap image_undistorter --image_path "
                  "images --input_path sparse/0 --output_path undistorted` and load `undistorted/`")


def colmap_params_count(model: str) -> int | None:
    """Number of parameters of a COLMAP model name, or None for a name we do not know."""
    i = COLMAP_MODEL_IDS.get(model)
    return None if i is None else COLMAP_MODELS[i][1]


def colmap_intrinsics(model: str, params, *, label: str | None = None, view: int | None = None
                      ) -> tuple[np.ndarray, tuple | None]:
    """``(K [3, 3] float64, distortion (k1, k2, p1, p2) or None)`` of a COLMAP camera (table above).

    ``K`` is in ``Scene``'s convention as written (pixel centres at +0.5, module docstring).
    Raises ``unsupported_camera`` naming the model (and the undistorter) for every other model,
    ``invalid_camera`` when the parameter count does not match the model.
    """
    if model not in COLMAP_SUPPORTED:
        kind = "a fisheye model" if "FISHEYE" in model else (
            "a rational distortion model" if model == "FULL_OPENCV" else
            "not a pinhole model" if model in COLMAP_MODEL_IDS else "an unknown model")
        raise DatasetError(
            f"COLMAP camera model {model} ({kind}) is not supported: the models loaded are "
            f"{', '.join(COLMAP_SUPPORTED)}; {UNDISTORT_HINT}", file=label, view=view, code="unsupported_camera")
    p = [float(v) for v in params]
    if len(p) != colmap_params_count(model):
        raise DatasetError(f"COLMAP camera model {model} takes {colmap_params_count(model)} parameters, "
                           f"got {len(p)}", file=label, view=view, code="invalid_camera")
    if not np.isfinite(p).all():
        raise DatasetError("camera parameters have NaN or infinite entries", file=label, view=view,
                           code="nonfinite_camera")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        rest = p[3:]
    else:
        fx, fy, cx, cy = p[:4]
        rest = p[4:]
    coeffs = (tuple(rest) + (0.0,) * 4)[:4]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return K, (coeffs if any(c != 0.0 for c in coeffs) else None)


def check_nerfstudio_model(model, *, label: str | None = None, view: int | None = None) -> str:
    """The ``camera_model`` string when we load it (:data:`NERFSTUDIO_SUPPORTED`), else
    ``unsupported_camera`` naming it (fisheye and equirectangular images are not pinhole)."""
    if model in NERFSTUDIO_SUPPORTED:
        return model
    why = {"OPENCV_FISHEYE": "a fisheye model", "EQUIRECTANGULAR": "a 360-degree panorama"}.get(
        model, "an unknown model")
    raise DatasetError(
        f"camera_model {model!r} ({why}) is not supported: the models loaded are "
        f"{', '.join(NERFSTUDIO_SUPPORTED)}; undistort the images first (e.g. process the capture with "
        "`ns-process-data images --camera-type perspective`)", file=label, view=view,
        code="unsupported_camera")
