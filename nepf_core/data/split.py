"""The held-out split: which views of a dataset train and which are kept for evaluation.

Rule (the benchmarks' convention): with ``holdout_every = K > 0`` the views ``0, K, 2K, ...``
(every K-th in the dataset's own order, starting at the first) are held out and the others
train; ``K = 0`` trains on all views. Held out: ``ceil(n / K)`` views.

Default (:func:`default_holdout_every`): ``K = 8`` for sets of :data:`MIN_VIEWS_FOR_HOLDOUT`
(16) or more views, 0 below (a small set cannot spare views), and 0 when the caller has its
own held-out set (``nepf fit --eval-test``: the synthetic benchmarks keep their test views).

Bounds (:func:`check_holdout_every`): 0, or ``2 <= K <= n // 2``. ``K = 1`` would hold out
every view and leave none to train on; ``K <= n // 2`` holds out at least two views (one view
is too few to measure an error from), and ``K >= 2`` trains on at least every other view.

Torch-free (the upload validator reports the default and the bounds).
"""

from __future__ import annotations

import numpy as np

DEFAULT_HOLDOUT_EVERY = 8
MIN_VIEWS_FOR_HOLDOUT = 16
EVAL_PIXEL_BUDGET = 1 << 17
"""Pixels one held-out evaluation renders at most (all views together): 8 views at 128², a few
seconds on a 2-core CPU. Without it, 7 held-out views at 1600x1200 would render 13.4 M pixels,
minutes per evaluation, every minute of training."""


def default_holdout_every(n_views: int, has_test_set: bool = False) -> int:
    """8 for ``n_views >= 16`` without a separate test set, else 0 (see the module docstring)."""
    if has_test_set or n_views < MIN_VIEWS_FOR_HOLDOUT:
        return 0
    return DEFAULT_HOLDOUT_EVERY


def max_holdout_every(n_views: int) -> int:
    """The largest allowed ``K``: ``n_views // 2`` (at least two views held out)."""
    return n_views // 2


def holdout_limits(n_views: int) -> dict:
    """What the upload validator reports for a training split of ``n_views`` views: the default
    ``K`` and the largest allowed one (the service checks a job's ``holdout_every`` against them)."""
    return {"holdout_default_every": default_holdout_every(n_views), "holdout_max_every": max_holdout_every(n_views)}


def check_holdout_every(every: int, n_views: int, what: str = "holdout_every") -> int:
    """``every`` when it is 0 or in ``[2, n_views // 2]``; ``ValueError`` naming ``what``,
    the bounds and why otherwise."""
    if isinstance(every, bool) or not isinstance(every, (int, np.integer)):
        raise ValueError(f"{what} must be an integer (0: no held-out views), not {every!r}")
    every = int(every)
    if every == 0:
        return 0
    hi = max_holdout_every(n_views)
    if hi < 2:
        raise ValueError(f"{what} = {every}: this dataset has {n_views} views, too few to hold any out "
                         f"(at least 4 are needed); use 0")
    if not 2 <= every <= hi:
        raise ValueError(f"{what} = {every} is out of range for {n_views} views: use 0 (train on all) or "
                         f"2..{hi} (at least two views held out, at least every other view training)")
    return every


def holdout_indices(n_views: int, every: int) -> tuple[np.ndarray, np.ndarray]:
    """``(train_idx, test_idx)``: ``test_idx = 0, K, 2K, ... < n_views`` and the rest, both sorted
    (``K = 0``: all views train, none held out)."""
    idx = np.arange(n_views)
    if every <= 0:
        return idx, idx[:0]
    held = idx % every == 0
    return idx[~held], idx[held]


def eval_stride_for(n_views: int, width: int, height: int, max_pixels: int = EVAL_PIXEL_BUDGET) -> int:
    """The smallest stride ``s >= 1`` with ``n_views * ceil(H / s) * ceil(W / s) <= max_pixels``:
    an evaluation renders every ``s``-th pixel of every ``s``-th row. The PSNR of that grid is an
    unbiased estimate of the full image's (its MSE is a mean over a regular pixel sample); SSIM
    is that of the subsampled images."""
    s = 1
    while n_views * -(-height // s) * -(-width // s) > max_pixels and s < max(width, height):
        s += 1
    return s


def split_info(n_views: int, every: int) -> dict:
    """The JSON record of a split (``summary.json`` / ``report.json`` key ``"split"``)."""
    train_idx, test_idx = holdout_indices(n_views, every)
    return {"holdout_every": int(every), "n_train": int(len(train_idx)), "n_test": int(len(test_idx)),
            "test_views": [int(i) for i in test_idx]}


def split_scene(scene, every: int):
    """``(train, test)`` :class:`~nepf_core.data.scene.Scene` s of ``scene`` by the rule above
    (``test`` is None when ``every == 0``). Both keep the scene's ``world_from_norm``: the
    normalisation was fitted to all cameras, so held-out views lie in the same frame."""
    train_idx, test_idx = holdout_indices(scene.n_views, every)
    if len(test_idx) == 0:
        return scene, None
    train, test = scene.subset(train_idx), scene.subset(test_idx)
    train.split, test.split = "train", "test"
    return train, test
