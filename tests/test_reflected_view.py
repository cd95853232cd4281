"""The radiance network's reflected view input (``HeadConfig.view_input = "reflected"``, Ref-NeRF):
the reflection by hand, its invariants, and the reason for it (a highlight is a low-frequency
function of the reflected direction, so the same small network fits a mirror-like lobe on a
curved surface better from it than from the ray direction)."""

import math

import pytest
import torch
from torch.nn.functional import normalize

from nepf_core.config import NePFConfig, fast
from nepf_core.fields.heads import HeadConfig, RadianceField, reflected_view


def test_reflection_by_hand():
    # straight down onto an upward normal of length 2: back up, n.v = -1
    out = reflected_view(torch.tensor([[0.0, 0.0, -1.0]]), torch.tensor([[0.0, 0.0, 2.0]]))
    assert torch.allclose(out, torch.tensor([[0.0, 0.0, 1.0, -1.0]]))
    # 45 degrees in the x-z plane onto the z = 0 plane: the z component flips
    s = 1.0 / math.sqrt(2.0)
    out = reflected_view(torch.tensor([[s, 0.0, -s]]), torch.tensor([[0.0, 0.0, 1.0]]))
    assert torch.allclose(out, torch.tensor([[s, 0.0, s, -s]]), atol=1e-6)


def test_reflection_invariants():
    torch.manual_seed(0)
    v = normalize(torch.randn(500, 3), dim=-1)
    n = torch.randn(500, 3) * 3.0                       # unnormalised, as the SDF gradient
    out = reflected_view(v, n)
    r, vn = out[:, :3], out[:, 3]
    nu = normalize(n, dim=-1)
    assert torch.allclose(r.norm(dim=-1), torch.ones(500), atol=1e-5)            # a rotation keeps length
    assert torch.allclose((r * nu).sum(-1), -vn, atol=1e-5)                       # the normal component flips
    assert torch.allclose(r - (r * nu).sum(-1, keepdim=True) * nu,                # the tangent part stays
                          v - vn[:, None] * nu, atol=1e-5)
    assert torch.allclose(reflected_view(r, n)[:, :3], v, atol=1e-5)              # twice is the identity


SHARPNESS = 10.0


def _fit_error(view_input: str, seed: int = 0, steps: int = 200) -> float:
    """Held-out RMSE of a small radiance head fitted to a Phong-like mirror lobe on a unit sphere,
    ``L = exp(k (r . l - 1))``, k = SHARPNESS, with ``r`` the reflected ray and ``l`` a fixed light direction,
    seen from random directions in the upper hemisphere of each point."""
    g = torch.Generator().manual_seed(seed)
    light = normalize(torch.tensor([0.3, -0.4, 1.0]), dim=0)

    def sample(k):
        x = normalize(torch.randn(k, 3, generator=g), dim=-1)
        v = normalize(torch.randn(k, 3, generator=g), dim=-1)
        v = torch.where(((v * x).sum(-1) > 0)[:, None], -v, v)                 # rays that hit the outside
        r = reflected_view(v, x)[:, :3]
        return x, v, torch.exp(SHARPNESS * ((r * light).sum(-1) - 1.0))[:, None].expand(k, 3)

    torch.manual_seed(seed)
    head = RadianceField(HeadConfig(width=64, depth=2, activation="relu", n_freqs_v=4, view_input=view_input), 4)
    opt = torch.optim.Adam(head.parameters(), lr=5e-3)
    xs, vs, ts = sample(2048)
    feat = torch.zeros(2048, 4)
    for _ in range(steps):
        opt.zero_grad()
        ((head(xs, vs, xs, feat) - ts) ** 2).mean().backward()
        opt.step()
    xh, vh, th = sample(2048)
    with torch.no_grad():
        return float(((head(xh, vh, xh, torch.zeros(2048, 4)) - th) ** 2).mean().sqrt())


def test_reflected_input_fits_a_mirror_lobe_better():
    direction, reflected = _fit_error("direction"), _fit_error("reflected")
    assert reflected < 0.5 * direction, (reflected, direction)


def test_unknown_view_input_is_refused():
    with pytest.raises(ValueError, match="view_input"):
        RadianceField(HeadConfig(width=8, depth=1, view_input="halfway"), 4)


def test_view_input_survives_config_json():
    cfg = fast()
    cfg.model.radiance.view_input = "reflected"
    back = NePFConfig.from_dict(cfg.to_dict())
    assert back.model.radiance.view_input == "reflected"
