"""The metal record (nepf_core.train.metal_record): which cell a point falls in, the decaying
sums and the share by hand, and the state a resumed run restores."""

import pytest
import torch

from nepf_core.train.metal_record import MetalRecord


def test_cells_by_hand():
    rec = MetalRecord("cpu", resolution=4)
    # cell width 0.5 over [-1, 1]: x = -0.9 -> 0, -0.1 -> 1, 0.1 -> 2, 0.99 -> 3; outside clamps
    x = torch.tensor([[-0.9, -0.1, 0.1], [0.99, -0.9, -0.1], [5.0, -5.0, 0.6]])
    i = rec.cells(x)
    assert i.tolist() == [(0 * 4 + 1) * 4 + 2, (3 * 4 + 0) * 4 + 1, (3 * 4 + 0) * 4 + 3]


def test_share_decays_and_weighs_confidence_by_hand():
    rec = MetalRecord("cpu", resolution=2, decay=0.5, prior_confidence=0.25)
    a, b = torch.tensor([[0.5, 0.5, 0.5]]), torch.tensor([[-0.5, -0.5, -0.5]])
    # step 1: a metal call at a (q 0.5), a dielectric call at b (q 0.8), and a metal call at b (q 0.2)
    rec.update(torch.cat([a, b, b]), torch.tensor([1.0, 0.0, 1.0]), torch.tensor([0.5, 0.8, 0.2]))
    assert float(rec.metal_share(a)) == pytest.approx(0.5 / (0.5 + 0.25))
    assert float(rec.metal_share(b)) == pytest.approx(0.2 / (1.0 + 0.25))
    # step 2, no evidence: both sums halve, so the share moves toward 0 (the evidence goes stale)
    rec.update(torch.zeros(0, 3), torch.zeros(0), torch.zeros(0))
    assert float(rec.metal_share(a)) == pytest.approx(0.25 / (0.25 + 0.25))
    # a cell never reached keeps the prior in full
    assert float(rec.metal_share(torch.tensor([[0.5, -0.5, 0.5]]))) == 0.0
    # many confident metal calls: the share approaches 1 but never reaches it
    for _ in range(30):
        rec.update(a.expand(8, 3), torch.ones(8), torch.full((8,), 0.9))
    s = float(rec.metal_share(a))
    assert 0.95 < s < 1.0


def test_state_round_trip_and_errors():
    rec = MetalRecord("cpu", resolution=3)
    rec.update(torch.rand(20, 3) * 2 - 1, (torch.rand(20) > 0.5).float(), torch.rand(20))
    other = MetalRecord("cpu", resolution=3)
    other.load_state_dict(rec.state_dict())
    x = torch.rand(50, 3) * 2 - 1
    assert torch.equal(other.metal_share(x), rec.metal_share(x))
    with pytest.raises(ValueError, match="cells"):
        MetalRecord("cpu", resolution=4).load_state_dict(rec.state_dict())
    with pytest.raises(ValueError, match="decay"):
        MetalRecord("cpu", decay=0.0)
