"""The trilinear table lookup (fields/trilinear.py) against ``F.grid_sample``, by hand, and its
gradient bookkeeping: one dense zero fill of the table's gradient per backward, whatever the
number of lookups."""
import pytest
import torch
import torch.nn.functional as F
from torch.utils._python_dispatch import TorchDispatchMode

from nepf_core.fields.grid_encoding import GridConfig, MultiResGrid


def _grid(levels=3, feats=3, bound=1.0, seed=0):
    torch.manual_seed(seed)
    g = MultiResGrid(GridConfig(n_levels=levels, base_resolution=4, max_resolution=11, features_per_level=feats,
                                init_std=1.0, bound=bound)).double()
    g.set_active_levels(levels)
    return g


def _volumes(g):
    """Each level as the ``grid_sample`` volume ``[1, F, R, R, R]`` (a leaf of its own)."""
    f = g.cfg.features_per_level
    return [g.level(l).detach().t().reshape(1, f, r, r, r).clone().requires_grad_()
            for l, r in enumerate(g.resolutions)]


def _reference(vols, x, bound):
    n = x.shape[0]
    return torch.cat([F.grid_sample(v, (x / bound).view(1, n, 1, 1, 3), mode="bilinear", padding_mode="border",
                                    align_corners=True).view(v.shape[1], n).t() for v in vols], 1)


@pytest.mark.parametrize("bound", [1.0, 2.0])
def test_value_and_gradients_match_grid_sample(bound):
    g = _grid(bound=bound)
    vols = _volumes(g)
    # a third of the points outside the cube: border padding clamps them, and their x-gradient is 0
    x = ((torch.rand(400, 3, dtype=torch.float64) * 2.6 - 1.3) * bound).requires_grad_()
    x_ref = x.detach().clone().requires_grad_()
    out, ref = g(x), _reference(vols, x_ref, bound)
    assert torch.allclose(out, ref, atol=1e-12)
    w = torch.randn_like(out)
    (out * w).sum().backward()
    (ref * w).sum().backward()
    for l, v in enumerate(vols):
        assert torch.allclose(g.table.grad[g.first_rows[l]:g.first_rows[l] + v[0, 0].numel()],
                              v.grad.reshape(v.shape[1], -1).t(), atol=1e-12)
    assert torch.allclose(x.grad, x_ref.grad, atol=1e-10)
    outside = (x.detach().abs() > bound).any(-1)
    assert outside.any() and (x.grad[outside][x.detach()[outside].abs() > bound] == 0).all()


def test_hand_worked_point():
    """R = 3 on [-1, 1]: nodes at -1, 0, 1. x = (0.5, -0.5, 0.25) is in the cell with lower
    node (1, 0, 1) (x, y, z) at fractions (0.5, 0.5, 0.25): weight (1-fz)=0.75 on the z=1 face,
    0.25 on the z=2 face, a quarter of each to the four x/y corners."""
    g = MultiResGrid(GridConfig(n_levels=1, base_resolution=3, max_resolution=3, features_per_level=1)).double()
    with torch.no_grad():
        g.table.copy_(torch.arange(27, dtype=torch.float64)[:, None])   # value = row = (z*3 + y)*3 + x
    x = torch.tensor([[0.5, -0.5, 0.25]], dtype=torch.float64)
    # rows of the z=1 face: 9 + {0*3+1, 0*3+2, 1*3+1, 1*3+2} = 10, 11, 13, 14 (mean 12); z=2 face: 19, 20, 22, 23 (mean 21)
    assert g(x).item() == pytest.approx(0.75 * 12 + 0.25 * 21)
    g(x).sum().backward()
    expect = torch.zeros(27, dtype=torch.float64)
    expect[[10, 11, 13, 14]] = 0.75 / 4
    expect[[19, 20, 22, 23]] = 0.25 / 4
    assert torch.allclose(g.table.grad[:, 0], expect)


class _DenseFills(TorchDispatchMode):
    """Counts the elements written by zero/fill ops on tensors at least ``min_numel`` large."""

    def __init__(self, min_numel):
        super().__init__()
        self.min_numel, self.filled = min_numel, 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        name = func.overloadpacket.__name__
        if name in ("zero_", "fill_", "zeros", "zeros_like", "new_zeros") and isinstance(out, torch.Tensor) \
                and out.numel() >= self.min_numel:
            self.filled += out.numel()
        return out


def test_one_dense_zero_fill_per_backward_whatever_the_lookups():
    """A step that looks the grid up 12 times zeroes at most one table's worth of gradient
    (grid_sample zeroed a level-sized gradient per lookup and level), and a second step reuses
    the buffer."""
    g = _grid(levels=3, feats=2)
    n_table = g.table.numel()
    for step in range(2):
        g.table.grad = None   # what zero_grad(set_to_none=True) does each step
        with _DenseFills(min_numel=g.resolutions[-1] ** 3) as mode:
            loss = sum(g(torch.rand(64, 3, dtype=torch.float64) * 2 - 1).square().sum() for _ in range(12))
            loss.backward()
        assert mode.filled <= n_table, f"step {step}: {mode.filled} gradient elements zeroed for a table of {n_table}"
        if step == 0:
            first_buffer = g.table.grad.data_ptr()
    assert g.table.grad.data_ptr() == first_buffer


def test_legacy_volume_checkpoint_loads_into_the_table():
    g = _grid()
    legacy = {f"grids.{l}": v.detach() for l, v in enumerate(_volumes(g))}
    legacy["_extra_state"] = g.get_extra_state()
    g2 = _grid(seed=1)
    g2.load_state_dict(legacy)
    assert torch.equal(g2.table, g.table)


def test_no_grad_lookup_builds_no_graph():
    g = _grid()
    with torch.no_grad():
        y = g(torch.rand(10, 3, dtype=torch.float64))
    assert y.grad_fn is None and g.table.grad is None
