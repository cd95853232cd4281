"""bench/colmap_roundtrip.py: the two forms of one scene hold the same views, neither with masks."""

import numpy as np
import pytest

from bench.colmap_roundtrip import prepare
from nepf_core.data.detect import load_scene


def test_prepare_gives_the_same_views_without_masks(small_scene_dir, tmp_path):
    forms = prepare(small_scene_dir, tmp_path)
    assert not (forms["dtu"] / "mask").exists()
    dtu, colmap = load_scene(forms["dtu"]), load_scene(forms["colmap"])
    assert not dtu.has_masks and not colmap.has_masks
    assert dtu.n_views == colmap.n_views == load_scene(small_scene_dir / "dtu").n_views
    np.testing.assert_allclose(np.asarray(dtu.images), np.asarray(colmap.images), atol=1e-6)
    # the same cameras in the world: camera centres through each load's world_from_norm
    def centres(s):
        c = np.asarray(s.c2w, dtype=np.float64)[:, :3, 3]
        w = np.asarray(s.world_from_norm, dtype=np.float64)
        return c @ w[:3, :3].T + w[:3, 3]
    np.testing.assert_allclose(centres(dtu), centres(colmap), atol=1e-4)
    assert prepare(small_scene_dir, tmp_path) == forms      # a second call reuses what is there


def test_the_points_form_carries_points3d_on_the_true_surface(small_scene_dir, tmp_path):
    forms = prepare(small_scene_dir, tmp_path)
    dtu, with_points = load_scene(forms["dtu"]), load_scene(forms["colmap_points"])
    assert not with_points.has_masks and with_points.points is not None and len(with_points.points) > 100
    np.testing.assert_allclose(np.asarray(dtu.images), np.asarray(with_points.images), atol=1e-6)
    # in the world the points lie on the scene's true mesh (a sphere: at its vertices' radius)
    import trimesh
    w = np.asarray(with_points.world_from_norm, dtype=np.float64)
    world = np.asarray(with_points.points, dtype=np.float64) @ w[:3, :3].T + w[:3, 3]
    mesh = trimesh.load(small_scene_dir / "gt" / "mesh.ply", force="mesh")
    centre = mesh.vertices.mean(0)
    radius = np.linalg.norm(mesh.vertices - centre, axis=1).mean()
    np.testing.assert_allclose(np.linalg.norm(world - centre, axis=1), radius, rtol=0.01)


def test_surface_points_face_two_cameras(tmp_path):
    import trimesh

    from bench.colmap_roundtrip import surface_points
    trimesh.creation.icosphere(subdivisions=3, radius=0.5).export(tmp_path / "ball.ply")
    cams = np.array([[0.0, 0.0, 3.0], [0.4, 0.0, 3.0], [0.0, 0.0, -3.0]])   # two above, one below
    pts = surface_points(tmp_path / "ball.ply", cams, n=2000)
    np.testing.assert_allclose(np.linalg.norm(pts, axis=1), 0.5, atol=0.01)
    # only the two cameras above can both face a point: the upper cap they share, none below
    assert pts[:, 2].min() > -0.05 and 0.3 < len(pts) / 2000 < 0.55


def test_only_the_forms_asked_for_are_written(small_scene_dir, tmp_path):
    forms = prepare(small_scene_dir, tmp_path, ("colmap",))
    assert set(forms) == {"dtu", "colmap"} and not (tmp_path / "colmap_points_txt").exists()


def test_an_unknown_form_is_named_and_nothing_is_written(small_scene_dir, tmp_path):
    with pytest.raises(SystemExit, match="unknown form.*colmap_bin"):
        prepare(small_scene_dir, tmp_path / "out", ("dtu", "colmap_bin"))
    assert not (tmp_path / "out").exists()
