"""COLMAP and nerfstudio inputs (issue 34 items 2-3) against the DTU loader on the same cameras.

A synthetic scene is written as DTU and again as COLMAP (binary and text) and nerfstudio
(``make_scene(formats=...)``, ``nepf_core/data/convert.py``). The loaders normalise differently
(DTU by ``scale_mat``, the others by the camera rule or the visual hull), so rays are compared in
the input's world frame: ``o_w = world_from_norm o``, ``d_w ~ world_from_norm[:3, :3] d``.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from datagen import gt_scene, project_opencv, project_scene, random_object_points, read_ply_vertices, synth_dir, to_norm
from nepf_core.data.colmap import load_colmap
from nepf_core.data.colmap_io import (ColmapCamera, ColmapImage, ColmapModel, qvec_to_rotmat, read_model,
                                      rotmat_to_qvec, write_model)
from nepf_core.data.convert import write_colmap, write_nerfstudio
from nepf_core.data.detect import load_scene, resolve_dataset
from nepf_core.data.dtu import load_dtu
from nepf_core.data.errors import DatasetError
from nepf_core.data.nerfstudio import load_nerfstudio
from nepf_core.data.validate import validate_dataset
from nepf_core.rays import rays_from_pixels

FORMATS = ("colmap", "colmap_txt", "nerfstudio")


def scene_dir():
    return synth_dir(formats=FORMATS)


def world_rays(scene, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel centre's ray of view ``i`` by the renderer's own ``rays_from_pixels``, mapped to
    the input's world: ``(origins [H*W, 3], unit directions [H*W, 3])``."""
    v, u = np.meshgrid(np.arange(scene.height) + 0.5, np.arange(scene.width) + 0.5, indexing="ij")
    n = u.size
    K_inv = torch.linalg.inv(torch.as_tensor(scene.intrinsics[i], dtype=torch.float64)).expand(n, 3, 3)
    c2w = torch.as_tensor(scene.c2w[i], dtype=torch.float64).expand(n, 4, 4)
    o, d = rays_from_pixels(K_inv, c2w, torch.as_tensor(u.ravel()), torch.as_tensor(v.ravel()))
    A = np.asarray(scene.world_from_norm, np.float64)
    o_w = o.numpy() @ A[:3, :3].T + A[:3, 3]
    d_w = d.numpy() @ A[:3, :3].T
    return o_w, d_w / np.linalg.norm(d_w, axis=1, keepdims=True)


def assert_same_rays(scene, ref, tol: float = 2e-6):
    """Origins within ``tol`` x the camera distance, directions within ``tol`` (float32 poses)."""
    assert scene.n_views == ref.n_views and (scene.width, scene.height) == (ref.width, ref.height)
    for i in range(ref.n_views):
        (o, d), (o_ref, d_ref) = world_rays(scene, i), world_rays(ref, i)
        np.testing.assert_allclose(o, o_ref, atol=tol * np.abs(o_ref).max())
        np.testing.assert_allclose(d, d_ref, atol=tol)


@pytest.mark.parametrize("fmt", FORMATS)
def test_same_rays_images_and_masks_as_dtu(fmt):
    d = scene_dir()
    ref = load_dtu(d / "dtu")
    scene = load_scene(d / fmt)
    assert scene.source_format == ("nerfstudio" if fmt == "nerfstudio" else "colmap")
    assert_same_rays(scene, ref)
    np.testing.assert_array_equal(scene.images, ref.images)
    if fmt == "nerfstudio":   # mask_path read like DTU masks
        np.testing.assert_array_equal(scene.masks, ref.masks)
    else:
        assert scene.masks is None   # COLMAP has no masks
    assert resolve_dataset(d / fmt)[0] == scene.source_format
    v = validate_dataset(d / fmt)
    assert v["ok"] and v["format"] == scene.source_format and v["n_views"] == ref.n_views


def _colmap_txt_camera(folder, i):
    """``(fx, fy, cx, cy, R, t)`` of image ``i + 1`` read from the text files by hand (no loader code)."""
    cams = [ln.split() for ln in (folder / "cameras.txt").read_text().splitlines() if ln and ln[0] != "#"]
    imgs = [ln.split() for ln in (folder / "images.txt").read_text().splitlines() if ln and ln[0] != "#"]
    im = next(e for e in imgs if e[0] == str(i + 1))
    cam = next(e for e in cams if e[0] == im[8])
    assert cam[1] == "PINHOLE"
    w, x, y, z = map(float, im[1:5])
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return (*map(float, cam[4:8]), R, np.array(list(map(float, im[5:8]))))


def test_pixel_centre_convention_projection_round_trip():
    """A known 3D point lands on the same pixel through the DTU and the COLMAP versions of one camera.

    DTU's ``world_mat`` is OpenCV's (centre of pixel (0, 0) at (0, 0)), COLMAP's ``cx, cy`` put it at
    (0.5, 0.5): ``u_colmap = u_dtu + 0.5``; both loaders' scenes then project to ``u_colmap``."""
    d = scene_dir()
    sc = gt_scene(d)["cameras"]["train"]
    X = random_object_points(d, n=50)
    dtu, col = load_dtu(d / "dtu"), load_colmap(d / "colmap_txt")
    for i in range(len(sc)):
        fx, fy, cx, cy, R, t = _colmap_txt_camera(d / "colmap_txt/sparse/0", i)
        xc = X @ R.T + t
        uv_colmap = np.stack([fx * xc[:, 0] / xc[:, 2] + cx, fy * xc[:, 1] / xc[:, 2] + cy], -1)
        uv_dtu = project_opencv(np.array(sc[i]["K_opencv"]), np.array(sc[i]["w2c_opencv"]), X)
        np.testing.assert_allclose(uv_colmap, uv_dtu + 0.5, atol=1e-6)
        np.testing.assert_allclose(project_scene(col, i, to_norm(col, X)), uv_colmap, atol=1e-3)
        np.testing.assert_allclose(project_scene(dtu, i, to_norm(dtu, X)), uv_colmap, atol=1e-3)


def _tiny_colmap(root, model="SIMPLE_PINHOLE", params=(10.0, 4.0, 4.0), binary=False, size=8):
    """One 8x8 view at (0, 0, -5) looking down +z (R = I, t = (0, 0, 5)), hand-written."""
    from PIL import Image

    (root / "images").mkdir(parents=True)
    Image.fromarray(np.full((size, size, 3), 128, np.uint8)).save(root / "images/a.png")
    write_model(root / "sparse/0", ColmapModel({1: ColmapCamera(1, model, size, size, list(params))},
                                               {1: ColmapImage(1, np.array([1.0, 0, 0, 0]), np.array([0, 0, 5.0]),
                                                               1, "a.png")}), binary=binary)
    return root


def test_hand_worked_colmap_camera(tmp_path):
    # 1 SIMPLE_PINHOLE 8 8 10 4 4: the principal point (4, 4) is the image centre, so pixel (0, 0)'s centre
    # (0.5, 0.5) looks along x = (0.5 - 4) / 10 = -0.35, and pixels 3 and 4 are symmetric (-0.05, +0.05).
    scene = load_scene(_tiny_colmap(tmp_path / "c"))
    np.testing.assert_allclose(scene.intrinsics[0], [[10, 0, 4], [0, 10, 4], [0, 0, 1]])
    o, dirs = world_rays(scene, 0)
    dirs = dirs.reshape(8, 8, 3)
    np.testing.assert_allclose(dirs[0, 0, :2] / dirs[0, 0, 2], [-0.35, -0.35], atol=1e-6)
    np.testing.assert_allclose(dirs[3, 3, :2] / dirs[3, 3, 2], [-0.05, -0.05], atol=1e-6)
    np.testing.assert_allclose(dirs[4, 4, :2] / dirs[4, 4, 2], [0.05, 0.05], atol=1e-6)
    np.testing.assert_allclose(o[0], [0, 0, -5], atol=1e-5)   # centre = -R^T t


def test_quaternions_and_model_files_round_trip(tmp_path):
    # 90 deg about z: q = (cos 45, 0, 0, sin 45) -> R = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    c = np.sqrt(0.5)
    np.testing.assert_allclose(qvec_to_rotmat([c, 0, 0, c]), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q = q / np.linalg.norm(q) * np.sign(q[0])
        np.testing.assert_allclose(rotmat_to_qvec(qvec_to_rotmat(q)), q, atol=1e-10)
    model = ColmapModel({3: ColmapCamera(3, "OPENCV", 40, 30, [30.0, 31.0, 20.5, 15.25, -0.1, 0.01, 1e-3, -2e-3])},
                        {7: ColmapImage(7, np.array([c, 0, 0, c]), np.array([1.0, 2.0, 3.0]), 3, "sub dir/x y.png")},
                        points=rng.normal(size=(5, 3)), errors=rng.uniform(size=5))
    for binary in (True, False):
        write_model(tmp_path / str(binary), model, binary=binary)
        back = read_model(tmp_path / str(binary), tmp_path)
        assert back.cameras[3] == model.cameras[3]
        im = back.images[7]
        assert (im.name, im.camera_id) == ("sub dir/x y.png", 3)
        np.testing.assert_allclose(im.qvec, model.images[7].qvec)
        np.testing.assert_allclose(im.tvec, [1, 2, 3])
        np.testing.assert_allclose(back.points, model.points)
        np.testing.assert_allclose(back.errors, model.errors)


@pytest.mark.parametrize("model,params", [("SIMPLE_RADIAL", (-0.3,)), ("RADIAL", (-0.35, 0.1)),
                                          ("OPENCV", (-0.4, 0.15, 0.01, -0.01))])
def test_distorted_colmap_models_are_undistorted_at_load(tmp_path, model, params):
    src = synth_dir(shape="sphere", material="textured", resolution=64, n_views=6, n_test=1)
    out = write_colmap(src / "dtu", tmp_path / "c", binary=model != "RADIAL", distortion=(model, params))
    scene, ref = load_scene(out), load_dtu(src / "dtu")
    assert scene.extras["undistorted"] and scene.extras["camera_models"] == [model]
    assert_same_rays(scene, ref)   # pinhole after undistortion, with the same K
    truth = np.clip(np.load(src / "gt/arrays_train.npz")["rgb_linear"], 0, 1)
    inner = (slice(None), slice(6, -6), slice(6, -6))

    def err(images):   # two bilinear resamplings of aliased checker edges: compare at a coarser scale
        return np.abs(gaussian_filter(images, (0, 2, 2, 0)) - gaussian_filter(truth, (0, 2, 2, 0)))[inner].mean()

    raw = ref.images.copy()
    for i, name in enumerate(scene.names):   # negative control: the distorted files read as they are
        from nepf_core.color import srgb_to_linear
        from nepf_core.data.images import read_image
        raw[i] = srgb_to_linear(read_image(out / name))
    assert err(scene.images) < 0.01 and err(scene.images) < 0.6 * err(raw), (err(scene.images), err(raw))


@pytest.mark.parametrize("model,n", [("FULL_OPENCV", 12), ("OPENCV_FISHEYE", 8), ("FOV", 5),
                                     ("SIMPLE_RADIAL_FISHEYE", 4), ("THIN_PRISM_FISHEYE", 12)])
def test_unsupported_colmap_models_are_refused_by_name(tmp_path, model, n):
    root = _tiny_colmap(tmp_path / "c", model=model, params=[10.0, 10.0, 4.0, 4.0, *[0.01] * (n - 4)][:n],
                        binary=model == "OPENCV_FISHEYE")
    for check in (lambda: load_scene(root), lambda: validate_dataset(root)):
        try:
            out = check()
        except DatasetError as e:
            err = e.to_dict()
        else:
            err = out["errors"][0]
        assert err["code"] == "unsupported_camera"
        assert model in err["message"] and "colmap image_undistorter" in err["message"]
        assert "SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV" in err["message"]


def test_unknown_text_model_and_malformed_binaries(tmp_path):
    root = _tiny_colmap(tmp_path / "t")
    cams = root / "sparse/0/cameras.txt"
    cams.write_text(cams.read_text().replace("SIMPLE_PINHOLE", "WARPED_LENS"))
    with pytest.raises(DatasetError, match="WARPED_LENS.*unknown model") as e:
        load_scene(root)
    assert e.value.code == "unsupported_camera"
    root = _tiny_colmap(tmp_path / "b", binary=True)
    data = (root / "sparse/0/cameras.bin").read_bytes()
    (root / "sparse/0/cameras.bin").write_bytes(data[:-4])
    with pytest.raises(DatasetError, match="file ends early") as e:
        load_scene(root)
    assert e.value.code == "unreadable_cameras" and e.value.file == "sparse/0/cameras.bin"
    (root / "sparse/0/cameras.bin").write_bytes((2 ** 62).to_bytes(8, "little") + data[8:])
    with pytest.raises(DatasetError, match="do not fit"):   # a hostile count allocates nothing
        load_scene(root)


def test_colmap_missing_image_size_mismatch_and_undistorter_layout(tmp_path):
    d = scene_dir()
    root = tmp_path / "c"
    shutil.copytree(d / "colmap_txt", root)
    (root / "images/frame_00003.png").unlink()
    with pytest.raises(DatasetError, match="not in images/") as e:
        load_scene(root)
    assert e.value.code == "missing_image" and e.value.view == 3
    shutil.copy(d / "colmap_txt/images/frame_00003.png", root / "images")
    cams = root / "sparse/0/cameras.txt"
    cams.write_text(cams.read_text().replace("PINHOLE 40 32", "PINHOLE 80 64"))
    with pytest.raises(DatasetError, match="metadata says 80x64") as e:
        load_scene(root)
    assert e.value.code == "size_mismatch"
    # every file stays inside the folder: an image name or a model file pointing out of it is refused
    imgs = root / "sparse/0/images.txt"
    imgs.write_text(imgs.read_text().replace("frame_00002.png", "../../x.png"))
    with pytest.raises(DatasetError) as e:
        load_scene(root)
    assert e.value.code == "path_outside_dataset" and "../../x.png" in e.value.message
    (tmp_path / "elsewhere.txt").write_text(cams.read_text())
    cams.unlink()
    cams.symlink_to(tmp_path / "elsewhere.txt")
    with pytest.raises(DatasetError) as e:
        load_scene(root)
    assert e.value.code == "path_outside_dataset"
    # `colmap image_undistorter` writes sparse/ (no 0/) beside images/
    und = tmp_path / "undistorted"
    shutil.copytree(d / "colmap", und)
    shutil.move(und / "sparse/0", und / "sp")
    shutil.rmtree(und / "sparse")
    shutil.move(und / "sp", und / "sparse")
    assert_same_rays(load_scene(und), load_dtu(d / "dtu"))


def test_unknown_layout_names_the_layouts_and_the_commands(tmp_path):
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos/IMG_0001.jpg").write_bytes(b"")
    with pytest.raises(DatasetError) as e:
        load_scene(tmp_path / "photos")
    msg = e.value.message
    assert e.value.code == "unknown_layout"
    for part in ("DTU", "NeRF-synthetic", "nerfstudio", "instant-ngp", "COLMAP", "sparse/0/",
                 "colmap automatic_reconstructor", "ns-process-data images"):
        assert part in msg, part


def test_sparse_points_serve_the_object_region(monkeypatch):
    """The capture's points (COLMAP points3D, nerfstudio's ply) are in the scene's frame and are used
    in place of the ORB triangulation."""
    import nepf_core.data.sparse_points as sp
    from nepf_core.reframe import reframe_scene
    from nepf_core.train.rules.masks import decide_object_region

    d = scene_dir()
    V = read_ply_vertices(d / "gt/mesh.ply")
    for fmt in FORMATS:
        scene = load_scene(d / fmt)
        A = scene.world_from_norm
        world = scene.points.astype(np.float64) @ A[:3, :3].T + A[:3, 3]
        np.testing.assert_allclose(world, V[:: max(1, len(V) // 4000)], atol=1e-5)
        moved = reframe_scene(scene, A @ np.diag([0.5, 0.5, 0.5, 1.0]))   # points follow the frame
        np.testing.assert_allclose(moved.points, 2.0 * scene.points, rtol=1e-5)
        monkeypatch.setattr(sp, "triangulate_scene", lambda *a, **k: pytest.fail("triangulated"))
        _, decisions, _, _ = decide_object_region(scene)
        assert f"{scene.source_format} sparse points" in decisions[0].reason


def _ns_copy(tmp_path, **kw):
    d = scene_dir()
    return write_nerfstudio(d / "dtu", tmp_path / "ns", points=read_ply_vertices(d / "gt/mesh.ply")[::50], **kw), d


@pytest.mark.parametrize("applied", ["ns-process-data", None, "rotated"])
def test_nerfstudio_applied_transform_is_respected(tmp_path, applied):
    """Poses written in another frame (``transform_matrix = A c2w``) come back in the capture's world."""
    from nepf_core.data.convert import NS_APPLIED_TRANSFORM

    A = NS_APPLIED_TRANSFORM if applied == "ns-process-data" else None
    if applied == "rotated":   # any rigid A with a translation
        c, s = np.cos(0.7), np.sin(0.7)
        A = np.c_[np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ NS_APPLIED_TRANSFORM[:, :3], [0.3, -1.0, 2.0]]
    root, d = _ns_copy(tmp_path, applied=A)
    scene = load_nerfstudio(root)
    assert_same_rays(scene, load_dtu(d / "dtu"))
    Aw = scene.world_from_norm
    world = scene.points.astype(np.float64) @ Aw[:3, :3].T + Aw[:3, 3]
    np.testing.assert_allclose(world, read_ply_vertices(d / "gt/mesh.ply")[::50], atol=1e-5)


def test_nerfstudio_per_frame_intrinsics_and_refusals(tmp_path):
    root, d = _ns_copy(tmp_path)
    meta = json.loads((root / "transforms.json").read_text())
    for k, fr in enumerate(meta["frames"]):
        fr.update({key: meta[key] + (0.5 * k if key == "cx" else 0.0) for key in ("fl_x", "fl_y", "cx", "cy")})
    for key in ("fl_x", "fl_y", "cx", "cy"):
        del meta[key]
    (root / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(root)
    np.testing.assert_allclose(scene.intrinsics[:, 0, 2], 20.0 + 0.5 * np.arange(scene.n_views))

    def refused(edit, code, *parts):
        m = json.loads(json.dumps(meta))
        edit(m)
        (root / "transforms.json").write_text(json.dumps(m))
        with pytest.raises(DatasetError) as e:
            load_scene(root)
        assert e.value.code == code, e.value
        for p in parts:
            assert p in e.value.message
        v = validate_dataset(root)
        assert not v["ok"] and v["errors"][0]["code"] == code

    refused(lambda m: m.update(camera_model="OPENCV_FISHEYE"), "unsupported_camera", "OPENCV_FISHEYE", "fisheye")
    refused(lambda m: m.update(camera_model="EQUIRECTANGULAR"), "unsupported_camera", "EQUIRECTANGULAR", "360")
    refused(lambda m: m["frames"][2].pop("mask_path"), "count_mismatch", "mask_path")
    refused(lambda m: m.update(applied_transform=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0]]), "invalid_camera",
            "applied_transform")
    refused(lambda m: m.update(ply_file_path="../outside.ply"), "path_outside_dataset")
    refused(lambda m: m.update(ply_file_path="missing.ply"), "missing_file")


def test_ns_process_data_folder_is_nerfstudio_and_opencv_is_undistorted(tmp_path):
    """``ns-process-data`` writes transforms.json beside colmap/sparse/0: the folder is nerfstudio's."""
    src = synth_dir(shape="sphere", material="textured", resolution=64, n_views=6, n_test=1)
    root = write_nerfstudio(src / "dtu", tmp_path / "ns", distortion=(-0.3, 0.05, 0.005, -0.005))
    write_colmap(src / "dtu", tmp_path / "ns" / "colmap")
    assert resolve_dataset(root) == ("nerfstudio", root)
    scene = load_scene(root)
    assert scene.extras["undistorted"]
    assert_same_rays(scene, load_dtu(src / "dtu"))
    from scipy.ndimage import binary_dilation, binary_erosion

    ref = load_dtu(src / "dtu")
    for m, r in zip(scene.masks, ref.masks):   # the distorted masks come back with the images:
        edge = binary_dilation(r) & ~binary_erosion(r)   # they differ on the outline only
        assert not ((m != r) & ~edge)[6:-6, 6:-6].any()


def test_convert_and_make_scene_commands(tmp_path, capsys):
    from nepf_core.data import convert, synth

    d = scene_dir()
    assert convert.main([str(d / "dtu"), str(tmp_path / "c"), "--to", "colmap_txt",
                         "--points", str(d / "gt/mesh.ply")]) == 0
    scene = load_scene(tmp_path / "c")
    assert scene.extras["model_format"] == "txt" and len(scene.points) == len(read_ply_vertices(d / "gt/mesh.ply"))
    assert_same_rays(scene, load_dtu(d / "dtu"))
    assert synth.main([str(tmp_path / "s"), "--resolution", "16", "--views", "3", "--test-views", "0",
                       "--supersample", "1", "--formats", "colmap,nerfstudio"]) == 0
    assert resolve_dataset(tmp_path / "s/colmap")[0] == "colmap"
    assert resolve_dataset(tmp_path / "s/nerfstudio")[0] == "nerfstudio"
    assert resolve_dataset(tmp_path / "s") == ("dtu", tmp_path / "s/dtu")   # DTU still preferred beside them


@pytest.mark.parametrize("fmt", ["colmap_txt", "nerfstudio"])
def test_renders_of_one_run_agree_through_dtu_and_other_cameras(tmp_path, capsys, fmt):
    """One run (tiny, 3 steps, trained on the DTU form) rendered through the DTU cameras and
    through the same cameras written as COLMAP text / nerfstudio: the same pictures, within
    float noise (the poses pass through float32 and quaternions)."""
    from nepf_core.cli import main as nepf_main

    d = scene_dir()
    run = tmp_path / "run"
    assert nepf_main(["fit", str(d / "dtu"), "--out", str(run), "--config", "tiny", "--iters", "3", "--device", "cpu",
                      "--no-export", "--max-side", "0"]) == 0
    outs = {}
    for name in ("dtu", fmt):
        out = tmp_path / f"render_{name}"
        assert nepf_main(["render", str(run), "--cameras", str(d / name), "--out", str(out), "--device", "cpu",
                          "--max-side", "0"]) == 0
        with np.load(out / "arrays.npz") as z:
            outs[name] = {k: z[k] for k in ("pbr", "radiance", "alpha")}
    capsys.readouterr()
    for k in ("pbr", "radiance", "alpha"):
        np.testing.assert_allclose(outs[fmt][k], outs["dtu"][k], atol=2e-4, err_msg=k)
