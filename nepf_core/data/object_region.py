"""Where the object is in a capture without masks: the support plane (issue 26).

Without masks the SDF is asked to model everything inside the unit sphere that every camera sees
whole (``data/normalize.py``): the object *and* the patch of wall or table it hangs from or
stands on. Those surfaces pass through the sphere, the background volume (outside it) cannot
explain them, and the SDF fills the sphere to paint them: the mesh becomes the region's solid
interior, not the object.

A wall or a table is the largest plane among the points the cameras see, and every camera is on
one side of it (a support is seen from one side only). Before training, RANSAC finds it among
the sparse points triangulated from the images (:mod:`nepf_core.data.sparse_points`):

    plane:  s(x) = n . x + c   (|n| = 1, n towards the cameras)
    inlier: |s(p)| < tau       (tau = ``inlier_distance``)

It is accepted as the support only when it holds at least ``min_support_share`` of the points in
the unit sphere, every camera centre is in front of it (``s(o_i) > tau``), and at least
``min_object_share`` of the points lie in front of it beyond the ``margin`` (the object). The
object region is then the ball cut by the half-space ``s(x) > margin``: the renderer ends the SDF's
part of each ray there and the background volume explains everything behind it (the wall with
its true parallax), and the export cuts the SDF to it (``max(f, |x| - 1, margin - s(x))``, a CSG
intersection, so the cut is capped flat like a mounting plate).

Why a plane from image features and not a segmentation: no segmentation model can ship offline
here; a support (wall, table, floor) is the common case of a phone capture; and the fitted SDF
cannot be asked (it is a fog while it is being fitted). An object captured all round (cameras
on both sides of every plane) has no support and keeps the whole ball. With masks none of this
runs: the masks separate the object. Shapes: points ``[P, 3]``, camera centres ``[N, 3]``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np


@dataclass
class RegionConfig:
    """How the support plane is searched for (normalised units: the region is the unit ball)."""

    inlier_distance: float = 0.03
    """``tau``: a point this close to a plane lies on it."""
    margin: float = 0.06
    """The object starts this far in front of the support (the plane's own thickness, 2 tau)."""
    min_support_share: float = 0.2
    """A support holds at least this share of the points."""
    min_object_share: float = 0.05
    """At least this share of the points lies in front of the support (else: no object)."""
    ransac_iters: int = 400
    max_points: int = 20_000
    seed: int = 0


@dataclass
class ObjectRegion:
    """The decided region: the unit ball, cut by a support plane when one was found."""

    support_normal: list[float] | None = None
    """Unit ``n`` towards the cameras (normalised frame), or None: no support found."""
    support_offset: float = 0.0
    """``c`` of ``s(x) = n . x + c``."""
    margin: float = 0.0
    support_share: float = 0.0
    """Share of the points on the plane (inliers)."""
    object_share: float = 0.0
    """Share of the points in front of the plane beyond the margin."""
    points: int = 0
    reason: str = ""
    """Why there is or is not a support plane (for the report)."""

    def in_frame(self, centre, radius: float) -> "ObjectRegion":
        """This region in the frame ``x' = (x - centre) / radius``: ``n`` stays, the offset becomes
        ``(n . centre + c) / radius`` and the margin ``margin / radius`` (the same plane and the same
        physical margin)."""
        out = dataclasses.replace(self)
        if self.support_normal is not None:
            n = np.asarray(self.support_normal, dtype=np.float64)
            out.support_offset = float((n @ np.asarray(centre, dtype=np.float64) + self.support_offset) / radius)
            out.margin = self.margin / radius
        return out

    def halfspace(self) -> tuple[float, float, float, float] | None:
        """``(n_x, n_y, n_z, c - margin)``: the object is where ``n . x + c - margin > 0``; None: no support."""
        if self.support_normal is None:
            return None
        return (*self.support_normal, self.support_offset - self.margin)


def _plane_through(p: np.ndarray) -> tuple[np.ndarray, float] | None:
    n = np.cross(p[1] - p[0], p[2] - p[0])
    norm = np.linalg.norm(n)
    if norm < 1e-9:
        return None
    n = n / norm
    return n, -float(n @ p[0])


def find_support_plane(points: np.ndarray, camera_centres: np.ndarray,
                       cfg: RegionConfig | None = None) -> ObjectRegion:
    """RANSAC for the support plane among ``points [P, 3]`` (seen by the cameras, in the unit sphere) (module docstring).

    The best plane (most inliers) is refined by least squares on its inliers (the smallest
    singular vector of the centred inliers), oriented towards the cameras, then checked against
    the three acceptance rules. Returns the region, with ``support_normal`` None when rejected.
    """
    cfg = cfg or RegionConfig()
    p = np.asarray(points, dtype=np.float64)
    region = ObjectRegion(points=int(len(p)))
    if len(p) < 100:
        region.reason = f"too few points seen in the region ({len(p)}) to look for a support"
        return region
    rng = np.random.default_rng(cfg.seed)
    if len(p) > cfg.max_points:
        p = p[rng.choice(len(p), cfg.max_points, replace=False)]
    best, best_count = None, -1
    for _ in range(cfg.ransac_iters):
        plane = _plane_through(p[rng.choice(len(p), 3, replace=False)])
        if plane is None:
            continue
        count = int((np.abs(p @ plane[0] + plane[1]) < cfg.inlier_distance).sum())
        if count > best_count:
            best, best_count = plane, count
    if best is None:
        region.reason = "no plane through the points"
        return region
    inliers = p[np.abs(p @ best[0] + best[1]) < cfg.inlier_distance]
    centre = inliers.mean(0)
    n = np.linalg.svd(inliers - centre, full_matrices=False)[2][-1]
    c = -float(n @ centre)
    cams = np.asarray(camera_centres, dtype=np.float64)
    if np.median(cams @ n + c) < 0:
        n, c = -n, -c
    s = p @ n + c
    support = float((np.abs(s) < cfg.inlier_distance).mean())
    obj = float((s > cfg.margin).mean())
    region.support_share, region.object_share = support, obj
    cams_in_front = bool((cams @ n + c > cfg.inlier_distance).all())
    if support < cfg.min_support_share:
        region.reason = f"largest plane holds {support:.0%} of the points seen (< {cfg.min_support_share:.0%})"
    elif not cams_in_front:
        region.reason = "cameras on both sides of the largest plane: not a support"
    elif obj < cfg.min_object_share:
        region.reason = f"only {obj:.0%} of the points seen in front of the largest plane: no object on it"
    else:
        region.support_normal = [float(v) for v in n]
        region.support_offset = c
        region.margin = cfg.margin
        region.reason = (f"support plane holds {support:.0%} of the points seen, "
                         f"{obj:.0%} lies in front of it")
    return region


def find_object_region(scene, cfg: RegionConfig | None = None, points: np.ndarray | None = None,
                         search_radius: float = 1.0) -> ObjectRegion:
    """Sparse points of ``scene`` (:func:`triangulate_scene`, or ``points [P, 3]`` when given) inside
    the ball of ``search_radius``, then :func:`find_support_plane` with its camera centres."""
    from nepf_core.data.sparse_points import triangulate_scene

    pts = points if points is not None else triangulate_scene(scene)
    pts = pts[np.linalg.norm(pts, axis=1) < search_radius]
    return find_support_plane(pts, np.asarray(scene.c2w)[:, :3, 3], cfg)


def enclosing_ball(object_points: np.ndarray, camera_centres: np.ndarray, *, quantile: float = 0.98,
                   margin: float = 1.1, clearance: float = 1.05) -> tuple[np.ndarray, float]:
    """``(centre [3], radius)`` of the ball the SDF should model: around the points in front of
    the support, ``[P, 3]``.

    The load-time unit sphere is the largest ball that every camera sees whole
    (:mod:`nepf_core.data.normalize`). A phone capture has close-ups, so that ball can be smaller
    than the object: on the fox the snout and the ears were outside it and only the background
    volume could draw them. The points say where the object is. Robust to stray points:

        centre = mid-point of the per-axis (1 - q, q) quantiles of the points
        radius = margin * q-quantile of |p - centre|,  capped at min_i |o_i - centre| / clearance

    (every camera centre ``o_i`` stays outside the ball, as the normalisation requires).
    """
    p = np.asarray(object_points, dtype=np.float64)
    lo, hi = np.quantile(p, 1.0 - quantile, axis=0), np.quantile(p, quantile, axis=0)
    centre = 0.5 * (lo + hi)
    radius = margin * float(np.quantile(np.linalg.norm(p - centre, axis=1), quantile))
    reach = float(np.linalg.norm(np.asarray(camera_centres, dtype=np.float64) - centre, axis=1).min()) / clearance
    return centre, min(radius, reach)
