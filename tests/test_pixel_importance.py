"""The error map that draws part of each batch where the radiance network fits worst
(nepf_core/train/pixel_importance.py): tiling, the draw's distribution, the blend by hand, the
per-ray error by hand, and an exact resume of a run that draws with it."""

import math

import pytest
import torch

from nepf_core.train.pixel_importance import START_ERROR, PixelImportance, ray_errors


def test_tiles_cover_the_images_and_stay_under_the_cell_budget():
    small = PixelImportance(2, 8, 8, "cpu", 0.5, max_cells=1000)     # 128 pixels: one tile each
    assert small.tile == 1 and small.error.numel() == 128
    big = PixelImportance(3, 50, 70, "cpu", 0.5, max_cells=100)       # 10,500 px / 100 -> tile ceil(sqrt(105)) = 11
    assert big.tile == 11
    assert (big.rows, big.cols) == (5, 7)                               # ceil(50 / 11), ceil(70 / 11)
    assert big.error.numel() == 3 * 5 * 7
    # the last pixel of the last view falls in the last tile
    last = big.cells(torch.tensor([2]), torch.tensor([49]), torch.tensor([69]))
    assert int(last) == big.error.numel() - 1


def test_all_draws_land_in_the_only_tile_with_error():
    imp = PixelImportance(2, 12, 12, "cpu", 1.0, max_cells=2 * 9)    # tile 4: 3 x 3 tiles a view
    assert imp.tile == 4
    imp.error.zero_()
    imp.error[imp.cells(torch.tensor([1]), torch.tensor([5]), torch.tensor([9]))] = 1.0   # view 1, tile (1, 2)
    view, row, col = imp.draw(500, torch.Generator().manual_seed(0))
    assert (view == 1).all()
    assert ((row >= 4) & (row < 8)).all() and ((col >= 8) & (col < 12)).all()
    # uniform inside the tile: each of its 16 pixels is drawn
    assert len(set(zip(row.tolist(), col.tolist()))) == 16


def test_draws_follow_the_errors_and_the_uniform_share():
    imp = PixelImportance(1, 2, 1, "cpu", 0.5)                         # two one-pixel tiles
    imp.error = torch.tensor([3.0, 1.0])
    n = 40_000
    _, row, _ = imp.draw(n, torch.Generator().manual_seed(1))
    # the uniform half puts 1/2 on each pixel, the error half 3/4 on pixel 0: 0.5 * 0.5 + 0.5 * 0.75
    share0 = float((row == 0).float().mean())
    assert share0 == pytest.approx(0.625, abs=4 * math.sqrt(0.625 * 0.375 / n))
    imp.fraction = 0.0
    _, row, _ = imp.draw(n, torch.Generator().manual_seed(2))
    assert float((row == 0).float().mean()) == pytest.approx(0.5, abs=4 * math.sqrt(0.25 / n))


def test_edge_tiles_cut_by_the_image_draw_inside_it():
    imp = PixelImportance(1, 10, 10, "cpu", 1.0, max_cells=9)          # tile 4: the last row/col tiles are 2 wide
    imp.error.zero_()
    imp.error[-1] = 1.0
    _, row, col = imp.draw(2000, torch.Generator().manual_seed(3))
    assert row.min() >= 8 and row.max() <= 9 and col.min() >= 8 and col.max() <= 9


def test_update_blends_the_mean_error_of_each_tile_by_hand():
    imp = PixelImportance(1, 2, 2, "cpu", 0.5)                          # four one-pixel tiles
    view = torch.tensor([0, 0, 0])
    row = torch.tensor([0, 0, 1])
    col = torch.tensor([0, 0, 1])
    imp.update(view, row, col, torch.tensor([0.2, 0.4, 0.0]))
    # tile (0, 0): mean 0.3 -> 0.5 * 1.0 + 0.5 * 0.3; tile (1, 1): 0.5 * 1.0 + 0.5 * 0.0; the others untouched
    assert imp.error.tolist() == pytest.approx([0.65, START_ERROR, START_ERROR, 0.5])


def test_state_round_trip_and_a_map_of_another_tiling_is_ignored():
    a = PixelImportance(1, 4, 4, "cpu", 0.5)
    a.error = torch.linspace(0.0, 1.0, 16)
    b = PixelImportance(1, 4, 4, "cpu", 0.5)
    b.load_state_dict(a.state_dict())
    assert torch.equal(a.error, b.error)
    other = PixelImportance(1, 8, 8, "cpu", 0.5)
    other.load_state_dict(a.state_dict())
    assert (other.error == START_ERROR).all()


def test_ray_errors_by_hand():
    # linear 0.2140 is sRGB 0.5 (to 4 digits); the radiance 1.0 is sRGB 1: |1 - 0.5| on every channel
    rgb_r = torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    target = torch.full((2, 3), 0.21404114)
    err = ray_errors(rgb_r, target, None, torch.ones(2))
    assert err.tolist() == pytest.approx([0.5, 0.5], abs=1e-4)
    # with masks: the colour counts on the foreground only, the opacity error everywhere
    mask = torch.tensor([1.0, 0.0])
    err = ray_errors(rgb_r, target, mask, torch.tensor([0.75, 0.25]))
    assert err.tolist() == pytest.approx([0.5 + 0.25, 0.25], abs=1e-4)


def test_a_non_finite_render_scores_the_start_error():
    rgb_r = torch.tensor([[float("nan"), 0.0, 0.0], [0.0, 0.0, 0.0]])
    err = ray_errors(rgb_r, torch.zeros(2, 3), None, torch.tensor([float("nan"), 1.0]))
    assert err.tolist() == [START_ERROR, 0.0]


def test_fraction_out_of_range_is_refused():
    with pytest.raises(ValueError, match="fraction"):
        PixelImportance(1, 4, 4, "cpu", 1.5)
