"""Masks decide the mask loss and the background model (before training).

* No masks: no mask loss; a background volume (:mod:`nepf_core.fields.background`) explains
  the pixels the object does not cover.
* Masks, and the images show something outside them (a real capture: table, floor, room): the
  mask BCE supervises the opacity, and the background volume is trained on the pixels outside
  the masks (``loss_bg``), so that the full image can be rendered and its PSNR means something.
* Masks, and the images are black outside them (the synthetic scenes): everything outside the
  mask is empty; no background model.

"Shows something" is measured on the data: more than ``BACKGROUND_MIN_FRACTION`` of the
pixels outside the masks have a channel above ``BACKGROUND_LEVEL`` (linear). This follows from
the data, so it applies with adaptivity off too.
"""

from __future__ import annotations

import numpy as np

from nepf_core.train.decisions import Decision

BACKGROUND_LEVEL = 0.01
"""Linear value above which a pixel outside the masks is not black (about 25/255 in sRGB)."""
BACKGROUND_MIN_FRACTION = 0.05
"""Share of the pixels outside the masks that must be above ``BACKGROUND_LEVEL``."""


def lit_outside_masks(images, masks) -> float:
    """Share of the pixels outside the masks whose brightest channel exceeds ``BACKGROUND_LEVEL``.

    ``images``: per view ``[H, W, 3]`` linear; ``masks``: per view ``[H, W]`` (foreground > 0.5).
    Views are read one at a time (no copy of the image set); 0 when no pixel is outside."""
    lit = total = 0
    for img, m in zip(images, masks):
        out = np.asarray(m) <= 0.5
        px = np.asarray(img)[out]
        lit += int((px.max(-1) > BACKGROUND_LEVEL).sum()) if px.size else 0
        total += int(out.sum())
    return lit / total if total else 0.0


def decide_masks(has_masks: bool, w_mask: float, lit_outside: float = 0.0) -> tuple[bool, bool, list[Decision]]:
    """``(use_mask_loss, background, decisions)`` for a dataset with or without masks;
    ``lit_outside`` is :func:`lit_outside_masks` of a masked dataset."""
    if has_masks:
        use = w_mask > 0
        mask_d = Decision("mask_loss", use, "the dataset has masks: mask BCE supervises the opacity")
        if lit_outside > BACKGROUND_MIN_FRACTION:
            return use, True, [mask_d, Decision(
                "background_model", True,
                f"{100 * lit_outside:.0f}% of the pixels outside the masks are not black: a background "
                "volume is trained on them so that the full image is rendered")]
        return use, False, [mask_d, Decision("background_model", False,
                                             "the images are black outside the masks: everything outside is empty")]
    return False, True, [Decision("mask_loss", False, "the dataset has no masks: no mask loss"),
                         Decision("background_model", True,
                                  "no masks: a background volume explains what the object does not cover")]


def decide_object_region(scene) -> tuple[list[float] | None, list[Decision], np.ndarray,
                                         tuple[np.ndarray, float] | None]:
    """Without masks: ``(halfspace, decisions, points, frame)``.

    The capture's sparse points (COLMAP, nerfstudio) or, without them, the points triangulated from
    the images (:func:`nepf_core.data.sparse_points.scene_points`) are searched
    for a support plane (:mod:`nepf_core.data.object_region`) within the largest ball around
    the load frame's origin that keeps every camera outside. With one, the object is what lies in
    front of it, and ``frame = (centre, radius)`` is the ball around those points
    (:func:`~nepf_core.data.object_region.enclosing_ball`) in load-frame units, the frame the SDF
    should model. ``halfspace`` (``n . x + c > 0``, or None: the whole unit sphere) and
    ``points`` (the triangulated points in the object region, ``[P, 3]``, for
    :mod:`nepf_core.train.surface_points`) are in that frame. ``frame`` is None when there is
    no support (the load frame stays)."""
    from nepf_core.data.normalize import CAMERA_CLEARANCE
    from nepf_core.data.object_region import enclosing_ball, find_object_region
    from nepf_core.data.sparse_points import scene_points

    def in_front(p: np.ndarray, hs) -> np.ndarray:
        return p[p @ np.asarray(hs[:3]) + hs[3] > 0.0]

    sparse, source = scene_points(scene)
    cams = np.asarray(scene.c2w, dtype=np.float64)[:, :3, 3]
    reach = float(np.linalg.norm(cams, axis=1).min()) / CAMERA_CLEARANCE
    region = find_object_region(scene, points=sparse, search_radius=reach)
    frame, decisions = None, []
    hs = region.halfspace()
    if hs is not None:
        obj = in_front(sparse[np.linalg.norm(sparse, axis=1) < reach], hs)
        centre, radius = enclosing_ball(obj, cams)
        frame, region = (centre, radius), region.in_frame(centre, radius)
        sparse, hs = (sparse - centre) / radius, region.halfspace()
        decisions.append(Decision("object_frame", {"centre": [round(float(v), 4) for v in centre],
                                                   "radius": round(radius, 4)},
                                  f"the SDF models the ball around the {len(obj)} sparse points in front "
                                  f"of the support (centre and radius in units of the load frame's unit sphere, "
                                  f"the largest ball every camera sees whole)", 0))
    inside = sparse[np.linalg.norm(sparse, axis=1) < 1.0]
    if hs is not None:
        inside = in_front(inside, hs)
    decisions.insert(0, Decision("object_region", hs is not None,
                                 f"no masks; {region.reason} ({region.points} points in the region, "
                                 f"{len(sparse)} in all, from {source}; {len(inside)} in front of the support)"))
    return (None if hs is None else list(hs)), decisions, inside, frame
