"""The working resolution: exact area resampling by any factor, and the intrinsics that match.

Images whose long side exceeds ``max_side`` are shrunk at load so that memory and step cost
stay bounded whatever the upload holds. The resampling is *area* (box) integration, exact
for any factor: output pixel ``i`` of an axis of ``n_in -> n_out`` pixels covers the input
interval ``[i r, (i + 1) r]``, ``r = n_in / n_out``, and averages the input over it,

    ``out[i] = sum_j |[j, j + 1] ∩ [i r, (i + 1) r]| / r * in[j]``.

The weights are computed in integer units (``n_out`` per input pixel, ``n_in`` per output
pixel), so they are exact rationals; each output is a convex combination (rows sum to 1)
and the image mean is preserved. For an integer factor this is the plain ``f x f`` block mean.

Intrinsics: the continuous image domain ``[0, W] x [0, H]`` maps onto ``[0, W'] x [0, H']``
by ``u' = u W'/W``, ``v' = v H'/H``. In the ``Scene`` convention (pixel centres at +0.5,
so the domain edges are the image edges) this is exactly ``K' = diag(W'/W, H'/H, 1) K``:
``fx, cx`` scale by ``W'/W`` and ``fy, cy`` by ``H'/H``; no half-pixel shift is needed.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse


def working_size(w: int, h: int, max_side: int | None) -> tuple[int, int]:
    """``(W', H')``: ``(w, h)`` scaled so the long side is ``max_side`` (unchanged when it
    already fits or ``max_side`` is 0/None). The short side is rounded: ``round(s * max_side / long)``."""
    long = max(w, h)
    if not max_side or long <= max_side:
        return int(w), int(h)
    s = max_side / long
    return max(1, int(round(w * s))), max(1, int(round(h * s)))


def area_matrix(n_in: int, n_out: int) -> scipy.sparse.csr_matrix:
    """Area-resampling weights ``[n_out, n_in]`` float32 (formula in the module docstring).

    In integer units input pixel ``j`` spans ``[j n_out, (j + 1) n_out]`` and output pixel
    ``i`` spans ``[i n_in, (i + 1) n_in]``; the weight is their overlap divided by ``n_in``.
    """
    i = np.arange(n_out, dtype=np.int64)[:, None]
    span = -(-n_in // n_out) + 1                        # inputs one output can touch
    j = (i * n_in) // n_out + np.arange(span, dtype=np.int64)[None, :]
    lo = np.maximum(j * n_out, i * n_in)
    hi = np.minimum((j + 1) * n_out, (i + 1) * n_in)
    overlap = np.maximum(hi - lo, 0)
    keep = (overlap > 0) & (j < n_in)
    rows = np.broadcast_to(i, j.shape)[keep]
    return scipy.sparse.csr_matrix(((overlap[keep] / n_in).astype(np.float32), (rows, j[keep])),
                                   shape=(n_out, n_in))


def area_resize(a: np.ndarray, w_out: int, h_out: int) -> np.ndarray:
    """Area-resample ``[H, W, ...]`` to ``[h_out, w_out, ...]`` float32 (separable: rows, then columns)."""
    h, w = a.shape[:2]
    rest = a.shape[2:]
    out = np.asarray(a, dtype=np.float32)
    if h_out != h:
        out = area_matrix(h, h_out) @ out.reshape(h, -1)
        out = out.reshape(h_out, w, *rest)
    if w_out != w:
        cols = np.moveaxis(out, 1, 0).reshape(w, -1)
        out = np.moveaxis((area_matrix(w, w_out) @ cols).reshape(w_out, h_out, *rest), 0, 1)
    return np.ascontiguousarray(out, dtype=np.float32)


def grid_scale(w: int, h: int, downscale: int, max_side: int | None) -> tuple[tuple[int, int], np.ndarray]:
    """The grid a full-size ``w x h`` view is loaded on, and the intrinsics map to it.

    First the integer box filter ``downscale`` (which crops ``w % f`` columns / ``h % f`` rows,
    see ``images.box_downscale``), then area resampling to :func:`working_size`. Returns
    ``((W', H'), S)`` with ``S = diag(W' / (f w1), H' / (f h1), 1)``, ``w1 = w // f``, so
    ``K' = S K`` (module docstring).
    """
    w1, h1 = w // downscale, h // downscale
    w2, h2 = working_size(w1, h1, max_side)
    S = np.diag([w2 / (downscale * w1) if w1 else 1.0 / downscale,
                 h2 / (downscale * h1) if h1 else 1.0 / downscale, 1.0])
    return (w2, h2), S
