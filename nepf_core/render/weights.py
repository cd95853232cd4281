"""Stage 1 of the renderer: samples on each ray, their SDF, the NeuS weights and the SDF regularisers.

One function per alpha mode (:attr:`nepf_core.render.renderer.RenderConfig.alpha_mode`), both
returning :class:`SampleWeights` for ``R`` rays of ``S`` samples (``P = R S``):

* :func:`weights_sample_mode`: the SDF at the samples ``x_i = o + t_i d`` and
  ``alpha_i = clip((Phi(s f_i) - Phi(s f_{i+1}) + 1e-5) / (Phi(s f_i) + 1e-5), 0, 1)``, the last
  sample's alpha 0. No gradient is needed for the weights, so the gradient (tetrahedral finite
  differences) is taken only where a head will be evaluated (``w_i > head_weight_threshold``,
  and each ray's max-weight sample) plus a random ``eikonal_fraction`` of the samples.
* :func:`weights_midpoint_mode`: NeuS's section opacity from the SDF at the section midpoints
  ``t_i + delta_i / 2`` and the annealed ray-normal cosine (needs the gradient at every sample:
  autograd or central differences), plus the Hessian norm on a random ``hessian_fraction``.

Then ``w_i = alpha_i prod_{j<i} (1 - alpha_j + 1e-7)`` (:func:`nepf_core.render.neus.weights_from_alpha`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from nepf_core.fields.fd_normals import sdf_gradient_fd
from nepf_core.fields.gradients import sdf_gradient_autograd, sdf_hessian_norm
from nepf_core.render.neus import alpha_from_sdf, annealed_cos, max_weight_index, weights_from_alpha


@dataclass
class SampleWeights:
    """The samples of ``R`` rays (``S`` each, ``P = R S`` flattened ray-major) and their weights."""

    z: Tensor
    """``[R, S]`` sample depths ``t_i`` along each ray (the section starts)."""
    t_eval: Tensor
    """``[R, S]`` depths where the SDF was evaluated: ``z`` (sample mode) or the section midpoints
    (midpoint mode); the expected depth is ``sum_i w_i t_eval_i``."""
    pts: Tensor
    """``[P, 3]`` the points ``o + t_eval d``."""
    dirs: Tensor
    """``[P, 3]`` each point's ray direction."""
    sdf: Tensor
    """``[R, S]`` the SDF ``f`` at ``pts``."""
    feat: Tensor
    """``[P, F]`` the SDF network's features at ``pts``."""
    grad: Tensor
    """``[P, 3]`` ``grad f`` (sample mode: zero where it was not taken)."""
    grad_norm: Tensor
    """``[P]`` ``|grad f|`` (one node for the eikonal and the normals: the gradients of both meet
    there, in the order they always have)."""
    weights: Tensor
    """``[R, S]`` the NeuS weights ``w_i``."""
    idx_max: Tensor
    """``[R]`` long: each ray's max-weight sample ``i* = argmax_i w_i`` (0 where all are 0)."""
    w_max: Tensor
    """``[R]`` ``w_{i*}``."""
    eikonal: Tensor
    """``[E]`` ``| |grad f| - 1 |`` at the points inside the unit sphere that have a gradient."""
    eikonal_ray: Tensor
    """``[E]`` long: the ray of each ``eikonal`` value."""
    hessian: Tensor
    """``[Q]`` ``|H f|_F`` on a random subset (midpoint mode, training; else empty)."""
    inv_s: Tensor
    """``[]`` the NeuS sharpness ``s`` the weights were computed with."""

    @property
    def flat_max(self) -> Tensor:
        """``[R]`` the max-weight samples' indices into the flattened ``[P]`` samples."""
        R, S = self.weights.shape
        return torch.arange(R, device=self.weights.device) * S + self.idx_max


def _expand(t: Tensor, S: int) -> Tensor:
    """``[R, C] -> [R S, C]``: each row repeated for the ``S`` samples of its ray."""
    return t[:, None, :].expand(-1, S, -1).reshape(-1, t.shape[-1])


def weights_sample_mode(model, o: Tensor, d: Tensor, z: Tensor, inv_s: Tensor, *, head_threshold: float,
                        eikonal_fraction: float, train: bool) -> SampleWeights:
    """Sample-mode weights (module docstring) for rays ``o, d [R, 3]`` at depths ``z [R, S]``.

    The random eikonal subset is drawn from torch's global generator (``torch.rand``)."""
    R, S = z.shape
    sdf_only = model.sdf.sdf
    pts = (o[:, None, :] + d[:, None, :] * z[..., None]).reshape(-1, 3)
    sdf, feat = model.sdf(pts)
    f = sdf.reshape(R, S)
    prev_cdf = torch.sigmoid(f[:, :-1] * inv_s)
    next_cdf = torch.sigmoid(f[:, 1:] * inv_s)
    alpha = ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clip(0.0, 1.0)
    alpha = torch.cat([alpha, torch.zeros_like(alpha[:, :1])], -1)
    weights = weights_from_alpha(alpha)
    idx_max, w_max = max_weight_index(weights)
    # gradients (FD) only where a head is evaluated, plus a random subset for the eikonal
    need = weights.reshape(-1).detach() > head_threshold
    need[torch.arange(R, device=o.device) * S + idx_max] = True
    if train and eikonal_fraction > 0:
        need |= torch.rand(need.shape, device=o.device) < eikonal_fraction
    gidx = need.nonzero(as_tuple=True)[0]
    g_sub, _ = sdf_gradient_fd(sdf_only, pts[gidx], model.sdf.fd_step(), scheme="tetra", center="mean")
    grad = pts.new_zeros(pts.shape[0], 3).index_copy(0, gidx, g_sub)
    inside_sub = pts[gidx].norm(dim=-1) < 1.0
    eikonal = (g_sub.norm(dim=-1) - 1.0).abs()[inside_sub]
    eik_ray = torch.div(gidx, S, rounding_mode="floor")[inside_sub]
    return SampleWeights(z=z, t_eval=z, pts=pts, dirs=_expand(d, S), sdf=f, feat=feat, grad=grad,
                         grad_norm=grad.norm(dim=-1), weights=weights,
                         idx_max=idx_max, w_max=w_max, eikonal=eikonal, eikonal_ray=eik_ray,
                         hessian=o.new_zeros(0), inv_s=inv_s)


def weights_midpoint_mode(model, o: Tensor, d: Tensor, z: Tensor, inv_s: Tensor, *, normals: str,
                          hessian_fraction: float, cos_anneal: float, train: bool) -> SampleWeights:
    """Midpoint-mode (NeuS) weights (module docstring) for rays ``o, d [R, 3]`` at depths ``z [R, S]``.

    ``normals``: ``autograd`` (double backward in training) or ``fd`` (central differences). The
    Hessian subset is drawn from torch's global generator (``torch.randint``)."""
    R, S = z.shape
    sdf_only = model.sdf.sdf
    dists = z[:, 1:] - z[:, :-1]
    dists = torch.cat([dists, dists[:, -1:].clamp_min(1e-4)], -1)
    mid = z + dists * 0.5
    pts = (o[:, None, :] + d[:, None, :] * mid[..., None]).reshape(-1, 3)
    dirs = _expand(d, S)
    if normals == "fd":
        sdf, feat = model.sdf(pts)
        grad, _ = sdf_gradient_fd(sdf_only, pts, model.sdf.fd_step(), scheme="central", center="mean")
    else:
        sdf, feat, grad = sdf_gradient_autograd(model.sdf, pts, create_graph=train)
    hess = o.new_zeros(0)
    if train and hessian_fraction > 0:  # |H f|_F on a random subset (fields/gradients.py)
        q = max(1, int(pts.shape[0] * hessian_fraction))
        sub = torch.randint(0, pts.shape[0], (q,), device=pts.device)
        hess = sdf_hessian_norm(sdf_only, pts[sub], model.sdf.fd_step(),
                                gradient="fd" if normals == "fd" else "autograd")
    cos = annealed_cos((dirs * grad).sum(-1), cos_anneal if train else 1.0)
    weights = weights_from_alpha(alpha_from_sdf(sdf.reshape(R, S), cos.reshape(R, S), dists, inv_s))
    idx_max, w_max = max_weight_index(weights)
    inside = pts.norm(dim=-1) < 1.0
    gnorm = grad.norm(dim=-1)
    eikonal = (gnorm - 1.0).abs()[inside]
    eik_ray = torch.div(torch.arange(pts.shape[0], device=o.device), S, rounding_mode="floor")[inside]
    return SampleWeights(z=z, t_eval=mid, pts=pts, dirs=dirs, sdf=sdf.reshape(R, S), feat=feat, grad=grad,
                         grad_norm=gnorm, weights=weights, idx_max=idx_max, w_max=w_max, eikonal=eikonal, eikonal_ray=eik_ray,
                         hessian=hess, inv_s=inv_s)
