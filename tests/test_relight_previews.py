"""The export's canonical relit previews and their record in the manifest."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from nepf_core.export.manifest import write_manifest
from nepf_core.relight.previews import canonical_camera, write_relit_previews
from tests.export_fixtures import SphereQuery, similarity


def test_canonical_camera_looks_at_the_centre():
    c, R = np.array([3.0, -1.0, 0.5]), 1.5
    cam = canonical_camera(c, R, (0, 0, 1), 64)
    c2w = np.asarray(cam["c2w_world"])
    assert np.allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-12) and np.linalg.det(c2w[:3, :3]) > 0
    to_c = c - c2w[:3, 3]
    assert np.allclose(c2w[:3, 2], to_c / np.linalg.norm(to_c))                 # optical axis through the centre
    # the bounding sphere subtends FILL (0.8) of the 40 deg vertical field of view
    assert math.degrees(2 * math.asin(R / np.linalg.norm(to_c))) == pytest.approx(0.8 * 40.0)
    assert c2w[:3, 1] @ np.array([0, 0, 1.0]) < 0                                # image down = world down
    assert math.degrees(math.asin(-c2w[:3, 2] @ np.array([0, 0, 1.0]))) == pytest.approx(20.0)


def test_relit_previews_are_written_and_recorded(tmp_path):
    q = SphereQuery()
    M = similarity()
    s = float(np.cbrt(np.linalg.det(M[:3, :3])))
    centre = M[:3, :3] @ q.center.numpy() + M[:3, 3]
    paths = write_relit_previews(q, M, tmp_path, centre, q.radius * s, up=(0, 0, 1), size=48)
    assert [p.name for p in paths] == ["relit_canonical_0.png", "relit_canonical_1.png", "relit_canonical_2.png",
                                       "relit_canonical.json"]
    imgs = [np.asarray(Image.open(p)).astype(float) for p in paths[:3]]
    for img in imgs:
        assert img.shape == (48, 48, 3) and img[0, 0].max() == 0      # black outside the sphere
    assert max(img[20:28, 20:28].max() for img in imgs) > 0           # the sphere fills the middle
    assert np.abs(imgs[0] - imgs[1]).max() > 20                       # three different lights
    rec = json.loads(paths[3].read_text())
    # hand-worked: R = 0.6 * 2.5 = 1.5, so the lights are 3 R = 4.5 from the centre at elevation 45 deg
    # and azimuths 0, 120, 240 deg measured from a_x = -y towards a_y = +x (the viewer's axes for
    # +Z up), each with I = 2 (3 R)^2 = 40.5 (irradiance 2 at the centre)
    h = math.sqrt(0.5)
    dirs = np.array([[0.0, -h, h], [h * math.sin(math.radians(120)), -h * math.cos(math.radians(120)), h],
                     [h * math.sin(math.radians(240)), -h * math.cos(math.radians(240)), h]])
    np.testing.assert_allclose([l["position_world"] for l in rec["lights"]], centre + 4.5 * dirs, rtol=1e-12)
    np.testing.assert_allclose([l["intensity_rgb"] for l in rec["lights"]], np.full((3, 3), 40.5), rtol=1e-12)
    assert rec["camera"]["width"] == 48 and rec["bsdf"] == "paper"
    man = write_manifest(tmp_path)
    kinds = {a["path"]: a["kind"] for a in man["artifacts"]}
    assert kinds["previews/relit_canonical_0.png"] == "preview" and kinds["previews/relit_canonical.json"] == "preview"
    assert man["relit_previews"] == rec
    assert json.loads((tmp_path / "manifest.json").read_text())["relit_previews"]["lights"] == rec["lights"]


def test_lit_side_faces_the_light(tmp_path):
    # light 0 sits at azimuth 0 (+x side, world frame = normalised frame here); the camera at azimuth
    # 30 deg sees +x on the image's left or right: the lit half of the sphere is on the side where
    # the projected light direction points
    q = SphereQuery(center=(0.0, 0.0, 0.0))
    paths = write_relit_previews(q, np.eye(4), tmp_path, np.zeros(3), q.radius, size=48)
    cam = json.loads(paths[3].read_text())["camera"]
    img = np.asarray(Image.open(paths[0])).astype(float).sum(-1)
    fwd = np.asarray(cam["target_world"]) - np.asarray(cam["position_world"])
    right = np.cross(fwd, np.asarray(cam["up"]))
    light_right = np.asarray(json.loads(paths[3].read_text())["lights"][0]["position_world"]) @ right > 0
    left, rightside = img[:, :24].sum(), img[:, 24:].sum()
    assert (rightside > left) == light_right
