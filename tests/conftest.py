"""Shared fixtures: small synthetic scenes written by the project's own scene maker."""

from __future__ import annotations

import os

import pytest

# Two cores: keep torch from oversubscribing when pytest runs alongside other processes.
os.environ.setdefault("OMP_NUM_THREADS", "2")


@pytest.fixture(scope="session")
def small_scene_dir(tmp_path_factory):
    """A 32x32 textured sphere: 8 train + 2 test views, DTU + Blender + gt/."""
    from nepf_core.data.synth import make_scene
    out = tmp_path_factory.mktemp("scene_sphere")
    make_scene(out, shape="sphere", material="textured", n_views=8, n_test=2, resolution=32)
    return out


@pytest.fixture(scope="session")
def small_scene(small_scene_dir):
    from nepf_core.data.detect import load_scene
    return load_scene(small_scene_dir / "dtu")
