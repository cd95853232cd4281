"""Working resolution and decoded-pixel budget (issue 23, finding 3).

Area resampling is exact for any factor, intrinsics follow the pixels, masks are
re-thresholded, and the pixel budget is read from the headers before anything is decoded.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from PIL import Image

from datagen import copy_scene, project_scene, random_object_points, synth_dir, to_norm
from nepf_core.data import DatasetError
from nepf_core.data.blender import load_blender
from nepf_core.data.dtu import load_dtu
from nepf_core.data.images import box_downscale, mask_from_array, read_image
from nepf_core.data.resample import area_resize, working_size
from nepf_core.data.validate import validate_dataset


def reference_area_resize(a: np.ndarray, w_out: int, h_out: int) -> np.ndarray:
    """Independent reference: replicate every pixel ``n_out`` times along each axis (a grid
    ``n_in * n_out`` long, on which both pixel sizes are whole numbers of cells), then take
    the mean of blocks of ``n_in`` cells."""
    h, w = a.shape[:2]
    up = np.repeat(np.repeat(a.astype(np.float64), h_out, axis=0), w_out, axis=1)
    return up.reshape(h_out, h, w_out, w, *a.shape[2:]).mean(axis=(1, 3))


def test_integer_factor_gives_the_block_means():
    blocks = np.arange(4 * 3 * 2, dtype=np.float32).reshape(4, 3, 2) / 24
    img = np.repeat(np.repeat(blocks, 2, axis=0), 2, axis=1)      # [8, 6, 2], 2x2-constant blocks
    np.testing.assert_array_equal(area_resize(img, 3, 4), blocks)
    rng = np.random.default_rng(0)
    x = rng.random((12, 9, 3)).astype(np.float32)
    np.testing.assert_allclose(area_resize(x, 3, 4), box_downscale(x, 3), atol=1e-6)


@pytest.mark.parametrize("shape,size", [((37, 23, 3), (16, 10)), ((30, 41), (29, 7)), ((5, 64, 1), (5, 17))])
def test_any_factor_matches_the_reference_and_keeps_the_mean(shape, size):
    x = np.random.default_rng(1).random(shape).astype(np.float32)
    out = area_resize(x, *size)
    assert out.shape == (size[1], size[0], *shape[2:])
    np.testing.assert_allclose(out, reference_area_resize(x, *size), atol=2e-6)
    np.testing.assert_allclose(out.mean(axis=(0, 1)), x.mean(axis=(0, 1)), atol=2e-6)


def test_working_size_caps_the_long_side():
    assert working_size(1920, 1080, 1600) == (1600, 900)
    assert working_size(1080, 1920, 540) == (304, 540)        # 1080 * 540 / 1920 = 303.75
    assert working_size(800, 600, 1600) == (800, 600)
    assert working_size(800, 600, 0) == (800, 600)


@pytest.mark.parametrize("layout", ["dtu", "blender"])
def test_projection_round_trip_after_downscaling(layout):
    """A 3D point lands at the same relative image position (u / W, v / H) at full size and
    at a non-integer working resolution: intrinsics scale with the pixels."""
    folder = synth_dir() / layout
    load = load_dtu if layout == "dtu" else load_blender
    full, small = load(folder), load(folder, max_side=25)              # 40x32 -> 25x20
    assert (full.width, full.height, small.width, small.height) == (40, 32, 25, 20)
    X = to_norm(full, random_object_points(synth_dir(), n=50))
    np.testing.assert_allclose(small.world_from_norm, full.world_from_norm)
    for i in (0, 5):
        uv_full = project_scene(full, i, X) / [full.width, full.height]
        uv_small = project_scene(small, i, X) / [small.width, small.height]
        np.testing.assert_allclose(uv_small, uv_full, atol=1e-5)
    # the pixels follow: each working view is the exact area resampling of the full one
    np.testing.assert_allclose(small.images[3], area_resize(full.images[3], 25, 20), atol=1e-6)


def test_max_side_at_an_integer_factor_equals_the_box_downscale():
    folder = synth_dir() / "dtu"
    a, b = load_dtu(folder, max_side=20), load_dtu(folder, downscale=2)
    np.testing.assert_allclose(a.images, b.images, atol=1e-6)
    np.testing.assert_array_equal(a.masks, b.masks)
    np.testing.assert_allclose(a.intrinsics, b.intrinsics, rtol=1e-6)


def test_masks_are_resampled_then_rethresholded():
    folder = synth_dir() / "dtu"
    small = load_dtu(folder, max_side=25)
    m = mask_from_array(np.asarray(Image.open(folder / "mask/004.png")))
    np.testing.assert_array_equal(small.masks[4], area_resize(m.astype(np.float32), 25, 20) >= 0.5)
    rgba = load_blender(synth_dir() / "blender", max_side=25)
    alpha = read_image(synth_dir() / "blender/train/r_2.png")[..., 3]
    np.testing.assert_array_equal(rgba.masks[2], area_resize(alpha, 25, 20) >= 0.5)


def test_too_small_working_size_and_bad_max_side(tmp_path):
    folder = synth_dir() / "dtu"
    with pytest.raises(DatasetError) as ei:
        load_dtu(folder, max_side=9)                           # 9 x 7: below 8 pixels
    assert ei.value.code == "image_too_small" and "max side 9" in ei.value.message
    with pytest.raises(DatasetError) as ei:
        load_dtu(folder, max_side=-1)
    assert ei.value.code == "bad_argument"


def test_pixel_budget_is_checked_from_headers_before_decoding(tmp_path):
    ds = copy_scene(tmp_path) / "dtu"
    total = 8 * 40 * 32
    assert load_dtu(ds, max_total_pixels=total).n_views == 8        # exactly at the limit: fine
    with pytest.raises(DatasetError) as ei:
        load_dtu(ds, max_total_pixels=total - 1)
    assert ei.value.code == "too_many_pixels" and f"{total - 1:,}" in ei.value.message
    # a corrupt image is never decoded when the budget already refuses the dataset
    (ds / "image/005.png").write_bytes(b"not an image")
    with pytest.raises(DatasetError) as ei:
        load_dtu(ds, max_total_pixels=7 * 40 * 32 - 1)
    assert ei.value.code == "too_many_pixels"
    with pytest.raises(DatasetError) as ei:
        load_dtu(ds, max_total_pixels=7 * 40 * 32)
    assert ei.value.code == "unreadable_image"
    b = copy_scene(tmp_path / "b") / "blender"
    out = validate_dataset(b, max_total_pixels=10 * 40 * 32 - 1)   # train + test splits together
    assert out["ok"] is False and out["errors"][0]["code"] == "too_many_pixels"
    assert validate_dataset(b, max_total_pixels=10 * 40 * 32, max_side=25)["working_width"] == 25


def test_views_are_decoded_one_at_a_time(tmp_path):
    """Loading 10 views of 600x600 at a working side of 60 allocates far less than the
    full-size float images would take together (10 x 600 x 600 x 3 x 4 bytes = 43 MB)."""
    from service_fixtures import make_dtu_dir
    ds = make_dtu_dir(tmp_path / "big", n=10, size=600)
    full_float_bytes = 10 * 600 * 600 * 3 * 4
    tracemalloc.start()
    try:
        scene = load_dtu(ds, max_side=60)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert (scene.width, scene.height) == (60, 60)
    assert peak < 0.4 * full_float_bytes, peak


def test_cli_max_side_reaches_fit_render_and_eval(tmp_path, capsys):
    import json

    from nepf_core.cli import main
    ds = copy_scene(tmp_path) / "blender"                       # 40x32 train and test views
    run = tmp_path / "run"
    assert main(["fit", str(ds), "--out", str(run), "--config", "tiny", "--iters", "2", "--max-side", "20",
                 "--no-export", "--device", "cpu"]) == 0
    assert json.loads((run / "summary.json").read_text())["working_size"] == [20, 16]
    assert main(["render", str(run), "--cameras", str(ds), "--out", str(tmp_path / "r"), "--max-side", "25",
                 "--device", "cpu"]) == 0
    assert Image.open(tmp_path / "r" / "pbr" / "000.png").size == (25, 20)
    assert main(["eval", str(run), "--test", str(ds), "--out", str(tmp_path / "e"), "--max-side", "16",
                 "--device", "cpu"]) == 0
    assert np.load(tmp_path / "e" / "renders" / "arrays.npz")["pbr"].shape[1:3] == (13, 16)
    assert json.loads((tmp_path / "e" / "eval.json").read_text())["views"] == 2
