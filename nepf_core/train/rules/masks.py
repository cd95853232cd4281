"""Masks decide the mask loss and the background model (before training).

With masks, the mask BCE supervises the opacity and everything outside the mask is empty (no
background model). Without masks there is no mask loss and a background radiance ``B(d)``
explains the pixels the object does not cover. This follows from the data, so it applies
with adaptivity off too.
"""

from __future__ import annotations

from nepf_core.train.decisions import Decision


def decide_masks(has_masks: bool, w_mask: float) -> tuple[bool, bool, list[Decision]]:
    """``(use_mask_loss, background, decisions)`` for a dataset with or without masks."""
    if has_masks:
        use = w_mask > 0
        return use, False, [Decision("mask_loss", use, "the dataset has masks: mask BCE supervises the opacity"),
                            Decision("background_model", False, "masked scene: everything outside the mask is empty")]
    return False, True, [Decision("mask_loss", False, "the dataset has no masks: no mask loss"),
                         Decision("background_model", True,
                                  "no masks: a background radiance B(d) explains non-object pixels")]
