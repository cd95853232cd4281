"""Every malformed input gives a DatasetError with a code, the file and the view named,
and the validator reports it as JSON without importing torch."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from datagen import copy_scene
from nepf_core.data import DatasetError
from nepf_core.data.blender import load_blender
from nepf_core.data.detect import load_scene
from nepf_core.data.dtu import load_dtu
from nepf_core.data.ingp import load_ingp
from nepf_core.data.validate import validate_dataset

REPO = Path(__file__).resolve().parents[1]


def _err(fn, *args, **kw) -> DatasetError:
    with pytest.raises(DatasetError) as ei:
        fn(*args, **kw)
    e = ei.value
    assert e.to_dict()["code"] == e.code and e.message
    return e


def _expect(e: DatasetError, code: str, file: str | None, view: int | None):
    assert (e.code, e.file, e.view) == (code, file, view), e.to_dict()
    # the message in str(e) names both, so a log line is enough to act on
    if file is not None:
        assert file in str(e)
    if view is not None:
        assert f"view {view}" in str(e)


@pytest.fixture
def dtu(tmp_path):
    return copy_scene(tmp_path) / "dtu"


@pytest.fixture
def blender(tmp_path):
    return copy_scene(tmp_path) / "blender"


def _edit_cams(dtu: Path, fn):
    cams = dict(np.load(dtu / "cameras.npz"))
    fn(cams)
    np.savez(dtu / "cameras.npz", **cams)


def _edit_json(folder: Path, fn, name="transforms_train.json"):
    meta = json.loads((folder / name).read_text())
    fn(meta)
    (folder / name).write_text(json.dumps(meta))  # allow_nan: NaN is written as the token NaN


# ---------------------------------------------------------------------------- DTU

def test_dtu_missing_image_is_a_count_mismatch(dtu):
    (dtu / "image/003.png").unlink()
    _expect(_err(load_dtu, dtu), "count_mismatch", "cameras.npz", 7)


def test_dtu_unreadable_and_truncated_images(dtu):
    (dtu / "image/002.png").write_bytes(b"this is not a png")
    _expect(_err(load_dtu, dtu), "unreadable_image", "image/002.png", 2)
    (dtu / "image/002.png").write_bytes((dtu / "image/005.png").read_bytes()[:60])
    _expect(_err(load_dtu, dtu), "unreadable_image", "image/002.png", 2)


def test_dtu_png_name_with_jpeg_content_is_fine_but_gif_is_not(dtu):
    Image.open(dtu / "image/001.png").convert("RGB").save(dtu / "image/001.png", format="JPEG", quality=95)
    assert load_dtu(dtu).n_views == 8
    Image.open(dtu / "image/001.png").save(dtu / "image/001.png", format="GIF")
    _expect(_err(load_dtu, dtu), "unsupported_image", "image/001.png", 1)


def test_dtu_mask_count_mismatch(dtu):
    (dtu / "mask/005.png").unlink()
    _expect(_err(load_dtu, dtu), "count_mismatch", "mask", 7)


def test_dtu_image_and_mask_size_mismatch(tmp_path):
    dtu = copy_scene(tmp_path) / "dtu"
    Image.open(dtu / "image/004.png").resize((20, 16)).save(dtu / "image/004.png")
    _expect(_err(load_dtu, dtu), "size_mismatch", "image/004.png", 4)
    Image.open(dtu / "image/000.png").save(dtu / "image/004.png")
    Image.open(dtu / "mask/006.png").resize((20, 16)).save(dtu / "mask/006.png")
    _expect(_err(load_dtu, dtu), "size_mismatch", "mask/006.png", 6)


def test_dtu_nonfinite_and_singular_cameras(dtu):
    _edit_cams(dtu, lambda c: c["world_mat_3"].__setitem__((0, 0), np.nan))
    _expect(_err(load_dtu, dtu), "nonfinite_camera", "cameras.npz", 3)
    _edit_cams(dtu, lambda c: c.__setitem__("world_mat_3", c["world_mat_0"]))

    def rank2(c):
        c["world_mat_2"][1, :3] = c["world_mat_2"][0, :3]
    _edit_cams(dtu, rank2)
    _expect(_err(load_dtu, dtu), "singular_camera", "cameras.npz", 2)


def test_dtu_camera_keys_and_scale_mats(dtu):
    _edit_cams(dtu, lambda c: c.pop("world_mat_4"))
    _expect(_err(load_dtu, dtu), "count_mismatch", "cameras.npz", 4)
    _edit_cams(dtu, lambda c: c.__setitem__("world_mat_4", c["world_mat_0"]))
    _edit_cams(dtu, lambda c: c.__setitem__("scale_mat_2", c["scale_mat_2"] * 2))
    _expect(_err(load_dtu, dtu), "invalid_camera", "cameras.npz", 2)
    _edit_cams(dtu, lambda c: c.__setitem__("scale_mat_2", c["scale_mat_0"]))
    _edit_cams(dtu, lambda c: c.__setitem__("world_mat_5", np.eye(3)))
    _expect(_err(load_dtu, dtu), "invalid_camera", "cameras.npz", 5)
    (dtu / "cameras.npz").write_bytes(b"PK\x03\x04garbage")
    _expect(_err(load_dtu, dtu), "unreadable_cameras", "cameras.npz", None)


@pytest.mark.parametrize("content", [b"garbage, not an npz at all", b"", None])
def test_dtu_garbage_camera_file_is_not_a_valid_npz(dtu, content):
    """numpy.load reads any non-zip, non-.npy file as a pickle; the message must say what is
    wrong (not an npz), never "pickled data". ``None``: a bare .npy saved under the npz name."""
    if content is None:
        with open(dtu / "cameras.npz", "wb") as f:
            np.save(f, np.eye(4))
    else:
        (dtu / "cameras.npz").write_bytes(content)
    e = _err(load_dtu, dtu)
    _expect(e, "unreadable_cameras", "cameras.npz", None)
    assert "not a valid .npz" in e.message and "pickle" not in e.message


def test_dtu_empty_mask(dtu):
    Image.fromarray(np.zeros((32, 40, 3), np.uint8)).save(dtu / "mask/001.png")
    _expect(_err(load_dtu, dtu), "empty_mask", "mask/001.png", 1)


def test_dtu_unsupported_format_and_ignored_junk(dtu):
    (dtu / "image/.DS_Store").write_bytes(b"junk")
    (dtu / "image/notes.txt").write_text("ignored")
    assert load_dtu(dtu).n_views == 8
    Image.open(dtu / "image/000.png").save(dtu / "image/008.bmp")
    _expect(_err(load_dtu, dtu), "unsupported_image", "image/008.bmp", None)


def test_dtu_zero_views_tiny_images_and_bad_downscale(dtu):
    _expect(_err(load_dtu, dtu, downscale=8), "image_too_small", "image/000.png", 0)
    _expect(_err(load_dtu, dtu, downscale=0), "bad_argument", None, None)
    _expect(_err(load_dtu, dtu, downscale=1.5), "bad_argument", None, None)
    for p in list((dtu / "image").iterdir()) + list((dtu / "mask").iterdir()):
        Image.new("RGB", (1, 1), (255, 255, 255)).save(p)
    _expect(_err(load_dtu, dtu), "image_too_small", "image/000.png", 0)
    for p in (dtu / "image").iterdir():
        p.unlink()
    _expect(_err(load_dtu, dtu), "no_views", "image", None)


def test_dtu_has_no_test_split(dtu):
    _expect(_err(load_dtu, dtu, "test"), "missing_split", ".", None)


# ---------------------------------------------------------------------------- Blender

def test_blender_missing_and_unreadable_images(blender):
    (blender / "train/r_3.png").unlink()
    e = _err(load_blender, blender)
    _expect(e, "missing_image", "train/r_3", 3)
    assert ".png" in e.message  # says which extensions were tried
    Image.open(blender / "train/r_0.png").save(blender / "train/r_3.png")
    (blender / "train/r_2.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    _expect(_err(load_blender, blender), "unreadable_image", "train/r_2.png", 2)


def test_blender_bad_json(blender):
    text = (blender / "transforms_train.json").read_text()
    (blender / "transforms_train.json").write_text(text[: len(text) // 2])
    e = _err(load_blender, blender)
    _expect(e, "bad_json", "transforms_train.json", None)
    assert "line" in e.message
    (blender / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7}))
    _expect(_err(load_blender, blender), "bad_json", "transforms_train.json", None)
    (blender / "transforms_train.json").write_text(text)
    _edit_json(blender, lambda m: m["frames"][6].__setitem__("transform_matrix", [[1, 0, 0], [0, 1, 0]]))
    _expect(_err(load_blender, blender), "bad_json", "transforms_train.json", 6)
    (blender / "transforms_train.json").write_text(text)
    _edit_json(blender, lambda m: [m.pop(k) for k in ("camera_angle_x", "fl_x", "fl_y")])
    _expect(_err(load_blender, blender), "bad_json", "transforms_train.json", 0)


def test_blender_nonfinite_and_singular_cameras(blender):
    text = (blender / "transforms_train.json").read_text()
    _edit_json(blender, lambda m: m["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan")))
    _expect(_err(load_blender, blender), "nonfinite_camera", "transforms_train.json", 1)
    (blender / "transforms_train.json").write_text(text)

    def zero_rot(m):
        for r in range(3):
            m["frames"][2]["transform_matrix"][r][:3] = [0.0, 0.0, 0.0]
    _edit_json(blender, zero_rot)
    _expect(_err(load_blender, blender), "singular_camera", "transforms_train.json", 2)
    (blender / "transforms_train.json").write_text(text)
    _edit_json(blender, lambda m: m.__setitem__("fl_x", -10.0))
    _expect(_err(load_blender, blender), "singular_camera", "transforms_train.json", 0)


def test_blender_empty_alpha_mask_and_rgba_rgb_mix(blender):
    rgba = np.array(Image.open(blender / "train/r_5.png"))
    rgba[..., 3] = 0
    Image.fromarray(rgba).save(blender / "train/r_5.png")
    _expect(_err(load_blender, blender), "empty_mask", "train/r_5.png", 5)
    Image.open(blender / "train/r_0.png").save(blender / "train/r_5.png")
    Image.open(blender / "train/r_6.png").convert("RGB").save(blender / "train/r_6.png")
    _expect(_err(load_blender, blender), "count_mismatch", "train/r_6.png", 6)


def test_blender_size_mismatch(blender):
    Image.open(blender / "train/r_4.png").resize((20, 16)).save(blender / "train/r_4.png")
    _expect(_err(load_blender, blender), "size_mismatch", "train/r_4.png", 4)
    _edit_json(blender, lambda m: [m.pop("w"), m.pop("h")])  # no declared size: view 0 decides
    _expect(_err(load_blender, blender), "size_mismatch", "train/r_4.png", 4)


def test_blender_unsupported_image_and_zero_views(blender):
    Image.open(blender / "train/r_1.png").save(blender / "train/r_1.tiff")
    (blender / "train/r_1.png").unlink()
    _edit_json(blender, lambda m: m["frames"][1].__setitem__("file_path", "./train/r_1.tiff"))
    _expect(_err(load_blender, blender), "unsupported_image", "train/r_1.tiff", 1)
    _edit_json(blender, lambda m: m.__setitem__("frames", []))
    _expect(_err(load_blender, blender), "no_views", "transforms_train.json", None)
    _expect(_err(load_blender, blender, "val"), "missing_split", "transforms_val.json", None)


def test_ingp_fisheye_and_missing_split(tmp_path):
    d = tmp_path / "ngp"
    d.mkdir()
    Image.new("RGB", (16, 16)).save(d / "a.png")
    meta = {"fl_x": 10, "fl_y": 10, "cx": 8, "cy": 8, "w": 16, "h": 16, "is_fisheye": True,
            "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]}
    (d / "transforms.json").write_text(json.dumps(meta))
    _expect(_err(load_ingp, d), "unsupported_camera", "transforms.json", 0)
    _expect(_err(load_ingp, d, "test"), "missing_split", "transforms.json", None)


# ---------------------------------------------------------------------------- layout

def test_unknown_layouts(tmp_path):
    _expect(_err(load_scene, tmp_path / "nope"), "unknown_layout", str(tmp_path / "nope"), None)
    (tmp_path / "empty").mkdir()
    _expect(_err(load_scene, tmp_path / "empty"), "unknown_layout", ".", None)
    (tmp_path / "junk" / "a" / "b").mkdir(parents=True)
    (tmp_path / "junk" / "a" / "b" / "readme.txt").write_text("hi")
    _expect(_err(load_scene, tmp_path / "junk"), "unknown_layout", "a/b", None)
    (tmp_path / "cams_only").mkdir()
    np.savez(tmp_path / "cams_only" / "cameras.npz", world_mat_0=np.eye(4))
    _expect(_err(load_scene, tmp_path / "cams_only"), "unknown_layout", ".", None)


# ---------------------------------------------------------------------------- validator

def _run_validate(path: Path) -> tuple[int, dict, str]:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    p = subprocess.run([sys.executable, "-m", "nepf_core.data.validate", str(path)], capture_output=True,
                       text=True, env=env, timeout=120)
    return p.returncode, json.loads(p.stdout), p.stderr


def test_validate_cli_ok_and_errors(tmp_path):
    scene = copy_scene(tmp_path)
    rc, out, _ = _run_validate(scene)
    assert rc == 0
    assert out == {"ok": True, "format": "dtu", "n_views": 8, "width": 40, "height": 32,
                   "working_width": 40, "working_height": 32, "has_masks": True,
                   "splits": {"train": 8}, "total_pixels": 8 * 40 * 32, "root": "dtu",
                   "holdout_default_every": 0, "holdout_max_every": 4}   # 8 views: < 16, 8 // 2
    (scene / "dtu/image/001.png").write_bytes(b"garbage")
    (scene / "dtu/image/006.png").write_bytes(b"garbage")
    rc, out, err = _run_validate(scene)
    assert rc == 2 and out["ok"] is False and "Traceback" not in err
    assert [(e["code"], e["file"], e["view"]) for e in out["errors"]] == [
        ("unreadable_image", "image/001.png", 1), ("unreadable_image", "image/006.png", 6)]


def test_validate_function_blender_splits_and_bad_test_split(tmp_path):
    b = copy_scene(tmp_path) / "blender"
    assert validate_dataset(b) == {"ok": True, "format": "blender", "n_views": 8, "width": 40,
                                   "height": 32, "working_width": 40, "working_height": 32,
                                   "has_masks": True, "splits": {"train": 8, "test": 2},
                                   "total_pixels": (8 + 2) * 40 * 32, "root": ".",
                                   "holdout_default_every": 0, "holdout_max_every": 4}
    (b / "test/r_1.png").unlink()
    out = validate_dataset(b)
    assert out["ok"] is False
    assert out["errors"] == [{"code": "missing_image", "file": "test/r_1", "view": 1,
                              "message": out["errors"][0]["message"]}]


def test_validate_is_torch_free(tmp_path):
    scene = copy_scene(tmp_path)
    code = ("import sys, nepf_core.data, nepf_core.data.validate as v; "
            f"r = v.validate_dataset({str(scene / 'blender')!r}); assert r['ok'], r; "
            "from nepf_core.data.detect import load_scene; s = load_scene(" + repr(str(scene)) + "); "
            "assert s.n_views == 8; "
            "bad = [m for m in sys.modules if m == 'torch' or m.startswith('torch.')]; "
            "assert not bad, bad; print('clean')")
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert p.returncode == 0 and p.stdout.strip() == "clean", p.stderr
