"""The switches in effect during a run, kept apart from the config the user asked for.

Adaptivity (:mod:`nepf_core.train.rules`) changes what is trained while a run goes on: it drops
the GGX lobe and fades it out, switches the Hessian term, and decides the background model and
the mask loss from the data. Those choices live here, not in the config: ``config.json`` stays
what the user asked for, the run state is saved in every checkpoint (restored on resume, read
by :func:`nepf_core.train.load.load_model`) and written to ``report.json``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from nepf_core.losses import LossConfig
from nepf_core.model import ModelConfig
from nepf_core.render.renderer import Shading


@dataclass
class RunState:
    """What the renderer, the losses and the model are built with right now."""

    specular: bool = True
    """Evaluate the GGX lobe (:class:`~nepf_core.render.renderer.Shading`)."""
    diffuse_metal_weight: float = 0.0
    """Lobe off: the fade weight ``w`` of ``(1 - w m) f_d(c) + w f_s`` (1 at the drop, then to 0)."""
    w_hessian: float = 0.0
    """Weight of the Hessian term in effect (the preset's, or 0 while the surface is smooth)."""
    background: bool = False
    """The model has a background volume (:mod:`nepf_core.fields.background`): captures without
    masks, and masks whose images are not black outside them (:mod:`nepf_core.train.rules.masks`)."""
    use_mask_loss: bool = False
    """The mask BCE applies (scenes with masks and ``loss.w_mask > 0``)."""
    object_halfspace: list[float] | None = None
    """``(n_x, n_y, n_z, c)``: the object is in front of the support plane found in a capture
    without masks (:mod:`nepf_core.data.object_region`); None: the whole unit sphere."""

    @classmethod
    def from_config(cls, cfg) -> "RunState":
        """The start of a run: everything as configured (the data decide the rest)."""
        return cls(specular=bool(cfg.render.specular), w_hessian=float(cfg.loss.w_hessian),
                   background=bool(cfg.model.background))

    def shading(self) -> Shading:
        return Shading(specular=self.specular, diffuse_metal_weight=self.diffuse_metal_weight)

    def loss_config(self, base: LossConfig) -> LossConfig:
        """``base`` with the Hessian weight in effect (a copy: the config is never written)."""
        return base if base.w_hessian == self.w_hessian else dataclasses.replace(base, w_hessian=self.w_hessian)

    def model_config(self, base: ModelConfig) -> ModelConfig:
        """``base`` with the background model and the object region in effect (a copy)."""
        hs = None if self.object_halfspace is None else tuple(float(v) for v in self.object_halfspace)
        return dataclasses.replace(base, background=self.background, object_halfspace=hs)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict, default: "RunState") -> "RunState":
        """Fields of ``d`` over ``default`` (unknown keys ignored)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return dataclasses.replace(default, **{k: v for k, v in d.items() if k in names})

    @classmethod
    def from_checkpoint(cls, extra: dict | None, cfg) -> "RunState":
        """The run state saved in a checkpoint's ``extra``; a checkpoint written before the run
        state existed kept the lobe switches with the adaptivity counters, and its config.json
        already carried the background decision."""
        extra = extra or {}
        start = cls.from_config(cfg)
        if "run_state" in extra:
            return cls.from_dict(extra["run_state"], start)
        legacy = extra.get("adaptivity") or {}
        return cls.from_dict({k: legacy[k] for k in ("specular", "diffuse_metal_weight", "w_hessian") if k in legacy},
                             start)
