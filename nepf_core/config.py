"""Presets (``paper``, ``fast``, ``tiny``): one :class:`NePFConfig` composed of the config
dataclasses that live beside what they configure."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field

from nepf_core.fields.heads import HeadConfig
from nepf_core.fields.sdf_mlp import MLPSDFConfig
from nepf_core.losses import LossConfig
from nepf_core.model import ModelConfig
from nepf_core.render.renderer import RenderConfig
from nepf_core.train.rules.config import RuleConfig


@dataclass
class TrainConfig:
    """The optimisation loop."""

    iters: int = 250_000
    """Training steps (paper: 250k)."""
    batch_rays: int = 512
    """Rays per step (paper: 512)."""
    lr: float = 3e-4
    """Base learning rate (paper: 3e-4)."""
    lr_grid: float = 1e-2
    """Learning rate of grid-encoding parameters (fast preset)."""
    warmup_steps: int = 5000
    """Linear warm-up (NeuS: 5000)."""
    lr_alpha: float = 0.05
    """Cosine floor (NeuS: 0.05)."""
    anneal_end: int = 50_000
    """Steps of NeuS cosine annealing (0: none)."""
    seed: int = 0
    log_every: int = 10
    """Write a metrics record every N steps."""
    sync_every: int = 2500
    """Sync-PSNR of L_r / L_surf / L_vol every N steps (paper: 2500)."""
    sync_views: int = 2
    """Training views used for sync-PSNR."""
    sync_rays: int = 2048
    """Pixels per sync evaluation."""
    checkpoint_every: int = 5000
    """Checkpoint period in steps."""
    keep_checkpoints: int = 2
    eval_every_s: float = 0.0
    """Wall-clock period of held-out evaluation (0: only at the end, when a test set is given)."""
    eval_stride: int = 1
    """Render held-out views every N-th pixel (speed)."""
    unlit_rel_threshold: float = 0.01
    """A target pixel is unlit when ``max_c L_gt < unlit_rel_threshold * q99(foreground)``
    (:func:`nepf_core.rays.unlit_threshold`): such pixels do not train the albedo
    (``render.unlit_albedo_stopgrad``) and are left out of the lit-pixel metrics."""
    max_nonfinite_steps: int = 50
    """Fail the run after this many skipped (non-finite) steps."""
    grad_clip: float = 0.0
    """Clip the gradient norm (0: off)."""
    occupancy_every: int = 16
    """Occupancy-grid refresh period in steps (when the model has one)."""
    coarse_to_fine_frac: float = 0.3
    """Fraction of training over which grid levels are activated coarse-to-fine."""
    amp: bool = False
    """bf16 autocast for the head networks on CUDA (never on CPU); the SDF and density stay fp32
    (RenderConfig.amp_heads). No GradScaler: bf16 has fp32's exponent range."""
    ema_decay: float = 0.0
    """> 0: keep an exponential moving average of the parameters with this decay
    (:mod:`nepf_core.weight_average`) and use it for held-out evaluation and the saved model
    (render / export / eval); training uses the live weights. 0: off (the paper)."""
    adaptive: bool = False
    """Let fit() leave out what the scene does not need (:mod:`nepf_core.train.rules`: drop the
    GGX lobe, switch the Hessian term, stop at a plateau, leave empty rays out; every decision in
    report.json). Off in ``paper`` (the paper trains every term for its whole schedule)."""


_MOVED = (("unlit_rel_threshold", "render", "train"), ("plateau_patience", "train", "rules"),
          ("plateau_window", "train", "rules"), ("plateau_min_frac", "train", "rules"),
          ("plateau_cooldown_frac", "train", "rules"))
"""``(key, old section, new section)`` of fields that moved (config.json of older runs)."""


@dataclass
class NePFConfig:
    """Everything ``fit()`` needs besides the data."""

    name: str = "paper"
    model: ModelConfig = field(default_factory=ModelConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    rules: RuleConfig = field(default_factory=RuleConfig)
    """The adaptivity rules' constants (used with ``train.adaptive``)."""

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    def check(self) -> None:
        """ValueError for settings that contradict each other (fit() calls it)."""
        if (self.loss.w_albedo_smooth > 0 or self.loss.w_brdf_smooth > 0) and self.render.albedo_smooth_sigma <= 0:
            raise ValueError("loss.w_albedo_smooth / loss.w_brdf_smooth > 0 need render.albedo_smooth_sigma > 0 "
                             "(the jitter of the smoothness priors); set it, or set the weights to 0")
        if self.loss.w_normal_smooth > 0 and not (self.render.albedo_smooth_sigma > 0 and self.render.surface_refine
                                                  and self.render.alpha_mode == "sample"):
            raise ValueError("loss.w_normal_smooth > 0 needs render.surface_refine with render.alpha_mode = \"sample\" "
                             "and render.albedo_smooth_sigma > 0 (the prior reads the normals at the refined surface "
                             "point and its jittered points); set them, or set the weight to 0")
        if self.loss.w_material_evidence > 0 and self.render.bsdf_kind != "gltf":
            raise ValueError("loss.w_material_evidence > 0 needs render.bsdf_kind = \"gltf\" (the evidence fits "
                             "the glTF BSDF); set it, or set the weight to 0")
        if self.loss.w_albedo_fill > 0 and self.model.light != "emitters":
            raise ValueError("loss.w_albedo_fill > 0 needs model.light = \"emitters\" (the prior finds the points no "
                             "light reaches by the traced shadows); set it, or set the weight to 0")

    @staticmethod
    def from_dict(d: dict) -> "NePFConfig":
        """The config of a ``config.json``. Keys no field has (removed since) are ignored; a key that
        moved is read from where older runs wrote it (``render.unlit_rel_threshold``,
        ``train.plateau_*``)."""
        sections = {k: dict(d.get(k, {})) for k in ("render", "train", "rules")}
        for key, old, new in _MOVED:
            if key in sections[old] and key not in sections[new]:
                sections[new][key] = sections[old][key]
        d = {**d, **sections}

        def build(cls, data):
            kwargs = {}
            for f in dataclasses.fields(cls):
                if f.name not in data:
                    continue
                v = data[f.name]
                if dataclasses.is_dataclass(f.default_factory() if f.default_factory is not dataclasses.MISSING else None) and isinstance(v, dict):
                    sub = f.default_factory()
                    v = build(type(sub), v)
                elif isinstance(v, list):
                    v = tuple(v)
                kwargs[f.name] = v
            return cls(**kwargs)
        return build(NePFConfig, d)


def paper() -> NePFConfig:
    """The supplementary's architecture: 8x256 SDF (softplus, see sdf_mlp) and photon (ReLU)
    networks, 8x256 SIREN radiance and material networks, 512 rays, 64 + 64 samples, 250k steps
    at learning rate 3e-4. No adaptivity: every loss term and the GGX lobe stay on for the
    whole schedule."""
    return NePFConfig(name="paper")


def tiny() -> NePFConfig:
    """Small networks for tests: seconds on a CPU, same code paths as ``paper``."""
    head = HeadConfig(width=32, depth=2, activation="relu", n_freqs_v=2)
    return NePFConfig(
        name="tiny",
        model=ModelConfig(sdf_mlp=MLPSDFConfig(width=64, depth=3, feature_dim=32, n_freqs=4, skips=(), weight_norm=False),
                          radiance=head, photon=HeadConfig(width=32, depth=2), material=head),
        render=RenderConfig(n_samples=24, n_importance=8, up_sample_steps=1, hessian_fraction=0.05),
        train=TrainConfig(iters=100, batch_rays=128, lr=5e-4, warmup_steps=20, anneal_end=100, log_every=5,
                          sync_every=50, sync_rays=512, checkpoint_every=50, eval_stride=2, adaptive=True),
    )


def fast() -> NePFConfig:
    """Grid SDF + small heads + finite-difference normals + an occupancy grid (rays that meet no
    occupied cell leave the training batch; NeuS coarse + importance samples on the others),
    adaptivity on, a parameter average for evaluation and export, and three albedo priors the
    paper does not have: unlit pixels do not train the albedo, a small albedo smoothness term
    (docs/FAST.md, "Albedo in unlit regions"), and, only once adaptivity has dropped the specular
    lobe, an albedo flatness term (docs/FAST.md, "What fixed it"). L_surf is shaded at the SDF
    zero crossing of the max-weight section (``render.surface_refine``, docs/FAST.md "Shading
    L_surf at the zero crossing"). It shades with the glTF metallic-roughness BRDF
    (``render.bsdf_kind="gltf"``: Lambert + Smith GGX), the BRDF three.js and Blender render the
    exported GLB with, so its roughness and metallic mean there what they meant in training;
    ``paper`` keeps the supplementary's BSDF (:mod:`nepf_core.bsdf`). Three material priors
    (docs/FAST.md, "Materials: saturation and the unseen lobe"): the material logits stay within
    ±3 (no saturated channel), metallic costs where its lobe is not seen (a texture cannot hide in a
    ``(1 - m)`` dimmer), and roughness and metallic share the albedo's smoothness prior; the
    trade-off is that a metal seen away from its highlight comes out dielectric (bench/RESULTS.md).
    Against that prior, the metal evidence (``w_material_evidence``): at a few lit surface points a
    step, the radiance network's colours from other training cameras fitted as a metal and as a
    dielectric pull the metallic toward the kind that fits (docs/FAST.md, "Metal evidence from the
    radiance field across views"), and a decaying per-region record of those calls lifts the
    unseen-lobe prior where they say metal (``nepf_core/train/metal_record.py``).
    A second difference of the SDF normal across the surface (``w_normal_smooth``) smooths the
    grid's cell-scale normal noise, which a highlight shows, without flattening true curvature
    (docs/FAST.md, "Normals: a second difference of the normal at the surface").
    The light is not the paper's photon network but two global point emitters whose shadows are
    traced through the SDF (``model.light = "emitters"``, :mod:`nepf_core.fields.emitters`): every
    point's light must come from one place, so texture cannot hide in per-point light directions,
    and a dark pixel under a traced light trains the albedo (a black texture) while one in a
    traced shadow does not; where no light reaches, the albedo is pulled weakly toward the lit
    mean (``w_albedo_fill``; docs/FAST.md, "The light model"). The paper's light-variance terms
    are off (``w_light = 0``): with traced shadows the irradiance is 0 or ``E``, and
    ``|var x - var I|`` is lowered by dimming the emitters (bench/RESULTS.md v56). Without masks, the points triangulated in front of the support plane pull the SDF's
    zero level set onto them (``w_surface_points``, Geo-NeuS; docs/ARCHITECTURE.md, the object
    frame). The colour networks' logits stay within ±9 (``w_colour_range``): a black background
    without masks otherwise saturates them for good (docs/FAST.md, "Colours out of saturation").
    Options tried for this preset and not adopted: docs/TRIED.md."""
    head = HeadConfig(width=64, depth=2, activation="relu", n_freqs_v=4)
    return NePFConfig(
        name="fast",
        model=ModelConfig(sdf_kind="grid", radiance=head, light="emitters",
                          photon=HeadConfig(width=64, depth=2, n_freqs_x=2, use_feature=False),
                          material=HeadConfig(width=64, depth=2), occupancy_resolution=64),
        render=RenderConfig(n_samples=24, n_importance=8, up_sample_steps=1,
                            normals="fd", alpha_mode="sample", head_weight_threshold=1e-4,
                            eikonal_fraction=0.1, unlit_albedo_stopgrad=True, albedo_smooth_sigma=0.02,
                            surface_refine=True, bsdf_kind="gltf"),
        loss=LossConfig(w_hessian=0.0, w_surface_points=0.1, w_albedo_smooth=2e-4, w_albedo_flat=3e-6,
                        w_albedo_fill=2e-5, w_brdf_smooth=2e-4, w_material_range=1e-4, w_colour_range=1e-2,
                        w_metallic_unseen=1e-4, w_material_evidence=1e-3, w_normal_smooth=0.025, w_light=0.0,
                        lambda4=0.0, lambda5=0.0),
        train=TrainConfig(iters=20_000, batch_rays=1024, lr=5e-3, lr_grid=2e-2, warmup_steps=200,
                          anneal_end=2000, log_every=20, sync_every=500, checkpoint_every=1000,
                          eval_every_s=60.0, eval_stride=1, ema_decay=0.995, adaptive=True),
    )


PRESETS = {"paper": paper, "fast": fast, "tiny": tiny}


def preset(name: str) -> NePFConfig:
    """The preset called ``name`` (``paper|fast|tiny``); ValueError otherwise."""
    if name not in PRESETS:
        raise ValueError(f"unknown config {name!r}: choose one of {', '.join(PRESETS)}")
    return PRESETS[name]()
