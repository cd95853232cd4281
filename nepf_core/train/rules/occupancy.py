"""Empty space: the occupancy grid's start from the masks' visual hull, and its refreshes.

With masks (and adaptivity on) cells outside the masks' visual hull start empty and are never
queried at a refresh, so no sample falls outside the mask bounds. Every
``train.occupancy_every`` steps the grid is refreshed from the SDF
(:meth:`nepf_core.render.occupancy.OccupancyGrid.update`); the share of cells still occupied is
reported as ``occupied_fraction``.
"""

from __future__ import annotations

from nepf_core.train.decisions import Decision


def empty_space_decision(cfg) -> Decision | None:
    """The record of what the grid is used for (None without a grid); ``cfg``: the run's
    :class:`~nepf_core.config.NePFConfig`."""
    res, on = cfg.model.occupancy_resolution, bool(cfg.train.adaptive)
    if res <= 0:
        return None
    how = ("rays that meet no occupied cell leave the training batch" if on else
           "the grid is maintained but not used (adaptivity off)")
    return Decision("empty_space_skipping", on, f"occupancy grid {res}^3 refreshed from the SDF during training: {how}")


def carve_visual_hull(model, scene, cfg) -> Decision | None:
    """Restrict the grid (and its refreshes) to the masks' visual hull; None without masks."""
    from nepf_core.render.visual_hull import visual_hull_cells
    if not scene.has_masks:
        return None
    if not cfg.train.adaptive:
        return Decision("visual_hull", False, "adaptivity disabled: samples may fall outside the mask bounds "
                        "(everything-on baseline)")
    hull = visual_hull_cells(scene, model.occupancy.cfg.resolution, device=model.hull.device)
    if not hull.any():
        return Decision("visual_hull", False, "the masks' visual hull is empty (inconsistent masks/cameras?): not used")
    model.hull.copy_(hull)
    model.occupancy.occ &= hull
    return Decision("visual_hull", True, f"no samples outside the mask bounds: cells outside the masks' visual "
                    f"hull are empty ({1 - float(hull.float().mean()):.1%} of the grid culled)")


def refresh_occupancy(model, step: int) -> float:
    """Refresh the grid from the SDF (cells outside the hull are never queried); returns the
    occupied fraction."""
    occ = model.occupancy
    hull = None if bool(model.hull.all()) else model.hull
    occ.update(model.sdf.sdf, float(model.deviation().detach()), step, allowed=hull)
    return float(occ.occupied_fraction())
