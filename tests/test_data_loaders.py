"""Loaders against known truth: synthetic scenes written as DTU, Blender and instant-ngp."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from PIL import Image
from scipy.ndimage import gaussian_filter

from datagen import (copy_scene, gt_scene, project_opencv, project_scene, random_object_points,
                     read_ply_vertices, srgb_decode, synth_dir, to_norm)
from nepf_core.data.blender import load_blender
from nepf_core.data.detect import detect_format, load_scene, resolve_dataset
from nepf_core.data.dtu import decompose_projection, load_dtu
from nepf_core.color import linear_to_srgb, srgb_to_linear
from nepf_core.data.ingp import (distort_image, distort_points, load_ingp, undistort_image,
                                 undistort_points)
from nepf_core.data.normalize import normalization_from_cameras


def _check_cameras(scene, gt_cams, X_world, tol_px=1e-3):
    """Every view projects world points where the ground-truth OpenCV camera does
    (Scene pixel centres sit at +0.5, OpenCV's at integers: u_scene = u_cv + 0.5)."""
    Xn = to_norm(scene, X_world)
    assert scene.n_views == len(gt_cams)
    for i, c in enumerate(gt_cams):
        uv_gt = project_opencv(np.array(c["K_opencv"]), np.array(c["w2c_opencv"]), X_world) + 0.5
        np.testing.assert_allclose(project_scene(scene, i, Xn), uv_gt, atol=tol_px)
        # world_from_norm maps the normalised camera centre back to the world one
        o = scene.world_from_norm @ np.r_[scene.c2w[i, :3, 3].astype(np.float64), 1.0]
        np.testing.assert_allclose(o[:3], np.array(c["c2w_opencv"])[:3, 3], rtol=1e-5,
                                   atol=1e-5 * np.abs(o[:3]).max())


def _check_images_and_masks(scene, folder, split="train"):
    a = np.load(folder / "gt" / f"arrays_{split}.npz")
    ref = np.clip(a["rgb_linear"], 0, 1)
    # 8-bit sRGB quantisation: |d lin / d srgb| <= 2.4 near 1, so <= 2.4 / 510 ~ 0.0047
    assert np.abs(scene.images - ref).max() < 0.006
    assert scene.images.dtype == np.float32
    np.testing.assert_array_equal(scene.masks, a["alpha"] >= 0.5)


@pytest.mark.parametrize("loader", ["dtu", "blender"])
def test_round_trip_cameras_images_masks(loader):
    d = synth_dir()
    sc = gt_scene(d)
    scene = load_dtu(d / "dtu") if loader == "dtu" else load_blender(d / "blender")
    assert scene.source_format == loader
    assert (scene.width, scene.height) == (40, 32)
    _check_cameras(scene, sc["cameras"]["train"], random_object_points(d))
    _check_images_and_masks(scene, d)
    # the object (gt mesh, world) lies inside the unit sphere, and fills a good part of it
    r = np.linalg.norm(to_norm(scene, read_ply_vertices(d / "gt/mesh.ply")), axis=1)
    assert r.max() < 1.0 and r.max() > 0.6
    assert scene.names[0].endswith(("000.png", "r_0.png"))


def test_dtu_uses_scale_mat_as_world_from_norm():
    d = synth_dir(world_scale=3.0, world_offset=(10.0, -5.0, 2.0))
    scene = load_dtu(d / "dtu")
    np.testing.assert_allclose(scene.world_from_norm, np.load(d / "dtu/cameras.npz")["scale_mat_0"])
    assert scene.world_scale() == pytest.approx(3.3)
    assert scene.extras["normalization"] == "scale_mat"
    _check_cameras(scene, gt_scene(d)["cameras"]["train"], random_object_points(d))


def test_test_splits_share_the_training_frame():
    d = synth_dir()
    sc = gt_scene(d)
    train = load_blender(d / "blender", "train")
    test = load_blender(d / "blender", "test")
    np.testing.assert_array_equal(train.world_from_norm, test.world_from_norm)
    _check_cameras(test, sc["cameras"]["test"], random_object_points(d))
    _check_images_and_masks(test, d, "test")
    dtu_test = load_scene(d / "gt" / "dtu_test")
    _check_cameras(dtu_test, sc["cameras"]["test"], random_object_points(d))


@pytest.mark.parametrize("preset", [dict(world_scale=1e-3, world_offset=(2e-3, -1e-3, 5e-4)),
                                    dict(world_scale=1e3, world_offset=(500.0, -200.0, 100.0))])
def test_extreme_world_scales_normalise_to_the_same_frame(preset):
    base = synth_dir(shape="box", material="glossy")
    d = synth_dir(shape="box", material="glossy", **preset)
    for load in (lambda p: load_dtu(p / "dtu"), lambda p: load_blender(p / "blender")):
        a, b = load(base), load(d)
        np.testing.assert_allclose(a.c2w, b.c2w, atol=1e-4)
        np.testing.assert_allclose(a.intrinsics, b.intrinsics, rtol=1e-6, atol=1e-9)
        assert b.world_scale() / a.world_scale() == pytest.approx(preset["world_scale"], rel=1e-6)
        _check_cameras(b, gt_scene(d)["cameras"]["train"], random_object_points(d), tol_px=1e-2)


def test_blender_normalisation_from_visual_hull_contains_the_object():
    d = synth_dir(shape="capsule", material="metal", world_offset=(0.4, -0.3, 0.2), world_scale=1.7)
    scene = load_blender(d / "blender")
    assert scene.extras["normalization"] == "visual_hull"
    r = np.linalg.norm(to_norm(scene, read_ply_vertices(d / "gt/mesh.ply")), axis=1)
    assert 0.7 < r.max() < 1.0  # contains the object, not grossly loose
    # the same rule without masks (frustum bound) is looser but still contains it
    n = normalization_from_cameras(scene.intrinsics.astype(np.float64),
                                   np.einsum("ij,njk->nik", scene.world_from_norm, scene.c2w.astype(np.float64)),
                                   (scene.width, scene.height), None)
    assert n.method == "frustum"
    v = (read_ply_vertices(d / "gt/mesh.ply") - n.centre) / n.radius
    assert np.linalg.norm(v, axis=1).max() < 1.0


def test_dtu_without_scale_mat_estimates_a_normalisation(tmp_path):
    d = copy_scene(tmp_path)
    cams = dict(np.load(d / "dtu/cameras.npz"))
    np.savez(d / "dtu/cameras.npz", **{k: v for k, v in cams.items() if k.startswith("world_mat")})
    scene = load_dtu(d / "dtu")
    assert scene.extras["normalization"] == "visual_hull"
    _check_cameras(scene, gt_scene(d)["cameras"]["train"], random_object_points(d))
    r = np.linalg.norm(to_norm(scene, read_ply_vertices(d / "gt/mesh.ply")), axis=1)
    assert 0.6 < r.max() < 1.0


def test_downscale_and_max_views():
    d = synth_dir()
    full = load_dtu(d / "dtu")
    half = load_scene(d / "dtu", downscale=2)
    assert half.images.shape == (8, 16, 20, 3)
    np.testing.assert_allclose(half.images, full.images.reshape(8, 16, 2, 20, 2, 3).mean((2, 4)), atol=1e-6)
    np.testing.assert_allclose(half.intrinsics[:, :2], full.intrinsics[:, :2] / 2, rtol=1e-6)
    X = to_norm(full, random_object_points(d))
    np.testing.assert_allclose(project_scene(half, 3, X), project_scene(full, 3, X) / 2, atol=1e-3)
    sub = load_scene(d / "blender", max_views=3)
    assert sub.n_views == 3 and sub.names == ["train/r_0.png", "train/r_4.png", "train/r_7.png"]


def test_soft_three_channel_masks_are_thresholded_at_127(tmp_path):
    d = copy_scene(tmp_path)
    m = np.array(Image.open(d / "dtu/mask/000.png").convert("L")) > 127
    soft = np.zeros(m.shape + (3,), np.uint8)
    soft[m] = (200, 190, 210)
    soft[~m] = (100, 130, 90)  # luma 119.9: background although one channel is 130
    Image.fromarray(soft).save(d / "dtu/mask/000.png")
    scene = load_dtu(d / "dtu")
    np.testing.assert_array_equal(scene.masks[0], m)


def test_decompose_projection_recovers_K_R_centre_with_skew_and_sign():
    rng = np.random.default_rng(1)
    K = np.array([[800.0, 3.0, 310.0], [0.0, 790.0, 245.0], [0.0, 0.0, 1.0]])
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    C = np.array([0.3, -2.0, 4.0])
    P = K @ np.c_[R, -R @ C]
    for scale in (1.0, -3.7, 1e-4):
        K2, c2w = decompose_projection(scale * P)
        np.testing.assert_allclose(K2, K, rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose(c2w[:3, :3], R.T, atol=1e-9)
        np.testing.assert_allclose(c2w[:3, 3], C, atol=1e-9)


def test_srgb_transfer_functions_match_reference():
    v = np.linspace(0, 1, 256)
    np.testing.assert_allclose(srgb_to_linear(v), srgb_decode(v), atol=1e-6)
    np.testing.assert_allclose(linear_to_srgb(srgb_decode(v)), v, atol=1e-5)
    assert srgb_to_linear(np.array([0.5]))[0] == pytest.approx(0.21404, abs=1e-5)


def test_distortion_points_round_trip():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.6, 0.6, (500, 2))
    c = (-0.2, 0.05, 0.003, -0.002, 0.01)
    np.testing.assert_allclose(undistort_points(distort_points(xy, c), c), xy, atol=1e-9)
    # hand value: k1 only, (x, y) = (0.5, 0): x_d = 0.5 (1 + k1 0.25)
    np.testing.assert_allclose(distort_points(np.array([[0.5, 0.0]]), (0.1, 0, 0, 0)), [[0.5125, 0.0]])


def _write_ingp(src, dst, coeffs, per_frame=False):
    """instant-ngp transforms.json from a synthetic Blender split, images distorted with ``coeffs``."""
    meta = json.loads((src / "blender/transforms_train.json").read_text())
    (dst / "images").mkdir(parents=True)
    K = np.array([[meta["fl_x"], 0, meta["cx"]], [0, meta["fl_y"], meta["cy"]], [0, 0, 1.0]])
    frames = []
    for i, fr in enumerate(meta["frames"]):
        rgba = np.array(Image.open(src / "blender" / (fr["file_path"] + ".png"))) / 255.0
        lin = srgb_decode(rgba[..., :3]) * rgba[..., 3:]
        dist = distort_image(lin.astype(np.float32), K, coeffs)
        Image.fromarray(np.round(linear_to_srgb(dist) * 255).astype(np.uint8)).save(dst / f"images/{i:04d}.jpg",
                                                                                     quality=98)
        f = {"file_path": f"images/{i:04d}.jpg", "transform_matrix": fr["transform_matrix"]}
        if per_frame:
            f.update(fl_x=meta["fl_x"], fl_y=meta["fl_y"], cx=meta["cx"], cy=meta["cy"])
        frames.append(f)
    out = {"k1": coeffs[0], "k2": coeffs[1], "p1": coeffs[2], "p2": coeffs[3], "aabb_scale": 4,
           "w": meta["w"], "h": meta["h"], "frames": frames}
    if not per_frame:
        out.update(fl_x=meta["fl_x"], fl_y=meta["fl_y"], cx=meta["cx"], cy=meta["cy"])
    (dst / "transforms.json").write_text(json.dumps(out))
    return K


def test_ingp_undistortion_recovers_the_pinhole_images(tmp_path):
    src = synth_dir(shape="sphere", material="textured", resolution=64, n_views=6, n_test=1)
    coeffs = (-0.4, 0.15, 0.01, -0.01)  # up to ~3 px at the corners
    _write_ingp(src, tmp_path / "fox", coeffs)
    assert detect_format(tmp_path / "fox") == "ingp"
    scene = load_ingp(tmp_path / "fox")
    assert scene.extras["undistorted"] and scene.extras["aabb_scale"] == 4 and scene.masks is None
    ref = np.clip(np.load(src / "gt/arrays_train.npz")["rgb_linear"], 0, 1)
    inner = (slice(None), slice(6, -6), slice(6, -6))

    def blur(x):  # two bilinear resamplings of aliased checker edges: compare at a coarser scale
        return gaussian_filter(x, (0, 2, 2, 0))

    err = np.abs(blur(scene.images) - blur(ref))[inner].mean()
    # negative control: the same files read as if there were no distortion
    meta = json.loads((tmp_path / "fox/transforms.json").read_text())
    for k in ("k1", "k2", "p1", "p2"):
        meta[k] = 0.0
    (tmp_path / "fox/transforms.json").write_text(json.dumps(meta))
    raw = load_ingp(tmp_path / "fox")
    err_raw = np.abs(blur(raw.images) - blur(ref))[inner].mean()
    assert err < 0.01 and err < 0.6 * err_raw, (err, err_raw)
    _check_cameras(scene, gt_scene(src)["cameras"]["train"], random_object_points(src))


def test_ingp_per_frame_intrinsics_and_undistort_image_inverse(tmp_path):
    src = synth_dir(shape="sphere", material="textured", resolution=64, n_views=6, n_test=1)
    K = _write_ingp(src, tmp_path / "d", (0.1, 0.0, 0.0, 0.0), per_frame=True)
    scene = load_scene(tmp_path)  # descends into the only sub-folder
    np.testing.assert_allclose(scene.intrinsics[0], K, rtol=1e-6)
    img = np.random.default_rng(0).uniform(size=(64, 64, 1)).astype(np.float32)
    smooth = np.cumsum(np.cumsum(img, 0), 1)
    smooth /= smooth.max()
    back = undistort_image(distort_image(smooth, K, (0.1, 0, 0, 0)), K, (0.1, 0, 0, 0))
    assert np.abs(back - smooth)[10:-10, 10:-10].max() < 0.02


def test_detection_rules(tmp_path):
    d = synth_dir()
    assert resolve_dataset(d) == ("dtu", d / "dtu")  # dtu/ and blender/ beside gt/: prefer DTU
    assert detect_format(d / "blender") == "blender"
    assert detect_format(d / "gt") == "dtu"  # gt/dtu_test
    wrapped = tmp_path / "upload" / "my_scene"
    shutil.copytree(d / "blender", wrapped / "data")
    (tmp_path / "upload" / "__MACOSX").mkdir()
    (tmp_path / "upload" / ".hidden").mkdir()
    fmt, folder = resolve_dataset(tmp_path / "upload")
    assert (fmt, folder) == ("blender", wrapped / "data")
    assert load_scene(tmp_path / "upload").n_views == 8


@pytest.mark.parametrize("variant", [dict(n_views=1, n_test=0), dict(camera_distance=1.3),
                                     dict(camera_distance=50.0)])
def test_single_view_close_and_far_cameras_load(variant):
    d = synth_dir(shape="sphere", material="glossy", **variant)
    sc = gt_scene(d)
    V = read_ply_vertices(d / "gt/mesh.ply")
    for scene in (load_dtu(d / "dtu"), load_blender(d / "blender")):
        _check_cameras(scene, sc["cameras"]["train"], random_object_points(d), tol_px=2e-3)
        r = np.linalg.norm(to_norm(scene, V), axis=1)
        assert r.max() < 1.0
        # every camera stays outside the unit sphere
        assert np.linalg.norm(scene.c2w[:, :3, 3], axis=1).min() > 1.0
