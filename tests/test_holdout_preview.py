"""The held-out side-by-side picture (nepf_core/holdout_preview.py), by hand."""
import numpy as np
import pytest
from matplotlib import colormaps
from PIL import Image

from nepf_core.holdout_preview import GAP, PREVIEW_PATH, side_by_side, write_holdout_preview


def test_panels_and_error_by_hand():
    gt = np.zeros((2, 3, 3))
    render = gt.copy()
    render[0, 0] = 0.25            # error 4 * 0.25 = 1 -> the colour map's top
    render[1, 2] = [0.0, 0.0, 0.075]   # mean 0.025, error 0.1
    out = side_by_side(render, gt)
    assert out.shape == (2, 3 * 3 + 2 * GAP, 3) and out.dtype == np.uint8
    assert (out[:, 3:3 + GAP] == 0).all() and (out[:, 6 + GAP:6 + 2 * GAP] == 0).all()
    assert np.array_equal(out[:, :3], (render * 255 + 0.5).astype(np.uint8))
    assert np.array_equal(out[:, 3 + GAP:6 + GAP], (gt * 255 + 0.5).astype(np.uint8))
    err = out[:, 6 + 2 * GAP:]
    expect = lambda v: (np.asarray(colormaps["inferno"](v)[:3]) * 255 + 0.5).astype(np.uint8)
    assert np.array_equal(err[0, 0], expect(1.0))
    assert np.array_equal(err[1, 2], expect(0.1))
    assert np.array_equal(err[0, 1], expect(0.0))
    with pytest.raises(ValueError, match="must both be"):
        side_by_side(render[:1], gt)


def test_written_atomically_where_the_record_says(tmp_path):
    rng = np.random.default_rng(0)
    a, b = rng.uniform(size=(5, 4, 3)), rng.uniform(size=(5, 4, 3))
    rel = write_holdout_preview(tmp_path, a, b)
    assert rel == PREVIEW_PATH
    with Image.open(tmp_path / rel) as im:
        assert np.array_equal(np.asarray(im), side_by_side(a, b))
    write_holdout_preview(tmp_path, b, a)   # replaced, no temporary left behind
    assert sorted(p.name for p in (tmp_path / rel).parent.iterdir()) == ["latest.png"]
