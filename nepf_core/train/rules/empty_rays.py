"""Rays that meet no occupied cell leave the training batch, except a random ``miss_keep`` share.

Such a ray crosses only cells where ``|f| > safety (r_h + delta/2) + k_s / s`` (occupancy rule
(1), :mod:`nepf_core.render.occupancy`), so its opacity is ``<= ~e^{-k_s}`` and rendering it
spends ``n_samples + n_importance`` SDF queries (with gradients) on empty space. The share kept
lets the mask loss and the eikonal term still see empty space; each kept miss gets the
importance weight ``RayBatch.weight = 1 / miss_keep`` (hits weigh 1) in the mask loss and in
the eikonal mean, so their expectations stay the means over the drawn batch (unweighted,
thinning would turn the eikonal into a near-surface term).

With a background volume (captures without masks, DTU), a ray that meets no occupied cell still
shows the background: its colour is ``C_bg`` (its SDF weights sum to at most ~e^{-k_s}). The
misses left out of the SDF batch are then returned too (at most as many as the SDF batch holds,
with importance weights), and the loop renders them through the background volume alone
(:func:`nepf_core.render.renderer.render_background_only`), so the background pixels train the
background at the cost of their background samples only: the background pixels (the wall
behind a mounted object, half the pixels of the fox) train as often as the object's.

Only with adaptivity on and an occupancy grid that has been refreshed. The NeuS sampler spreads
a kept ray's samples over its whole chord, so a surface outside the occupied cells is still
found, and then makes its cells occupied.
"""

from __future__ import annotations

import torch

from nepf_core.train.decisions import Decision


class EmptyRayRule:
    def __init__(self, cfg) -> None:
        """``cfg``: the run's :class:`~nepf_core.config.NePFConfig` (``rules.miss_keep``, ``train.adaptive``)."""
        self.cfg, self.rc = cfg, cfg.rules
        self.last: float | None = None
        """Share of the drawn rays left out at the last step (logged as ``rays_left_out``)."""
        self.total, self.count = 0.0, 0

    def mean_left_out(self) -> float | None:
        """Mean over training steps of the share of drawn rays left out (report.json)."""
        return self.total / self.count if self.count else None

    def thin(self, model, rays, step: int, generator: torch.Generator | None,
             first: bool) -> tuple[object, object | None, Decision | None]:
        """``rays`` (``R``) -> ``(kept, left_out, decision or None)``: ``kept`` the RayBatch of the
        hits and the kept misses (``R' <= R``, same order), ``left_out`` the other misses for the
        background alone (a RayBatch, or None when nothing was left out or the model has no
        background); ``first``: no ``empty_rays`` decision was recorded yet
        (it is recorded once)."""
        occ = getattr(model, "occupancy", None)
        if not self.cfg.train.adaptive or occ is None or int(occ.n_updates) == 0:
            return rays, None, None
        from nepf_core.render.sampling import object_segment
        near, far, _, _ = object_segment(rays.origins, rays.directions, model.cfg.object_halfspace)
        hit = occ.ray_hits(rays.origins, rays.directions, near, far)
        u = torch.rand(hit.shape, generator=generator).to(hit.device)
        keep = hit | (u < self.rc.miss_keep)
        thin = int(keep.sum()) >= 8 and not bool(keep.all())
        dropped = 1.0 - float(keep.float().mean()) if thin else 0.0
        self.last = dropped
        self.total += dropped
        self.count += 1
        if not thin:
            return rays, None, None
        decision = None
        if first:
            decision = Decision("empty_rays", {"left_out_fraction": round(dropped, 4), "miss_keep": self.rc.miss_keep},
                                f"{1 - float(hit.float().mean()):.1%} of the drawn rays meet no occupied cell (opacity "
                                f"<= ~e^-{occ.cfg.k_s:g}): they leave the batch except a random {self.rc.miss_keep:.0%}, "
                                "which keep the mask loss and the eikonal term on empty space", step)
        kept = rays.index(keep.nonzero(as_tuple=True)[0])
        kept.weight = torch.where(hit[keep], 1.0, 1.0 / max(self.rc.miss_keep, 1e-12)).to(rays.origins.dtype)
        left_out = (self._background_share(rays, keep, len(kept), generator)
                    if getattr(model, "background", None) is not None else None)   # only a background shows them
        return kept, left_out, decision

    @staticmethod
    def _background_share(rays, keep: torch.Tensor, n_kept: int, generator: torch.Generator | None):
        """The misses left out, for the background alone: at most as many as the SDF batch holds
        (a random subset of them, each weighing ``n_left_out / n_kept`` so the colour means stay
        the means over the drawn batch in expectation). Why: with masks (DTU) ~75 % of the drawn
        rays miss the visual hull, and rendering them all made a step ~2.5x slower for pixels
        the masked error does not count; a background ray costs a fraction of an SDF ray, so the
        background then takes at most about a quarter of a step."""
        left = (~keep).nonzero(as_tuple=True)[0]
        if len(left) <= n_kept:
            out = rays.index(left)
            out.weight = None
            return out
        pick = torch.randperm(len(left), generator=generator)[:n_kept].to(left.device)
        out = rays.index(left[pick])
        out.weight = torch.full((n_kept,), len(left) / n_kept, dtype=rays.origins.dtype, device=rays.origins.device)
        return out

    def state(self) -> dict:
        return {"drop_sum": self.total, "drop_n": self.count}

    def load_state(self, s: dict) -> None:
        self.total, self.count = s.get("drop_sum", 0.0), s.get("drop_n", 0)
