"""The loss as one sum: every term a named :class:`LossTerm` of :data:`LOSS_TERMS`,
:func:`compute_losses` (each term by name) and :func:`total_loss` (``sum_k w_k L_k``).

Adding a term means one function of a :class:`~nepf_core.losses.batch.LossBatch`, one weight in
:class:`~nepf_core.losses.config.LossConfig` and one row here; the sum, the records and the
renderer's requests (:func:`needs_lobe_split`, :func:`needs_jitter_normals`) follow from the row.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from torch import Tensor

from nepf_core.losses.batch import LossBatch, loss_batch
from nepf_core.losses.colour import loss_background, loss_colour_range, loss_radiance, loss_surface, loss_volume
from nepf_core.losses.config import LossConfig
from nepf_core.losses.geometry import (loss_eikonal, loss_hessian, loss_mask, loss_normal_smooth,
                                       loss_surface_points)
from nepf_core.losses.light import loss_light
from nepf_core.losses.material import (loss_albedo_fill, loss_albedo_flat, loss_albedo_smooth, loss_brdf_smooth,
                                       loss_material_evidence, loss_material_range, loss_metallic_unseen)
from nepf_core.rays import RayBatch


@dataclass(frozen=True)
class LossTerm:
    """One named loss term: its record key, the :class:`LossConfig` field holding its weight, and
    ``fn(LossBatch) -> []``. A term whose weight is 0 is not computed (its value is 0)."""

    name: str
    weight: str
    fn: Callable[[LossBatch], Tensor]
    lobe_split: bool = False
    """The term reads :attr:`RenderOutput.lobe` (the render must be asked for it)."""
    jitter_normals: bool = False
    """The term reads the jittered points' normals (the render must be asked for them)."""
    present: Callable[[LossBatch], bool] | None = None
    """For a term whose input only some renders carry: whether this batch has it (the term is left
    out otherwise). None: always present."""


LOSS_TERMS: tuple[LossTerm, ...] = (
    LossTerm("loss_r", "w_r", loss_radiance),
    LossTerm("loss_bg", "w_r", loss_background),
    LossTerm("loss_surf", "lambda1_surf", loss_surface),
    LossTerm("loss_vol", "lambda2_vol", loss_volume),
    LossTerm("loss_eik", "w_eikonal", loss_eikonal),
    LossTerm("loss_hess", "w_hessian", loss_hessian),
    LossTerm("loss_light", "w_light", loss_light),
    LossTerm("loss_mask", "w_mask", loss_mask),
    LossTerm("loss_albedo_smooth", "w_albedo_smooth", loss_albedo_smooth),
    LossTerm("loss_albedo_flat", "w_albedo_flat", loss_albedo_flat),
    LossTerm("loss_albedo_fill", "w_albedo_fill", loss_albedo_fill),
    LossTerm("loss_brdf_smooth", "w_brdf_smooth", loss_brdf_smooth),
    LossTerm("loss_normal_smooth", "w_normal_smooth", loss_normal_smooth, jitter_normals=True,
             present=lambda b: b.out.surface.jitter is not None and b.out.surface.jitter.normal is not None),
    LossTerm("loss_material_range", "w_material_range", loss_material_range),
    LossTerm("loss_colour_range", "w_colour_range", loss_colour_range),
    LossTerm("loss_metallic_unseen", "w_metallic_unseen", loss_metallic_unseen, lobe_split=True),
    LossTerm("loss_material_evidence", "w_material_evidence", loss_material_evidence,
             present=lambda b: b.out.material_evidence is not None),   # only the training step gathers it
    LossTerm("loss_surface_points", "w_surface_points", loss_surface_points,
             present=lambda b: b.surface_points is not None),
)
"""Every term, in the order they are computed and summed."""


def needs_lobe_split(cfg: LossConfig) -> bool:
    """Whether a term with a non-zero weight reads :attr:`RenderOutput.lobe`."""
    return any(t.lobe_split and getattr(cfg, t.weight) > 0 for t in LOSS_TERMS)


def needs_jitter_normals(cfg: LossConfig) -> bool:
    """Whether a term with a non-zero weight reads the jittered points' normals."""
    return any(t.jitter_normals and getattr(cfg, t.weight) > 0 for t in LOSS_TERMS)


def compute_losses(out, rays: RayBatch, cfg: LossConfig, *, use_mask: bool, specular: bool = True,
                   background: bool = False, background_rays: tuple[Tensor, RayBatch] | None = None,
                   surface_points: Callable[[], Tensor] | None = None) -> dict[str, Tensor]:
    """Every term of :data:`LOSS_TERMS` by name (unweighted; 0 where its weight is 0), for one
    render ``out`` of ``rays``; arguments as :func:`loss_batch`. ``loss_surface_points`` is
    present only with ``surface_points``, ``loss_material_evidence`` only when ``out`` carries the
    evidence (the training step gathers it; a plain render does not). :func:`total_loss` sums them."""
    b = loss_batch(out, rays, cfg, use_mask=use_mask, specular=specular, background=background,
                   background_rays=background_rays, surface_points=surface_points)
    terms = {}
    for t in LOSS_TERMS:
        if t.present is not None and not t.present(b):
            continue
        terms[t.name] = t.fn(b) if getattr(cfg, t.weight) > 0 else b.zero
    return terms


def total_loss(terms: dict[str, Tensor], cfg: LossConfig) -> Tensor:
    """``sum_k w_k L_k`` over the terms present, in :data:`LOSS_TERMS` order."""
    total = None
    for t in LOSS_TERMS:
        if t.name in terms:
            v = getattr(cfg, t.weight) * terms[t.name]
            total = v if total is None else total + v
    return total
