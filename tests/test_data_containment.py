"""Every file a dataset names must resolve inside the dataset folder (issue 23, finding 1).

Absolute ``file_path`` values, ``../..`` escapes and symbolic links out of the folder are
refused with ``path_outside_dataset``, naming the frame and the path as written, never the
resolved server path, and with the same message whether the outside file exists or not.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from datagen import copy_scene
from nepf_core.data import DatasetError
from nepf_core.data.blender import load_blender
from nepf_core.data.detect import load_scene
from nepf_core.data.dtu import load_dtu
from nepf_core.data.ingp import load_ingp
from nepf_core.data.paths import rel
from nepf_core.data.validate import validate_dataset


def _err(fn, *args, **kw) -> DatasetError:
    with pytest.raises(DatasetError) as ei:
        fn(*args, **kw)
    return ei.value


def _set_file_path(json_path: Path, view: int, written: str) -> None:
    meta = json.loads(json_path.read_text())
    meta["frames"][view]["file_path"] = written
    json_path.write_text(json.dumps(meta))


@pytest.fixture
def scene(tmp_path):
    return copy_scene(tmp_path)


@pytest.fixture
def outside(tmp_path):
    """A real PNG outside the dataset folder (a copy of one of its own images)."""
    d = tmp_path / "elsewhere"
    d.mkdir()
    shutil.copy(copy_scene(tmp_path / "src") / "blender/train/r_0.png", d / "x.png")
    return d / "x.png"


def _check_outside(load, ds: Path, written: str, outside: Path, *, file: str, view: int | None) -> str:
    """The loader refuses ``written`` with the same message whether ``outside`` exists or not."""
    messages = []
    for present in (True, False):
        if not present:
            outside.unlink()
        e = _err(load, ds)
        assert (e.code, e.file, e.view) == ("path_outside_dataset", file, view), e.to_dict()
        assert written in e.message
        messages.append(str(e))
    assert messages[0] == messages[1]
    return messages[0]


@pytest.mark.parametrize("kind", ["absolute", "dotdot", "dotdot_no_extension"])
def test_blender_file_path_outside_is_refused_without_existence_oracle(scene, outside, kind):
    ds = scene / "blender"
    written = {"absolute": str(outside),
               "dotdot": os.path.relpath(outside, ds),          # ../../elsewhere/x.png
               "dotdot_no_extension": os.path.relpath(outside.with_suffix(""), ds)}[kind]
    assert kind == "absolute" or written.startswith("../../")
    _set_file_path(ds / "transforms_train.json", 2, written)
    msg = _check_outside(load_blender, ds, written, outside, file="transforms_train.json", view=2)
    if kind != "absolute":   # the written path is relative: no server path at all in the message
        assert str(ds.parent.parent) not in msg and str(outside.resolve()) not in msg


def test_blender_symlink_out_of_the_folder_is_refused(scene, outside):
    ds = scene / "blender"
    link = ds / "train/r_1.png"
    link.unlink()
    link.symlink_to(outside)
    msg = _check_outside(load_blender, ds, "./train/r_1.png", outside, file="transforms_train.json", view=1)
    assert str(outside) not in msg and str(outside.resolve()) not in msg


def test_symlinked_folder_and_json_out_of_the_folder_are_refused(scene, outside, tmp_path):
    ds = scene / "blender"
    shutil.move(ds / "train", tmp_path / "train_elsewhere")
    (ds / "train").symlink_to(tmp_path / "train_elsewhere")
    e = _err(load_blender, ds)
    assert (e.code, e.view) == ("path_outside_dataset", 0) and "./train/r_0" in e.message
    assert str(tmp_path) not in str(e)
    (ds / "train").unlink()
    shutil.move(tmp_path / "train_elsewhere", ds / "train")
    shutil.move(ds / "transforms_test.json", tmp_path / "t.json")
    (ds / "transforms_test.json").symlink_to(tmp_path / "t.json")
    e = _err(load_blender, ds, "test")
    assert (e.code, e.file) == ("path_outside_dataset", "transforms_test.json")
    assert str(tmp_path) not in str(e)


def test_ingp_absolute_file_path_is_refused(scene, outside):
    ds = scene / "blender"
    (ds / "transforms_test.json").unlink()
    (ds / "transforms_train.json").rename(ds / "transforms.json")
    assert load_ingp(ds).n_views == 8   # the layout itself loads
    _set_file_path(ds / "transforms.json", 5, str(outside))
    _check_outside(load_ingp, ds, str(outside), outside, file="transforms.json", view=5)
    assert validate_dataset(ds)["errors"][0]["code"] == "path_outside_dataset"


def test_dtu_symlinked_image_mask_folder_and_cameras_are_refused(scene, outside, tmp_path):
    ds = scene / "dtu"
    img = ds / "image/003.png"
    img.unlink()
    img.symlink_to(outside)
    msg = _check_outside(load_dtu, ds, "image/003.png", outside, file="image/003.png", view=None)
    assert str(tmp_path) not in msg
    img.unlink()
    shutil.copy(ds / "image/002.png", img)
    assert load_dtu(ds).n_views == 8

    shutil.move(ds / "mask", tmp_path / "masks_elsewhere")
    (ds / "mask").symlink_to(tmp_path / "masks_elsewhere")
    e = _err(load_dtu, ds)
    assert (e.code, e.file) == ("path_outside_dataset", "mask") and str(tmp_path) not in str(e)
    (ds / "mask").unlink()
    shutil.move(tmp_path / "masks_elsewhere", ds / "mask")

    shutil.move(ds / "cameras.npz", tmp_path / "cams.npz")
    (ds / "cameras.npz").symlink_to(tmp_path / "cams.npz")
    e = _err(load_scene, ds)
    assert (e.code, e.file) == ("path_outside_dataset", "cameras.npz") and str(tmp_path) not in str(e)


def test_links_inside_the_folder_are_fine(scene):
    """Containment is about where a path resolves, not about links as such."""
    ds = scene / "blender"
    (ds / "train/r_4.png").rename(ds / "train/real_4.png")
    (ds / "train/r_4.png").symlink_to("real_4.png")
    _set_file_path(ds / "transforms_train.json", 6, str((ds / "train/r_6.png").resolve()))  # absolute, inside
    s = load_blender(ds)
    ref = load_blender(copy_scene(scene.parent / "ref") / "blender")
    np.testing.assert_array_equal(s.images, ref.images)


def test_missing_file_inside_is_named_relative_to_the_root(scene):
    ds = scene / "blender"
    _set_file_path(ds / "transforms_train.json", 3, "./train/../train/nothing_here")
    e = _err(load_blender, ds)
    assert (e.code, e.file, e.view) == ("missing_image", "train/nothing_here", 3)
    assert str(scene) not in str(e)


def test_rel_never_returns_an_absolute_path(tmp_path):
    assert rel(tmp_path / "a" / "b.png", tmp_path) == "a/b.png"
    assert rel(tmp_path / "a" / ".." / "c.png", tmp_path) == "c.png"
    assert rel("/somewhere/else/x.png", tmp_path) == "x.png"


def test_cli_fit_reports_the_path_as_written(scene, outside, tmp_path, capsys):
    from nepf_core.cli import main
    ds = scene / "blender"
    written = os.path.relpath(outside, ds)
    _set_file_path(ds / "transforms_train.json", 0, written)
    assert main(["fit", str(ds), "--out", str(tmp_path / "run"), "--config", "tiny", "--iters", "1",
                 "--no-export"]) == 2
    err = capsys.readouterr().err
    assert written in err and "points outside the dataset folder" in err
    assert str(outside.resolve()) not in err


def test_run_job_outputs_hold_no_absolute_path(tmp_path, monkeypatch):
    """summary.json (served by the artifact route) names files relative to the run folder,
    and run_job trains at the working resolution it is given."""
    import nepf_core.jobs as jobs

    def stub_export(run_dir, **_kw):   # the export itself is tested elsewhere; only its path matters here
        (Path(run_dir) / "manifest.json").write_text("{}")
        return Path(run_dir) / "manifest.json"

    monkeypatch.setattr(jobs, "export_run", stub_export)
    monkeypatch.setattr("nepf_core.export.manifest.write_manifest", lambda run: None)
    ds = copy_scene(tmp_path) / "dtu"
    summary = jobs.run_job(ds, tmp_path / "run", preset="tiny", iters=2, device="cpu", max_side=20,
                           log=lambda *a: None)
    text = (tmp_path / "run" / "summary.json").read_text()
    assert str(tmp_path) not in text and str(tmp_path.resolve()) not in text
    saved = json.loads(text)
    assert saved["manifest"] == summary["manifest"] == "manifest.json"
    assert saved["working_size"] == [20, 16]
    for name in ("report.json", "metrics.jsonl"):
        if (tmp_path / "run" / name).exists():
            assert str(tmp_path) not in (tmp_path / "run" / name).read_text(), name


def test_nul_in_a_file_path_is_a_clear_error(scene):
    ds = scene / "blender"
    _set_file_path(ds / "transforms_train.json", 1, "./train/r_1\u0000.png")
    e = _err(load_blender, ds)
    assert (e.code, e.file, e.view) == ("bad_json", "transforms_train.json", 1) and "NUL" in e.message
