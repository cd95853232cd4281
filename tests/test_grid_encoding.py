"""MultiResGrid, sphere prior and finite-difference normals."""
import pytest
import torch

from nepf_core.fields.fd_normals import sdf_gradient_fd
from nepf_core.fields.grid_encoding import GridConfig, MultiResGrid, sphere_sdf


def tiny_grid(dtype=torch.float64, levels=2):
    torch.manual_seed(0)
    g = MultiResGrid(GridConfig(n_levels=levels, base_resolution=3, max_resolution=5, features_per_level=2, init_std=1.0))
    g.set_active_levels(levels)
    return g.to(dtype)


def test_resolutions_and_shape():
    g = MultiResGrid(GridConfig(n_levels=4, base_resolution=16, max_resolution=128, features_per_level=2))
    assert g.resolutions == [16, 32, 64, 128]
    g.set_active_levels(4)
    assert g(torch.rand(10, 3) * 2 - 1).shape == (10, 8)
    # align_corners=True: R nodes span 2*bound -> h = 2/(R-1)
    assert g.active_cell_size() == pytest.approx(2 / 127)
    g.set_active_levels(2)
    assert g.active_cell_size() == pytest.approx(2 / 31)


def test_trilinear_at_nodes_and_midpoint():
    g = tiny_grid(levels=1)  # single level R=5, nodes at -1,-0.5,0,0.5,1
    r = g.resolutions[0]
    v = g.level(0).t().reshape(-1, r, r, r)  # [F, z, y, x]
    x = torch.tensor([[-0.5, 0.0, 0.5]], dtype=torch.float64)  # node (ix=1, iy=2, iz=3)
    assert torch.allclose(g(x)[0], v[:, 3, 2, 1])
    # midpoint between x-nodes 1 and 2: average of the two
    x = torch.tensor([[-0.25, 0.0, 0.5]], dtype=torch.float64)
    assert torch.allclose(g(x)[0], 0.5 * (v[:, 3, 2, 1] + v[:, 3, 2, 2]))


def test_gradcheck_wrt_x_and_grid():
    g = tiny_grid()
    # keep points away from node planes (trilinear is only piecewise smooth)
    x = torch.tensor([[0.13, -0.31, 0.62], [-0.71, 0.27, -0.09]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda xx: g(xx), (x,), eps=1e-6, atol=1e-6)
    p = g.table
    p.grad = None   # gradcheck's backward for x also scattered into it (fields/trilinear.py says why)

    # gradient w.r.t. grid values: output is linear in the grid -> compare to direct FD
    out_w = torch.randn(2, g.n_output_dims, dtype=torch.float64)
    loss = (g(x.detach()) * out_w).sum()
    loss.backward()
    for level in range(2):   # one touched value in each level's rows
        first = g.first_rows[level]
        rows = torch.nonzero(p.grad[first:first + g.resolutions[level] ** 3].abs() > 1e-3)[0]
        idx = (first + int(rows[0]), int(rows[1]))
        with torch.no_grad():
            old = p[idx].item()
            p[idx] = old + 1e-4
            lp = (g(x.detach()) * out_w).sum()
            p[idx] = old - 1e-4
            lm = (g(x.detach()) * out_w).sum()
            p[idx] = old
        assert p.grad[idx].item() == pytest.approx(((lp - lm) / 2e-4).item(), rel=1e-6, abs=1e-9)


def test_coarse_to_fine_masks_levels_and_grads():
    g = tiny_grid(levels=3)
    g.set_active_levels(1)
    x = torch.rand(20, 3, dtype=torch.float64) * 2 - 1
    y = g(x)
    f = g.cfg.features_per_level
    assert (y[:, f:] == 0).all() and (y[:, :f] != 0).any()
    y.sum().backward()
    n0 = g.resolutions[0] ** 3
    assert g.table.grad[:n0].abs().sum() > 0 and (g.table.grad[n0:] == 0).all()
    # progress schedule reaches all levels; state survives a state_dict round trip
    assert g.set_progress(0.0) == 1 and g.set_progress(1.0) == 3
    g2 = tiny_grid(levels=3)
    g2.set_active_levels(1)
    g2.load_state_dict(g.state_dict())
    assert g2.active_levels == 3


def test_device_agnostic_to():
    g = MultiResGrid(GridConfig(n_levels=2, base_resolution=4, max_resolution=8))
    g = g.to(torch.float64)
    assert all(p.dtype == torch.float64 for p in g.parameters())
    x = torch.rand(5, 3, dtype=torch.float64)
    assert g(x).device == x.device
    if torch.cuda.is_available():
        gc = g.to("cuda")
        assert gc(x.cuda()).device.type == "cuda"


def test_grid_sdf_starts_as_sphere():
    from nepf_core.fields.sdf_grid import GridSDF, GridSDFConfig
    sdf = GridSDF(GridSDFConfig(n_levels=2, base_resolution=8, max_resolution=16, width=16, feature_dim=3))
    x = torch.rand(100, 3) * 2 - 1
    s, feat = sdf(x)
    assert feat.shape == (100, 3)
    assert torch.allclose(s, sphere_sdf(x, 0.5), atol=1e-6)
    assert torch.allclose(sphere_sdf(torch.tensor([[0.3, 0.4, 0.0]]), 0.5), torch.zeros(1))


# ----------------------------------------------------------------- FD normals
@pytest.mark.parametrize("center", ["eval", "mean"])
def test_fd_central_on_sphere_is_second_order(center):
    torch.manual_seed(0)
    x = torch.randn(500, 3, dtype=torch.float64)
    x = x / x.norm(dim=1, keepdim=True) * (0.3 + 0.5 * torch.rand(500, 1, dtype=torch.float64))
    n_true = x / x.norm(dim=1, keepdim=True)
    errs = []
    for eps in (1e-2, 5e-3):
        grad, s = sdf_gradient_fd(lambda p: sphere_sdf(p, 0.5), x, eps, "central", center)
        errs.append((grad - n_true).abs().max().item())
        assert (s - sphere_sdf(x, 0.5)).abs().max().item() < (10 * eps**2 if center == "mean" else 1e-12)
    # |x| >= 0.3 -> |d3f| <= ~2/0.3^2; error ~ eps^2/6 * that; halving eps quarters the error
    assert errs[0] < 1e-3
    assert errs[1] < errs[0] / 3.5


def test_fd_tetra_on_sphere_first_order():
    torch.manual_seed(0)
    x = torch.randn(500, 3, dtype=torch.float64)
    x = x / x.norm(dim=1, keepdim=True) * 0.5
    grad, s = sdf_gradient_fd(lambda p: sphere_sdf(p, 0.5), x, 1e-3, "tetra", "mean")
    # error = eps * |offdiag Hessian| <= eps / r
    assert (grad - x / 0.5).abs().max() < 1e-3 / 0.5 + 1e-6
    assert s.abs().max() < 1e-5


def test_fd_matches_autograd_on_grid_mlp_and_is_trainable():
    from nepf_core.fields.sdf_grid import GridSDF, GridSDFConfig
    torch.manual_seed(0)
    sdf = GridSDF(GridSDFConfig(n_levels=2, base_resolution=8, max_resolution=16, width=16, start_levels=2)).double()
    g = sdf.encoding
    with torch.no_grad():
        for p in list(sdf.head.parameters()) + [g.table]:
            p.normal_(0, 0.3)
    x = (torch.rand(300, 3, dtype=torch.float64) * 1.6 - 0.8).requires_grad_(True)
    s = sdf.sdf(x)
    (g_ad,) = torch.autograd.grad(s.sum(), x)
    # central differences agree up to points whose stencil crosses a cell boundary or a
    # ReLU kink; with a tiny eps that is a small fraction of points
    g_fd, s_fd = sdf_gradient_fd(sdf.sdf, x.detach(), 1e-6, "central", "eval")
    err = (g_fd - g_ad).norm(dim=1)
    assert (err < 1e-5).float().mean() > 0.95
    assert torch.allclose(s_fd, s.detach())
    # eikonal through FD reaches the grid parameters
    sdf.zero_grad()
    g_fd, _ = sdf_gradient_fd(sdf.sdf, x.detach(), 0.5 * g.active_cell_size())
    (g_fd.norm(dim=1) - 1).square().mean().backward()
    assert g.table.grad[g.first_rows[1]:].abs().sum() > 0
