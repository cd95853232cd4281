"""bench/colmap_roundtrip.py: the two forms of one scene hold the same views, neither with masks."""

import numpy as np

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
