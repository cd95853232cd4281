"""NePF losses: the loss is ``sum_k w_k L_k`` over the named terms of :data:`LOSS_TERMS`.

Each term is a pure function of one :class:`LossBatch` (the step's render, its rays and the values
several terms share); :class:`LossConfig` weights it, and a weight of 0 switches it off. By family,
each module with its formulas:

* :mod:`~nepf_core.losses.colour`: ``L_r``, ``L_surf``, ``L_vol`` (the paper's three), ``L_bg`` and
  the colour logits' range;
* :mod:`~nepf_core.losses.geometry`: eikonal, Hessian, mask, the normal's second difference, the
  sparse surface points;
* :mod:`~nepf_core.losses.light`: the paper's light-variance term;
* :mod:`~nepf_core.losses.material`: the material priors and the metal terms;
* :mod:`~nepf_core.losses.batch`: :class:`LossBatch` and the masked means;
* :mod:`~nepf_core.losses.registry`: :data:`LOSS_TERMS`, :func:`compute_losses`, :func:`total_loss`.
"""

from nepf_core.losses.batch import LossBatch, l1_masked, loss_batch, mean_where, weighted_mean
from nepf_core.losses.config import LossConfig
from nepf_core.losses.geometry import mask_bce
from nepf_core.losses.light import batch_variance, light_variance_loss
from nepf_core.losses.registry import (LOSS_TERMS, LossTerm, compute_losses, needs_jitter_normals, needs_lobe_split,
                                       total_loss)

__all__ = ["LOSS_TERMS", "LossBatch", "LossConfig", "LossTerm", "batch_variance", "compute_losses", "l1_masked",
           "light_variance_loss", "loss_batch", "mask_bce", "mean_where", "needs_jitter_normals", "needs_lobe_split",
           "total_loss", "weighted_mean"]
