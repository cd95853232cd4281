"""The sRGB transfer functions (IEC 61966-2-1), the one home of the formula, for numpy and torch.

Images on disk are sRGB; the maths (BSDF, volume rendering) is linear; colour losses, PSNR and
SSIM compare sRGB values (display space, what the PNGs hold). So every module that crosses
that line calls these two functions:

    linear_to_srgb(x) = 12.92 x                     x <= 0.0031308
                        1.055 x^(1/2.4) - 0.055     otherwise           (x clipped to [0, 1])
    srgb_to_linear(s) = s / 12.92                   s <= 0.04045
                        ((s + 0.055) / 1.055)^2.4   otherwise           (s clipped to [0, 1])

Worked values: ``linear_to_srgb(0.5) = 0.73536``, ``srgb_to_linear(0.5) = 0.21404``, both map 0
to 0 and 1 to 1. The power is taken of ``max(x, 0.0031308)`` so that the branch not chosen
stays finite (its value and gradient are discarded by ``where``; a power of 0 would give an
infinite slope and a NaN gradient through ``where``); the slope near 0 is bounded by 12.92.

Both take a ``torch.Tensor`` (any shape, dtype kept, differentiable) or anything numpy reads
(float dtype kept; other dtypes computed in float64). Callers that promise float32 (the data
loaders) pass float32 arrays. torch-free unless given a tensor (the data package and
``nepf_core.data.validate`` import it without torch).
"""

from __future__ import annotations

import sys

import numpy as np

_LIN_KNEE = 0.0031308
_SRGB_KNEE = 0.04045


def _torch_if_tensor(x):
    """The torch module when ``x`` is a tensor, else None (torch is never imported here: if it was
    not imported already, ``x`` cannot be a tensor)."""
    torch = sys.modules.get("torch")
    return torch if torch is not None and isinstance(x, torch.Tensor) else None


def _as_float_array(x) -> np.ndarray:
    x = np.asarray(x)
    return x if np.issubdtype(x.dtype, np.floating) else x.astype(np.float64)


def linear_to_srgb(x):
    """sRGB OETF (module docstring): linear ``[...]`` -> sRGB ``[...]`` in [0, 1]."""
    torch = _torch_if_tensor(x)
    if torch is not None:
        x = x.clamp(0.0, 1.0)
        return torch.where(x <= _LIN_KNEE, 12.92 * x, 1.055 * x.clamp_min(_LIN_KNEE) ** (1 / 2.4) - 0.055)
    x = np.clip(_as_float_array(x), 0.0, 1.0)
    return np.where(x <= _LIN_KNEE, 12.92 * x, 1.055 * np.power(np.maximum(x, _LIN_KNEE), 1 / 2.4) - 0.055)


def srgb_to_linear(x):
    """sRGB EOTF, the inverse of :func:`linear_to_srgb`: sRGB ``[...]`` -> linear ``[...]``."""
    torch = _torch_if_tensor(x)
    if torch is not None:
        x = x.clamp(0.0, 1.0)
        return torch.where(x <= _SRGB_KNEE, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    x = np.clip(_as_float_array(x), 0.0, 1.0)
    return np.where(x <= _SRGB_KNEE, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
