"""Where the metal evidence has said "metal": a decaying record per region of the object frame.

The unseen-lobe prior (``loss.w_metallic_unseen``, ``m (1 - s)``) assumes a dielectric wherever a
lobe is not seen, and a metal seen away from its highlight looks like a darker dielectric, so the
prior turned every metal dielectric (bench/RESULTS.md v22-v36). The material evidence
(:mod:`nepf_core.render.material_evidence`) says which kind fits the radiance across views, but
only at a few lit points a step (``POINTS_PER_STEP``); the prior acts on every lit ray. This
record carries the evidence from those few points to every ray in the same region, so that the
prior is lifted where the evidence says metal and kept where it says dielectric or nothing.

Each cell ``c`` of a ``G^3`` grid over ``[-1, 1]^3`` (the normalised frame; ``G`` =
:data:`RESOLUTION`) keeps two sums that decay by ``gamma`` (:data:`DECAY`) per step, over the
evidence points ``p`` that fell in it at steps ``t <= T``:

    M_c = sum_(t, p) gamma^(T - t) q_p m*_p,        Q_c = sum_(t, p) gamma^(T - t) q_p
    share(x) = M_c(x) / (Q_c(x) + q0)                                       (q0 = PRIOR_CONFIDENCE)

``m*`` is the evidence's metallic target (0 or 1) and ``q`` its confidence. ``share`` is near 1
where the evidence has said metal confidently and repeatedly, near 0 where it said dielectric or
has not spoken (``q0``: the evidence a cell needs before it counts; an empty cell keeps the prior).
The prior becomes ``m (1 - s) (1 - share)``.

Why a grid and not the per-point evidence alone: with the prior excused only at the evidence's
own 64 points, it still pressed every other lit point, and a partial excuse keeps a metal at the
range prior's floor (docs/TRIED.md, the view-spread rows). Why it decays: the evidence changes as
the radiance field and the light sharpen (a probe on bunny_metal: 25 % of its points called metal
at step 100, 73 % at step 300), and a call made on a blurred early field should not stand.

Cost: two ``G^3`` float tensors (256 KB at ``G = 32``), two ``index_add_`` of 64 points and a
gather per lit ray per step.
"""

from __future__ import annotations

import torch
from torch import Tensor

RESOLUTION = 32
"""``G``: cells per axis over ``[-1, 1]`` (a cell is 1/16 of the unit radius)."""
DECAY = 0.99
"""``gamma`` per step: the record's half-life is ~69 steps, about 4,400 evidence points."""
PRIOR_CONFIDENCE = 0.25
"""``q0``: the summed confidence a cell's metal calls must pass for its share to pass a half
(one call at ``q = 0.3`` gives 0.55; a probe on bunny_metal saw a step's mean ``q`` at 0.24-0.36)."""


class MetalRecord:
    """The record of the module docstring on ``device``."""

    def __init__(self, device: torch.device | str, resolution: int = RESOLUTION, decay: float = DECAY,
                 prior_confidence: float = PRIOR_CONFIDENCE):
        if resolution < 1 or not 0.0 < decay <= 1.0 or prior_confidence <= 0.0:
            raise ValueError(f"MetalRecord: resolution >= 1, 0 < decay <= 1 and prior_confidence > 0 "
                             f"(got {resolution}, {decay}, {prior_confidence})")
        self.resolution, self.decay, self.prior_confidence = resolution, decay, prior_confidence
        self.metal = torch.zeros(resolution ** 3, device=device)
        self.confidence = torch.zeros(resolution ** 3, device=device)

    def cells(self, x: Tensor) -> Tensor:
        """``[N]`` long: the flat cell index of each point ``x [N, 3]`` (points outside
        ``[-1, 1]^3`` fall in the nearest boundary cell)."""
        g = self.resolution
        ijk = ((x.detach().float() + 1.0) * (0.5 * g)).floor().long().clamp(0, g - 1)
        return (ijk[:, 0] * g + ijk[:, 1]) * g + ijk[:, 2]

    @torch.no_grad()
    def update(self, x: Tensor, metallic_target: Tensor, confidence: Tensor) -> None:
        """One step: decay both sums, then add the evidence at ``x [P, 3]`` (``metallic_target``,
        ``confidence``: ``[P]``; ``P`` may be 0, a step without evidence still decays)."""
        self.metal.mul_(self.decay)
        self.confidence.mul_(self.decay)
        if x.shape[0] == 0:
            return
        i = self.cells(x).to(self.metal.device)
        q = confidence.detach().to(self.metal)
        self.metal.index_add_(0, i, q * metallic_target.detach().to(self.metal))
        self.confidence.index_add_(0, i, q)

    @torch.no_grad()
    def metal_share(self, x: Tensor) -> Tensor:
        """``[N]`` in ``[0, 1)``: ``share(x)`` of the module docstring at ``x [N, 3]``."""
        i = self.cells(x).to(self.metal.device)
        return (self.metal[i] / (self.confidence[i] + self.prior_confidence)).to(x.device)

    def state_dict(self) -> dict:
        return {"metal": self.metal.cpu(), "confidence": self.confidence.cpu()}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` (a resumed run keeps what the evidence said); a record of
        another resolution is an error."""
        if state["metal"].shape != self.metal.shape:
            raise ValueError(f"metal record of {state['metal'].numel()} cells, expected {self.metal.numel()}")
        self.metal.copy_(state["metal"])
        self.confidence.copy_(state["confidence"])
