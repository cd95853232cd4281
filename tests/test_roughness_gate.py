"""The roughness gate (RenderConfig.roughness_gate_inv_s): the BSDF reads the roughness detached
while NeuS's sharpness is below the gate, so a colour loss moves the material network's roughness
only once the surface is sharp; the image itself does not change, and the metallic is not gated."""

import dataclasses
import math

import torch

from nepf_core.config import fast
from nepf_core.model import NePFModel
from nepf_core.render.shading import Shading, shade_points


def _grads(cfg, inv_s: float):
    torch.manual_seed(0)
    model = NePFModel(cfg.model)
    with torch.no_grad():
        model.deviation.variance.fill_(math.log(inv_s) / 10.0)           # inv_s = exp(10 v)
    assert abs(float(model.deviation().detach()) - inv_s) < 1e-3 * inv_s
    g = torch.Generator().manual_seed(1)
    x = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1) * 0.5
    n = torch.nn.functional.normalize(x, dim=-1)
    v = -torch.nn.functional.normalize(x + 0.3 * torch.randn(64, 3, generator=g), dim=-1)
    _, f = model.sdf(x)
    p = shade_points(model, cfg.render, Shading(), x, v, n, f.detach(), None, logits=True)
    rough_grad, metal_grad = torch.autograd.grad(p.pbr.sum(), [p.roughness, p.metallic], allow_unused=True)
    return p.pbr.detach(), rough_grad, metal_grad


def test_the_roughness_gets_no_colour_gradient_below_the_gate_and_one_above():
    cfg = fast()
    gate = cfg.render.roughness_gate_inv_s
    assert gate > 0
    below, r_below, m_below = _grads(cfg, 0.5 * gate)
    above, r_above, m_above = _grads(cfg, 2.0 * gate)
    assert r_below is not None and float(r_below.abs().sum()) == 0.0  # detached: no colour gradient
    assert r_above is not None and float(r_above.abs().sum()) > 0.0
    for m in (m_below, m_above):                                     # the metallic is never gated
        assert m is not None and float(m.abs().sum()) > 0.0
    torch.testing.assert_close(below, above)                        # the gate changes gradients, not images
    # without the gate (paper's 0) the roughness gets its gradient at any sharpness
    off = dataclasses.replace(cfg, render=dataclasses.replace(cfg.render, roughness_gate_inv_s=0.0))
    _, r_off, _ = _grads(off, 0.5 * gate)
    assert r_off is not None and float(r_off.abs().sum()) > 0.0
