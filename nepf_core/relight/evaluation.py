"""The relight and material part of ``nepf eval`` (``--relight gt/relight --gt-maps gt/arrays_test.npz``).

``gt/relight`` holds ``lights.json`` (world frame) and ``arrays.npz`` with ``rgb_linear
[K, V, H, W, 3]`` and ``alpha [V, H, W]`` for the cameras of ``--test``, in the same order;
``gt/arrays_test.npz`` holds the GT maps of those views (``albedo``, ``roughness``,
``metallic``, ``normal_world``, ``alpha``). Scores: :mod:`.metrics`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _load_npz(path: Path, keys: tuple[str, ...], what: str) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{what}: {path.name} not found")
    with np.load(path) as z:
        missing = [k for k in keys if k not in z.files]
        if missing:
            raise ValueError(f"{what}: {path.name} lacks {', '.join(missing)}")
        return {k: np.asarray(z[k], np.float32) for k in keys}


GT_MAP_KEYS = ("albedo", "roughness", "metallic", "normal_world", "alpha")


def material_scores(renders: dict, gt_maps_path, test_images: np.ndarray, test_masks: np.ndarray | None,
                    unlit_rel_threshold: float) -> dict:
    """Material scores of ``nepf render``'s arrays (``albedo``, ``roughness``, ``metallic``,
    ``normal``) against the GT maps file; lit pixels from the test images (the training rule)."""
    from nepf_core.rays import unlit_threshold
    from nepf_core.relight.metrics import material_metrics
    gt = _load_npz(Path(gt_maps_path), GT_MAP_KEYS, "--gt-maps")
    lit = test_images.max(-1) >= unlit_threshold(test_images, test_masks, unlit_rel_threshold)
    if lit.shape != gt["alpha"].shape:
        lit = None
    return material_metrics(renders, gt, lit)


def relight_scores(run, relight_dir, cameras, out, device: str = "auto", max_side: int = 0) -> dict:
    """Relight the run under ``relight_dir/lights.json`` at the cameras of ``cameras`` (written to
    ``out``) and score it against ``relight_dir/arrays.npz``: ``relight_psnr``, ``relight_scale``."""
    from nepf_core.relight.metrics import relight_psnr
    from nepf_core.relight.run import relight_run
    relight_dir = Path(relight_dir)
    gt = _load_npz(relight_dir / "arrays.npz", ("rgb_linear", "alpha"), "--relight")
    info = relight_run(run, relight_dir / "lights.json", cameras, out, device, max_side=max_side)
    value, scale = relight_psnr(info["rgb_linear"], gt["rgb_linear"], gt["alpha"])
    return {"relight_psnr": value, "relight_scale": [float(c) for c in scale], "relight_bsdf": info["bsdf_kind"]}


def eval_section(run, test, renders: dict, test_images: np.ndarray, test_masks: np.ndarray | None, out_dir,
                 *, relight_dir=None, gt_maps=None, device: str = "auto", max_side: int = 0) -> dict:
    """What ``nepf eval`` adds with ``--gt-maps`` (material scores of its renders) and ``--relight``
    (relight PSNR; relit images in ``out_dir/relight``). The lit rule's threshold is the run's
    ``train.unlit_rel_threshold``."""
    import json

    from nepf_core.config import NePFConfig
    res: dict = {}
    if gt_maps:
        cfg = NePFConfig.from_dict(json.loads((Path(run) / "config.json").read_text()))
        res.update(material_scores(renders, gt_maps, test_images, test_masks, cfg.train.unlit_rel_threshold))
    if relight_dir:
        res.update(relight_scores(run, relight_dir, test, Path(out_dir) / "relight", device, max_side))
    res["relight_conventions"] = (
        "relight_psnr: nepf relight under --relight's lights at --test's cameras, one scale per colour channel "
        "over all lights, views and GT-alpha > 0.5 pixels, the one that minimises the displayed squared error "
        "sum (min(s p, 1) - min(g, 1))^2, then clip, sRGB, PSNR; "
        "albedo_psnr(_lit): a least-squares per-channel alignment on the albedo over the GT foreground (its lit pixels); "
        "roughness/metallic MAE over the GT foreground; normal_mae_deg: mean angle to normal_world")
    return res
