"""The NePF model: one SDF density field shared by radiance, photon and material networks."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from nepf_core.fields.background import BackgroundConfig, BackgroundVolume
from nepf_core.fields.heads import Deviation, HeadConfig, MaterialField, PhotonField, RadianceField
from nepf_core.fields.sdf_grid import GridSDF, GridSDFConfig
from nepf_core.fields.sdf_mlp import MLPSDF, MLPSDFConfig


@dataclass
class ModelConfig:
    """Network architecture (defaults: the paper's supplementary)."""

    sdf_kind: str = "mlp"
    """``mlp`` (paper) or ``grid`` (fast)."""
    sdf_mlp: MLPSDFConfig = field(default_factory=MLPSDFConfig)
    """Used when ``sdf_kind == "mlp"``."""
    sdf_grid: GridSDFConfig = field(default_factory=GridSDFConfig)
    """Used when ``sdf_kind == "grid"`` (fast)."""
    radiance: HeadConfig = field(default_factory=lambda: HeadConfig(activation="siren", n_freqs_v=4))
    """Outgoing radiance network (paper: 8x256 SIREN)."""
    photon: HeadConfig = field(default_factory=lambda: HeadConfig(activation="relu"))
    """Photon network (paper: 8x256 ReLU)."""
    light: str = "photon"
    """``photon``: the paper's per-point light; ``emitters``: ``emitters`` global point emitters
    with shadows traced through the SDF (:mod:`nepf_core.fields.emitters`)."""
    emitters: int = 2
    """``K``, the number of emitters (``light="emitters"``)."""
    material: HeadConfig = field(default_factory=lambda: HeadConfig(activation="siren"))
    """Material network (paper: 8x256 SIREN)."""
    init_variance: float = 0.3
    """NeuS deviation init: inv_s = exp(10 * 0.3) = 20."""
    background: bool = False
    """A background volume outside the unit sphere (:mod:`nepf_core.fields.background`). fit()
    decides it from the data (:mod:`nepf_core.train.rules.masks`: on without masks, and with masks
    whose images show something outside them) and builds the model with its run state's choice."""
    background_volume: BackgroundConfig = field(default_factory=BackgroundConfig)
    """Its sampling and capacity."""
    object_halfspace: tuple[float, float, float, float] | None = None
    """``(n_x, n_y, n_z, c)``: the object lies where ``n . x + c > 0`` (in front of the support plane
    that fit() found in a capture without masks, :mod:`nepf_core.data.object_region`); the
    renderer ends the SDF's part of each ray there and the background volume takes the rest, and
    :class:`ModelFieldQuery` cuts the SDF to it. None: the whole unit sphere. A run decision:
    fit() builds the model with its run state's value."""
    occupancy_resolution: int = 0
    """Occupancy grid resolution (0: none)."""


def build_sdf(cfg: ModelConfig) -> nn.Module:
    if cfg.sdf_kind == "mlp":
        return MLPSDF(cfg.sdf_mlp)
    if cfg.sdf_kind == "grid":
        return GridSDF(cfg.sdf_grid)
    raise ValueError(f"unknown sdf_kind {cfg.sdf_kind!r} (mlp|grid)")


def build_light(cfg: ModelConfig, feature_dim: int) -> nn.Module:
    """The light model: a :class:`PhotonField` or a
    :class:`~nepf_core.fields.emitters.TracedEmitters` (both ``forward(x, n, feature) ->
    (light_dir [N, 3], intensity [N])``)."""
    if cfg.light == "photon":
        return PhotonField(cfg.photon, feature_dim)
    if cfg.light == "emitters":
        from nepf_core.fields.emitters import TracedEmitters
        return TracedEmitters(cfg.emitters)
    raise ValueError(f"unknown light model {cfg.light!r} (photon|emitters)")


class NePFModel(nn.Module):
    """All fields of one NePF scene (normalised frame)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.sdf = build_sdf(cfg)
        F = self.sdf.feature_dim
        self.radiance = RadianceField(cfg.radiance, F)
        self.photon = build_light(cfg, F)
        self.material = MaterialField(cfg.material, F)
        self.deviation = Deviation(cfg.init_variance)
        self.background = BackgroundVolume(cfg.background_volume) if cfg.background else None
        self.occupancy = None
        if cfg.occupancy_resolution > 0:
            from nepf_core.render.occupancy import OccupancyConfig, OccupancyGrid
            self.occupancy = OccupancyGrid(OccupancyConfig(resolution=cfg.occupancy_resolution))
            r = cfg.occupancy_resolution
            # cells the masks' visual hull allows (all True without masks)
            self.register_buffer("hull", torch.ones(r, r, r, dtype=torch.bool))

    # ---- the FieldQuery protocol used by export and evaluation (normalised frame) ----
    @torch.no_grad()
    def query_sdf(self, x: Tensor) -> Tensor:
        return self.sdf.sdf(x)

    def query_normal(self, x: Tensor) -> Tensor:
        from nepf_core.fields.gradients import sdf_gradient_autograd
        _, _, g = sdf_gradient_autograd(self.sdf, x, create_graph=False)
        return (g / g.norm(dim=-1, keepdim=True).clamp_min(1e-8)).detach()

    @torch.no_grad()
    def query_material(self, x: Tensor, n: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        _, feat = self.sdf(x)
        return self.material(x, n, feat)

    @torch.no_grad()
    def query_light(self, x: Tensor, n: Tensor) -> tuple[Tensor, Tensor]:
        _, feat = self.sdf(x)
        return self.photon(x, n, feat)


class ModelFieldQuery:
    """Adapter from :class:`NePFModel` to the export's FieldQuery protocol (chunked)."""

    def __init__(self, model: NePFModel, chunk: int = 65536, *, shading=None) -> None:
        """``shading``: the run's :class:`nepf_core.render.renderer.Shading`. Without the GGX
        lobe :meth:`material` returns the material the surface was shaded with, metallic 0
        (:func:`nepf_core.bsdf.diffuse_only_material` with ``shading.diffuse_metal_weight``);
        None: the network's material as it is."""
        self.model = model
        self.chunk = chunk
        self.shading = shading

    def _chunks(self, fn, *xs):
        outs = [fn(*[x[i:i + self.chunk] for x in xs]) for i in range(0, xs[0].shape[0], self.chunk)]
        if isinstance(outs[0], tuple):
            return tuple(torch.cat([o[j] for o in outs]) for j in range(len(outs[0])))
        return torch.cat(outs)

    def sdf(self, x: Tensor) -> Tensor:
        """The SDF; with an object half-space the object's part of it, ``max(f, |x| - 1, -(n . x + c))``
        (a CSG intersection with the region the renderer gave the SDF: the cut is capped flat)."""
        f = self._chunks(self.model.query_sdf, x).reshape(-1)
        hs = self.model.cfg.object_halfspace
        if hs is None:
            return f
        n = torch.as_tensor(hs[:3], dtype=x.dtype, device=x.device)
        return torch.maximum(torch.maximum(f, torch.linalg.vector_norm(x, dim=-1) - 1.0), -(x @ n + float(hs[3])))

    def normal(self, x: Tensor) -> Tensor:
        return self._chunks(self.model.query_normal, x)

    def material(self, x: Tensor, n: Tensor):
        albedo, rough, metal = self._chunks(self.model.query_material, x, n)
        if self.shading is not None and not self.shading.specular:
            from nepf_core.bsdf import diffuse_only_material
            albedo, rough, metal = diffuse_only_material(albedo, rough, metal, self.shading.diffuse_metal_weight)
        return albedo, rough, metal

    def light(self, x: Tensor, n: Tensor):
        return self._chunks(self.model.query_light, x, n)

    @torch.no_grad()
    def emitters(self) -> tuple[Tensor, Tensor] | None:
        """The learned global emitters ``(positions [K, 3] normalised frame, radiant intensity
        [K])`` with ``model.light = "emitters"``; None with the photon network."""
        from nepf_core.fields.emitters import TracedEmitters
        light = self.model.photon
        if not isinstance(light, TracedEmitters):
            return None
        return light.positions.detach().clone(), light.log_intensity.detach().exp()
