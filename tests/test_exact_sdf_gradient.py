"""The grid SDF's exact gradient (issue 32): the lookup's spatial derivative from the same rows
(fields/trilinear.py), the head's input gradient in reverse mode (mlp.py), and their sum
``GridSDF.sdf_and_grad``, against hand-worked values, autograd and ``grid_sample``'s double
backward; and the renderer looking each gradient point up once (no finite-difference stencil)."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from grid_fixtures import level_volumes, random_grid
from nepf_core.fields.gradients import sdf_feature_and_gradient
from nepf_core.fields.sdf_grid import GridSDF, GridSDFConfig
from nepf_core.fields.sdf_mlp import MLPSDF, MLPSDFConfig
from nepf_core.fields.trilinear import trilinear_lookup, trilinear_lookup_with_gradient
from nepf_core.mlp import MLPConfig, build_mlp


def _grid(levels=3, feats=2, bound=1.0, seed=0):
    return random_grid(levels, feats, bound, seed)


def _points(n, bound, seed=1):
    """``n`` points in ``[-1.3, 1.3]^3 * bound``: about a third outside the grid's cube."""
    gen = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2.6 - 1.3) * bound


def test_a_linear_field_has_its_slope_everywhere_inside_and_zero_across_the_clamp():
    """Nodes holding ``a . p + b`` (``p`` the node's position): trilinear interpolation
    reproduces a linear function, so its derivative is ``a`` at every point inside the cube,
    and 0 along an axis where the point is clamped to the border."""
    g = _grid(levels=2, feats=1)
    a, b = torch.tensor([0.7, -1.9, 3.1], dtype=torch.float64), 0.25
    with torch.no_grad():
        for level, r in enumerate(g.resolutions):
            axis = torch.linspace(-1.0, 1.0, r, dtype=torch.float64)
            pz, py, px = torch.meshgrid(axis, axis, axis, indexing="ij")   # row (k R + j) R + i: x fastest
            g.level(level).copy_((a[0] * px + a[1] * py + a[2] * pz + b).reshape(-1, 1))
    x = _points(300, 1.0)
    value, slope = trilinear_lookup_with_gradient(g.table, x, g.layout, 2, 1.0)        # [N, L, 1], [N, L, 3, 1]
    clamped = x.clamp(-1.0, 1.0)
    assert torch.allclose(value[..., 0], (clamped @ a + b)[:, None].expand(-1, 2), atol=1e-12)
    expect = a * (x.abs() <= 1.0)                                                        # [N, 3]
    assert torch.allclose(slope[..., 0], expect[:, None, :].expand(-1, 2, -1), atol=1e-12)
    assert (x.abs() > 1.0).any() and (x.abs() <= 1.0).all(-1).any()


@pytest.mark.parametrize("bound", [1.0, 2.0])
def test_value_and_derivative_match_the_lookup_and_its_autograd(bound):
    g = _grid(bound=bound)
    x = _points(400, bound).requires_grad_()
    value, slope = trilinear_lookup_with_gradient(g.table.detach(), x.detach(), g.layout, 3, bound)
    plain = trilinear_lookup(g.table.detach(), x, g.layout, 3, bound)                    # [N, L, F]
    assert torch.allclose(value, plain.detach(), atol=1e-13)
    for level in range(3):
        for feat in range(2):
            (ref,) = torch.autograd.grad(plain[:, level, feat].sum(), x, retain_graph=True)
            assert torch.allclose(slope[:, level, :, feat], ref, atol=1e-12)


def test_table_gradient_of_a_loss_on_the_derivative_matches_grid_sample_double_backward():
    """An eikonal-like loss on the derivative trains the table: the rows scattered into
    ``table.grad`` equal ``grid_sample``'s (value and derivative through
    ``autograd.grad(create_graph=True)``), level by level."""
    g = _grid()
    vols = level_volumes(g)
    x = _points(300, 1.0)
    gen = torch.Generator().manual_seed(5)
    w_val, w_der = torch.randn(300, 3, 2, generator=gen, dtype=torch.float64), torch.randn(300, 3, 3, 2, generator=gen,
                                                                                            dtype=torch.float64)
    value, slope = trilinear_lookup_with_gradient(g.table, x, g.layout, 3, 1.0)
    ((value * w_val).sum() + (slope * w_der).square().sum()).backward()
    xr = x.clone().requires_grad_()
    loss = 0.0
    for level, v in enumerate(vols):
        ref = F.grid_sample(v, xr.view(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border",
                            align_corners=True).view(2, -1).t()                             # [N, F]
        for feat in range(2):
            (d,) = torch.autograd.grad(ref[:, feat].sum(), xr, create_graph=True)          # [N, 3]
            loss = loss + (d * w_der[:, level, :, feat]).square().sum()
        loss = loss + (ref * w_val[:, level]).sum()
    loss.backward()
    for level, v in enumerate(vols):
        rows = g.table.grad[g.first_rows[level]:g.first_rows[level] + v[0, 0].numel()]
        assert torch.allclose(rows, v.grad.reshape(2, -1).t(), atol=1e-10)


def test_point_gradient_through_the_derivative_weights():
    """The derivative's own dependence on ``x`` (the mixed second derivatives of trilinear
    interpolation) reaches ``x`` through autograd: gradcheck against finite differences."""
    g = _grid()
    table = g.table.detach()
    x = _points(40, 1.0, seed=3).clamp(-0.95, 0.95).requires_grad_()

    def derivative(p):
        return trilinear_lookup_with_gradient(table, p, g.layout, 3, 1.0)[1]

    assert torch.autograd.gradcheck(derivative, (x,), eps=1e-7, atol=1e-6)


@pytest.mark.parametrize("activation,skips,weight_norm", [("relu", (), False), ("softplus", (2,), True)])
def test_head_input_gradient_matches_autograd_and_trains_like_double_backward(activation, skips, weight_norm):
    torch.manual_seed(0)
    mlp = build_mlp(MLPConfig(in_dim=7, out_dim=4, width=16, depth=3, activation=activation, skips=skips,
                              weight_norm=weight_norm, softplus_beta=10.0)).double()
    x = torch.randn(50, 7, dtype=torch.float64).requires_grad_()
    y, dy = mlp.forward_with_input_gradient(x, out_index=2)
    assert torch.equal(y, mlp(x))
    (ref,) = torch.autograd.grad(mlp(x)[:, 2].sum(), x, create_graph=True)
    assert torch.allclose(dy, ref, atol=1e-12)
    params = [p for p in mlp.parameters()]
    mine = torch.autograd.grad(dy.square().sum(), params, allow_unused=True, materialize_grads=True)
    theirs = torch.autograd.grad(ref.square().sum(), params, allow_unused=True, materialize_grads=True)
    for a, b in zip(mine, theirs):
        assert torch.allclose(a, b, atol=1e-10)


def test_head_input_gradient_refuses_an_activation_it_cannot_differentiate():
    mlp = build_mlp(MLPConfig(in_dim=3, out_dim=2, width=8, depth=1, activation="siren"))
    with pytest.raises(ValueError, match="siren"):
        mlp.forward_with_input_gradient(torch.zeros(2, 3))


def _grid_sdf(seed=0):
    torch.manual_seed(seed)
    sdf = GridSDF(GridSDFConfig(n_levels=3, base_resolution=6, max_resolution=20, width=16, feature_dim=3,
                                start_levels=2)).double()
    with torch.no_grad():
        sdf.encoding.table.normal_(0.0, 0.05)
        for p in sdf.head.parameters():
            p.normal_(0.0, 0.3)
    return sdf


def test_grid_sdf_gradient_is_the_autograd_gradient_of_its_value():
    sdf = _grid_sdf()
    x = _points(300, 1.0).requires_grad_()
    value, feature, grad = sdf.sdf_and_grad(x.detach())
    ref_value, ref_feature = sdf(x)
    (ref_grad,) = torch.autograd.grad(ref_value.sum(), x)
    assert torch.allclose(value, ref_value, atol=1e-13) and torch.allclose(feature, ref_feature, atol=1e-13)
    assert torch.allclose(grad, ref_grad, atol=1e-12)
    # the level still off in coarse-to-fine (start_levels=2) adds nothing to the gradient
    sdf.encoding.table.data[sdf.encoding.first_rows[2]:] += 1.0
    assert torch.allclose(sdf.sdf_and_grad(x.detach())[2], grad, atol=1e-12)


def test_an_eikonal_loss_on_the_exact_gradient_trains_table_and_head():
    """The parameter gradients of ``sum (|grad f| - 1)^2 + f^2`` against central differences
    of the loss in each probed parameter (float64)."""
    sdf = _grid_sdf(seed=2)
    x = _points(200, 1.0, seed=4)

    def loss():
        value, _, grad = sdf.sdf_and_grad(x)
        return ((grad.norm(dim=-1) - 1.0).square() + value.square()).sum()

    sdf.zero_grad(set_to_none=True)
    loss().backward()
    table_grad = sdf.encoding.table.grad.clone()
    head_grad = sdf.head.layers[0].weight.grad.clone()
    probes = [(sdf.encoding.table, (int(r), 1)) for r in table_grad.abs().sum(1).nonzero()[::53, 0][:5]]
    probes += [(sdf.head.layers[0].weight, (3, 2)), (sdf.head.layers[0].weight, (5, 7))]
    for param, idx in probes:
        with torch.no_grad():
            param[idx] += 1e-6
            up = loss()
            param[idx] -= 2e-6
            down = loss()
            param[idx] += 1e-6
        analytic = (table_grad if param is sdf.encoding.table else head_grad)[idx]
        assert float(analytic) == pytest.approx(float((up - down) / 2e-6), rel=1e-5, abs=1e-8)


def test_fields_without_an_exact_gradient_fall_back_to_the_tetrahedral_difference():
    torch.manual_seed(0)
    sdf = MLPSDF(MLPSDFConfig(width=32, depth=2, skips=(), n_freqs=2)).double()
    x = _points(50, 0.6).requires_grad_()
    value, feature, grad = sdf_feature_and_gradient(sdf, x.detach())
    ref_value, ref_feature = sdf(x)
    (ref_grad,) = torch.autograd.grad(ref_value.sum(), x)
    assert torch.allclose(value, ref_value) and torch.allclose(feature, ref_feature)
    # first order in the step (1e-3): the error is the step times the curvature
    assert (grad - ref_grad).abs().max() < 5e-2 and (grad - ref_grad).abs().max() > 0


def _counted_fast_model():
    """The ``fast`` model at initialisation (the SDF is the sphere ``|x| - 0.5``) with a hook that
    counts the points of each grid lookup, plain and with the gradient."""
    from nepf_core.config import fast
    from nepf_core.model import NePFModel

    torch.manual_seed(0)
    model = NePFModel(fast().model)
    lookups = {"plain": 0, "with_gradient": 0}

    def count(_module, args, kwargs):
        lookups["with_gradient" if kwargs.get("with_gradient", False) else "plain"] += args[0].shape[0]

    model.sdf.encoding.register_forward_pre_hook(count, with_kwargs=True)
    return model, lookups


def _rays_at_the_sphere(n=48, samples=32):
    gen = torch.Generator().manual_seed(3)
    p = F.normalize(torch.randn(n, 3, generator=gen), dim=-1)
    d = F.normalize(0.2 * (torch.rand(n, 3, generator=gen) - 0.5) - 2.5 * p, dim=-1)
    z = torch.linspace(1.0, 4.0, samples)[None].expand(n, -1).contiguous()
    return 2.5 * p, d, z


def test_sample_weights_read_each_gradient_point_once():
    """The samples, then once per point that needs a gradient (the heads' samples and the
    eikonal points): a 4-point stencil read each gradient point 4 times."""
    from nepf_core.render.weights import weights_sample_mode

    model, lookups = _counted_fast_model()
    o, d, z = _rays_at_the_sphere()
    sw = weights_sample_mode(model, o, d, z, torch.tensor(64.0), head_threshold=1e-4, eikonal_fraction=0.1,
                             train=True)
    gradient_points = int((sw.grad.abs().sum(-1) > 0).sum())
    assert gradient_points > o.shape[0]
    assert lookups == {"plain": z.numel(), "with_gradient": gradient_points}
    # the sphere at initialisation: the gradient taken is the unit radial direction
    taken = sw.grad.abs().sum(-1) > 0
    assert torch.allclose(sw.grad[taken], F.normalize(sw.pts[taken], dim=-1), atol=1e-5)


def test_the_surface_point_and_its_smoothness_point_are_read_once_each():
    from nepf_core.render.neus import max_weight_index
    from nepf_core.render.surface import refine_surface
    from nepf_core.render.weights import weights_sample_mode

    model, lookups = _counted_fast_model()
    o, d, z = _rays_at_the_sphere()
    with torch.no_grad():
        sw = weights_sample_mode(model, o, d, z, torch.tensor(64.0), head_threshold=1e-4, eikonal_fraction=0.0,
                                 train=False)
    lookups.update(plain=0, with_gradient=0)
    xr, nr, fr, xj, fj = refine_surface(model, o, d, sw.z, sw.sdf, max_weight_index(sw.weights)[0], jitter_sigma=0.01)
    assert lookups == {"plain": 0, "with_gradient": 2 * o.shape[0]}
    assert torch.allclose(xr.norm(dim=-1), torch.full((o.shape[0],), 0.5), atol=1e-3)
    assert torch.allclose(nr, F.normalize(xr, dim=-1), atol=1e-5)
    assert fr.shape == fj.shape == (o.shape[0], model.sdf.feature_dim)
