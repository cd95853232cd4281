"""glTF's +Y-up frame (issue 34): the up axis from the cameras, the rotation into the GLB, and the
GLB read back with pygltflib (up on +Y, no node transform, normals and winding consistent).

Scenes are generated here: rings of ``look_at`` cameras with a known up, the project's synthetic
DTU scene (+Z up) with its world rotated so that another axis is up, and the analytic sphere of
``export_fixtures`` exported under a world whose up is not +Z.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pygltflib
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from datagen import synth_dir  # noqa: E402
from export_fixtures import SphereQuery  # noqa: E402
from nepf_core.data.synth_cameras import look_at  # noqa: E402
from nepf_core.up_axis import (UP_AXES, UpFrame, axis_from_vector, axis_vector, camera_up_world,  # noqa: E402
                               gltf_from_world, parse_up_axis, resolve_up_frame)


def rotation_taking(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A proper rotation with ``Q a = b`` (unit vectors; Rodrigues about ``a x b``)."""
    v, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        p = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        k = np.cross(a, p) / np.linalg.norm(np.cross(a, p))
        return 2 * np.outer(k, k) - np.eye(3)   # 180 degrees about k
    kx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + kx + kx @ kx / (1 + c)


def ring_cameras(up: np.ndarray, n: int = 12, elevation_deg: float = 25.0, seed: int = 0) -> np.ndarray:
    """``[n,4,4]`` OpenCV c2w on a ring about ``up`` looking at the origin, with small random rolls."""
    rng = np.random.default_rng(seed)
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    el = np.radians(elevation_deg)
    c2w = []
    for az in np.linspace(0, 2 * np.pi, n, endpoint=False):
        eye = 3.0 * (np.cos(el) * (np.cos(az) * e1 + np.sin(az) * e2) + np.sin(el) * up)
        tilt = up + 0.15 * rng.normal(size=3)   # a hand-held camera: up only roughly level
        c2w.append(look_at(eye, np.zeros(3), up=tilt))
    return np.stack(c2w)


# --------------------------------------------------------------------------- the rotation table
def test_each_rotation_is_proper_and_takes_its_axis_to_plus_y():
    for axis in UP_AXES:
        r = gltf_from_world(axis)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=0)
        assert np.linalg.det(r) == pytest.approx(1.0)   # a rotation, not a mirror
        np.testing.assert_allclose(r @ axis_vector(axis), [0, 1, 0], atol=0)
    # hand-worked: a +Z-up world is Blender's (x, y, z) -> (x, z, -y)
    np.testing.assert_allclose(gltf_from_world("+z") @ [1.0, 2.0, 3.0], [1.0, 3.0, -2.0])
    np.testing.assert_allclose(gltf_from_world("-y") @ [1.0, 2.0, 3.0], [-1.0, -2.0, 3.0])
    assert parse_up_axis("Z") == "+z" and parse_up_axis(" -Y ") == "-y" and parse_up_axis("auto") is None
    with pytest.raises(ValueError, match="auto, \\+x, -x"):
        parse_up_axis("up")


# --------------------------------------------------------------------------- detection
@pytest.mark.parametrize("axis", UP_AXES)
def test_up_is_the_snapped_mean_of_the_camera_ups(axis):
    up = axis_vector(axis)
    c2w = ring_cameras(up)
    assert axis_from_vector(camera_up_world(c2w)) == axis
    # the same cameras in a normalised frame: world_from_norm = [s Q | t] brings them back
    q = rotation_taking(np.array([0.0, 0.0, 1.0]), np.array([1.0, 1.0, 1.0]) / np.sqrt(3))
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = 2.5 * q, (3.0, -1.0, 0.5)
    c2w_norm = c2w.copy()
    c2w_norm[:, :3, :3] = q.T @ c2w[:, :3, :3]
    assert axis_from_vector(camera_up_world(c2w_norm, m)) == axis
    fr = resolve_up_frame(None, camera_up_world(c2w))
    assert (fr.world_up, fr.source) == (axis, "cameras")


def test_cameras_that_disagree_give_the_default_and_an_override_wins():
    # up vectors of cameras all around a sphere (rolled with their azimuth) cancel out
    c2w = np.concatenate([ring_cameras(axis_vector(a), n=8) for a in UP_AXES])
    mean = camera_up_world(c2w)
    assert np.linalg.norm(mean) < 0.05
    assert resolve_up_frame(None, mean) == UpFrame("+z", "default", tuple(mean))
    assert resolve_up_frame("-x", mean).world_up == "-x" and resolve_up_frame("-x", mean).source == "override"
    assert resolve_up_frame("auto", None) == UpFrame("+z", "default", None)


def rotate_dtu_world(src: Path, dst: Path, q: np.ndarray) -> None:
    """Copy a DTU folder with its world rotated, ``x' = Q x``: ``world_mat' = world_mat Q^T``
    (world -> camera reads ``x = Q^T x'``), ``scale_mat' = Q scale_mat``."""
    shutil.copytree(src, dst)
    q4 = np.eye(4)
    q4[:3, :3] = q
    cams = dict(np.load(src / "cameras.npz"))
    for k in list(cams):
        if k.startswith("world_mat_") and not k.startswith("world_mat_inv"):
            cams[k] = cams[k] @ q4.T
        elif k.startswith("scale_mat_") and not k.startswith("scale_mat_inv"):
            cams[k] = q4 @ cams[k]
    for k in list(cams):
        if "_inv_" in k:
            cams[k] = np.linalg.inv(cams[k.replace("_inv", "")])
    np.savez(dst / "cameras.npz", **cams)


@pytest.mark.parametrize("axis", ["-y", "+x"])
def test_up_detected_through_the_dtu_loader(tmp_path, axis):
    from nepf_core.data.detect import load_scene

    src = synth_dir() / "dtu"
    scene = load_scene(src)
    assert axis_from_vector(camera_up_world(scene.c2w, scene.world_from_norm)) == "+z"   # synthetic: +Z up
    q = rotation_taking(np.array([0.0, 0.0, 1.0]), axis_vector(axis))
    rotate_dtu_world(src, tmp_path / "dtu", q)
    rotated = load_scene(tmp_path / "dtu")
    assert axis_from_vector(camera_up_world(rotated.c2w, rotated.world_from_norm)) == axis


# --------------------------------------------------------------------------- the GLB read back
def _accessor(gltf, blob, idx):
    acc = gltf.accessors[idx]
    view = gltf.bufferViews[acc.bufferView]
    dtype = {5126: np.float32, 5125: np.uint32}[acc.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[acc.type]
    arr = np.frombuffer(blob, dtype=dtype, count=acc.count * width, offset=(view.byteOffset or 0) + (acc.byteOffset or 0))
    return arr.reshape(acc.count, width).astype(np.float64) if width > 1 else arr


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The analytic sphere exported from a world whose up is -Y (DTU-like), rotated by 30 degrees
    about that up and moved, so the rotation into the GLB is not the identity."""
    from nepf_core.export import export_asset

    out = tmp_path_factory.mktemp("gltf_frame")
    q = rotation_taking(np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0]))
    spin = np.array([[np.cos(0.5), 0, np.sin(0.5)], [0, 1, 0], [-np.sin(0.5), 0, np.cos(0.5)]])   # about y
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = 2.0 * spin @ q, (1.0, -2.0, 0.5)
    # the sphere's top in the normalised frame is +z, which this world calls -y (up)
    frame = resolve_up_frame(None, camera_up_world(ring_cameras(np.array([0.0, 0.0, 1.0])), m))
    assert frame.world_up == "-y" and frame.source == "cameras"
    query = SphereQuery()
    export_asset(query, m, out, texture_size=64, max_faces=1500, mesh_resolution=40, light_samples=800,
                 previews=False, frame=frame, log=lambda *_: None)
    gltf = pygltflib.GLTF2().load_binary(str(out / "asset.glb"))
    return {"dir": out, "m": m, "q": query, "frame": frame, "gltf": gltf}


def test_glb_puts_world_up_on_plus_y_without_a_node_transform(exported):
    gltf, m, query = exported["gltf"], exported["m"], exported["q"]
    node = gltf.nodes[gltf.scenes[gltf.scene].nodes[0]]
    assert node.matrix is None and node.rotation is None and node.translation is None and node.scale is None
    ex = gltf.asset.extras["nepf"]
    r = np.asarray(ex["gltf_from_world"], np.float64)
    np.testing.assert_allclose(r, gltf_from_world("-y"))
    assert ex["up"] == [0.0, 1.0, 0.0] and ex["world_up"] == "-y" and ex["up_source"] == "cameras"
    blob = gltf.binary_blob()
    prim = gltf.meshes[0].primitives[0]
    v = _accessor(gltf, blob, prim.attributes.POSITION)
    n = _accessor(gltf, blob, prim.attributes.NORMAL)
    centre_w = m[:3, :3] @ query.center.numpy() + m[:3, 3]
    radius_w = query.radius * 2.0
    centre_g = r @ centre_w
    # every GLB vertex is the world sphere's, rotated: same centre, same radius (world units)
    d = np.linalg.norm(v - centre_g, axis=-1)
    h = 2.0 / 39 * 2.0   # marching-cubes voxel in world units
    assert np.abs(d - radius_w).max() < 0.5 * h
    # the world's top (centre + r * up_world) is the GLB's highest point, on +Y
    top_g = r @ (centre_w + radius_w * axis_vector("-y"))
    np.testing.assert_allclose(top_g - centre_g, [0.0, radius_w, 0.0], atol=1e-12)
    assert v[:, 1].max() == pytest.approx(top_g[1], abs=0.5 * h)
    # normals: rotated like the vertices (outward radial in the GLB frame)
    assert np.min(((v - centre_g) / d[:, None] * n).sum(-1)) > 0.99


def test_glb_keeps_handedness_winding_agrees_with_normals(exported):
    gltf = exported["gltf"]
    blob = gltf.binary_blob()
    prim = gltf.meshes[0].primitives[0]
    v = _accessor(gltf, blob, prim.attributes.POSITION)
    n = _accessor(gltf, blob, prim.attributes.NORMAL)
    f = _accessor(gltf, blob, prim.indices).reshape(-1, 3)
    # glTF: front faces are counter-clockwise, so (v1 - v0) x (v2 - v0) points along the normal
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    agree = (cross * n[f].mean(axis=1)).sum(-1)
    assert (agree > 0).all(), f"{(agree <= 0).sum()} of {len(f)} triangles wound against their normals"
    # and outward: the signed volume of the closed mesh is positive (a mirror would flip it)
    vol = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0
    assert vol > 0


def test_lights_and_light_field_in_the_glb_frame_with_the_world_named(exported):
    d, m, query = exported["dir"], exported["m"], exported["q"]
    r = gltf_from_world("-y")
    light_w = m[:3, :3] @ query.light_pos.numpy() + m[:3, 3]
    lights = json.loads((d / "lights.json").read_text())
    assert lights["frame"] == "glb" and lights["world"]["frame"] == "world"
    np.testing.assert_allclose(lights["gltf_from_world"], r)
    np.testing.assert_allclose(lights["point_light"]["position"], r @ light_w, atol=2e-2)
    np.testing.assert_allclose(lights["world"]["point_light"]["position"], light_w, atol=2e-2)
    np.testing.assert_allclose(lights["dominant_direction"], r @ np.asarray(lights["world"]["dominant_direction"]),
                               atol=1e-12)
    lf = json.loads((d / "light_field.json").read_text())
    assert lf["frame"] == "glb"
    pts, dirs = np.asarray(lf["points"]), np.asarray(lf["directions"])
    centre_g = r @ (m[:3, :3] @ query.center.numpy() + m[:3, 3])
    assert np.abs(np.linalg.norm(pts - centre_g, axis=-1) - query.radius * 2.0).max() < 0.1
    to_light = (r @ light_w - pts) / np.linalg.norm(r @ light_w - pts, axis=-1, keepdims=True)
    assert np.min((dirs * to_light).sum(-1)) > 0.999


def test_frame_recorded_in_frame_json_and_the_manifest(exported):
    from nepf_core.export import write_manifest

    d = exported["dir"]
    rec = json.loads((d / "frame.json").read_text())
    man = write_manifest(d)
    assert man["frame"] == rec
    assert rec["world_up"] == "-y" and rec["up_source"] == "cameras" and rec["glb_up"] == "+y"
    assert rec["gltf_from_world"] == gltf_from_world("-y").astype(int).tolist()
    assert {a["path"]: a["kind"] for a in man["artifacts"]}["frame.json"] == "config"


# --------------------------------------------------------------------------- choosing the axis of a run
def test_export_frame_override_then_sticky_then_cameras(tmp_path):
    from nepf_core.jobs import export_frame

    extra = {"camera_up": [0.02, -0.9, 0.1]}
    assert export_frame(tmp_path, extra).to_json()["world_up"] == "-y"
    assert export_frame(tmp_path, {}).source == "default"     # a checkpoint from before issue 34
    fr = export_frame(tmp_path, extra, "+x")
    assert (fr.world_up, fr.source) == ("+x", "override")
    (tmp_path / "frame.json").write_text(json.dumps(fr.to_json()))
    assert export_frame(tmp_path, extra).world_up == "+x"      # nepf export again keeps nepf fit --up
    assert export_frame(tmp_path, extra, "auto").world_up == "-y"
    with pytest.raises(ValueError, match="up axis must be one of"):
        export_frame(tmp_path, extra, "sideways")


def test_cli_reads_up_values_that_start_with_a_dash(capsys):
    from nepf_core.cli import _join_up_values, build_parser

    ap = build_parser()
    assert ap.parse_args(_join_up_values(["export", "RUN", "--up", "-z"])).up == "-z"
    assert ap.parse_args(_join_up_values(["fit", "D", "--out", "R", "--up", "X"])).up == "+x"
    assert ap.parse_args(["export", "RUN"]).up is None
    with pytest.raises(SystemExit):
        ap.parse_args(["export", "RUN", "--up", "sideways"])
    assert "up axis must be one of auto" in capsys.readouterr().err


def test_fit_records_the_camera_up_and_the_export_turns_it_to_plus_y(tmp_path):
    """End to end on a generated scene whose world is +X up: the fit records the cameras' mean up
    in the checkpoint, the export finds +x from it; ``mesh.ply`` stays in the world frame and the
    GLB holds the same mesh rotated (``nepf eval`` / ``nepf relight`` work in the world frame)."""
    import trimesh

    from nepf_core.jobs import export_run, run_job

    q = rotation_taking(np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    rotate_dtu_world(synth_dir() / "dtu", tmp_path / "dtu", q)
    run = tmp_path / "run"
    s = run_job(tmp_path / "dtu", run, preset="tiny", iters=3, device="cpu", export=False, holdout_every=0,
                log=lambda *_: None)
    assert s["status"] == "succeeded"
    export_run(run, device="cpu", texture_size=64, max_faces=1000, mesh_resolution=32, previews=False,
               log=lambda *_: None)
    rec = json.loads((run / "frame.json").read_text())
    assert (rec["world_up"], rec["up_source"]) == ("+x", "cameras")
    assert json.loads((run / "manifest.json").read_text())["frame"] == rec
    r = gltf_from_world("+x")
    ply = np.asarray(trimesh.load(run / "mesh.ply", process=False).vertices)
    gltf = pygltflib.GLTF2().load_binary(str(run / "asset.glb"))
    acc = gltf.accessors[gltf.meshes[0].primitives[0].attributes.POSITION]
    np.testing.assert_allclose(acc.min, (ply @ r.T).min(0), atol=1e-4 * np.ptp(ply))
    np.testing.assert_allclose(acc.max, (ply @ r.T).max(0), atol=1e-4 * np.ptp(ply))
