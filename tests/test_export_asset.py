"""End-to-end export of an analytic sphere (tests/export_fixtures.py) into a run folder.

One export (module fixture) with a non-identity world_from_norm (scale 2.5, rotation 30
degrees, translation (3, -1, 0.5)) and a +Z-up world (the GLB, lights.json and light_field.json
are rotated into glTF's +Y-up frame, ``R = gltf_from_world("+z")``); every test reads its
artifacts. tests/test_gltf_frame.py checks the frame itself with another up axis.
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import subprocess
import sys
from pathlib import Path, PurePosixPath

import numpy as np
import pygltflib
import pytest
import trimesh
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))  # export_fixtures, any pytest import mode
from export_fixtures import METALLIC, ROUGHNESS, SphereQuery, albedo_numpy, similarity
from nepf_core.export import export_asset, write_manifest
from nepf_core.export.manifest import ARTIFACT_KINDS
from nepf_core.export.previews import BACKGROUND
from nepf_core.color import srgb_to_linear
from nepf_core.up_axis import UpFrame, gltf_from_world

REPO = Path(__file__).resolve().parents[1]
VALIDATOR_DIR = REPO / "tools" / "gltf-validator"
SCALE = 2.5
TEX = 256
RES = 96  # marching-cubes grid; voxel h = 2/95 ~ 0.021 (normalised)
R_GLB = gltf_from_world("+z")  # x_glb = R x_world: (x, y, z) -> (x, z, -y)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    q = SphereQuery()
    m = similarity(scale=SCALE)
    out = tmp_path_factory.mktemp("run")
    logs: list[str] = []
    entries = export_asset(q, m, out, texture_size=TEX, max_faces=6000, mesh_resolution=RES,
                           light_samples=3000, preview_frames=4, preview_size=128, log=logs.append,
                           frame=UpFrame("+z", "cameras"))
    return {"q": q, "m": m, "dir": out, "entries": entries, "logs": logs}


def _world_to_norm(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    return (np.asarray(x, np.float64) - m[:3, 3]) @ np.linalg.inv(m[:3, :3]).T


def _accessor(gltf: pygltflib.GLTF2, blob: bytes, idx: int) -> np.ndarray:
    acc = gltf.accessors[idx]
    view = gltf.bufferViews[acc.bufferView]
    dtype = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}[acc.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    arr = np.frombuffer(blob, dtype=dtype, count=acc.count * width, offset=start)
    return arr.reshape(acc.count, width) if width > 1 else arr


def _image(gltf: pygltflib.GLTF2, blob: bytes, tex_index: int) -> np.ndarray:
    img = gltf.images[gltf.textures[tex_index].source]
    view = gltf.bufferViews[img.bufferView]
    data = blob[view.byteOffset:view.byteOffset + view.byteLength]
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def test_glb_passes_khronos_validator(run):
    script = VALIDATOR_DIR / "validate.mjs"
    node = shutil.which("node")
    assert node, "node is not installed: the glTF validator needs Node.js (>= 18)"
    assert (VALIDATOR_DIR / "node_modules" / "gltf-validator").is_dir(), (
        "npm package gltf-validator is not installed: run `npm ci` in tools/gltf-validator "
        "(.ci/run does this for every folder in .ci/npm-dirs.txt)")
    proc = subprocess.run([node, str(script), str(run["dir"] / "asset.glb")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode in (0, 1), f"validator did not run: {proc.stderr}"
    report = json.loads(proc.stdout)
    msgs = [f"{m['code']}: {m['message']} ({m.get('pointer')})" for m in report["issues"]["messages"]
            if m["severity"] == 0]
    assert report["issues"]["numErrors"] == 0, msgs
    assert report["issues"]["numWarnings"] == 0, report["issues"]["messages"]
    assert report["info"]["hasTextures"] and report["info"]["materialCount"] == 1


def test_glb_round_trip_geometry_uv_and_textures(run):
    path = run["dir"] / "asset.glb"
    gltf = pygltflib.GLTF2().load_binary(str(path))
    blob = gltf.binary_blob()
    prim = gltf.meshes[0].primitives[0]
    pos = _accessor(gltf, blob, prim.attributes.POSITION).astype(np.float64)
    nrm = _accessor(gltf, blob, prim.attributes.NORMAL).astype(np.float64)
    uv = _accessor(gltf, blob, prim.attributes.TEXCOORD_0).astype(np.float64)
    idx = _accessor(gltf, blob, prim.indices)
    assert len(pos) == len(nrm) == len(uv) > 100
    assert idx.max() < len(pos) and len(idx) % 3 == 0 and len(idx) // 3 <= 6000
    assert np.all((uv >= 0) & (uv <= 1))
    assert gltf.asset.extras["nepf"]["up"] == [0.0, 1.0, 0.0]  # glTF's up; the world's was +z
    assert gltf.asset.extras["nepf"]["world_up"] == "+z"
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=-1), 1.0, atol=1e-5)

    # trimesh reads the same vertex count
    scene = trimesh.load(path, process=False)
    geom = list(scene.geometry.values())[0] if isinstance(scene, trimesh.Scene) else scene
    assert len(geom.vertices) == len(pos)

    pbr = gltf.materials[prim.material].pbrMetallicRoughness
    base = _image(gltf, blob, pbr.baseColorTexture.index)
    orm = _image(gltf, blob, pbr.metallicRoughnessTexture.index)
    assert base.shape == orm.shape == (TEX, TEX, 3)
    # sample at the vertices' UVs: texel (row, col) = floor(v * H), floor(u * W) (top-left origin)
    col = np.clip((uv[:, 0] * TEX).astype(int), 0, TEX - 1)
    row = np.clip((uv[:, 1] * TEX).astype(int), 0, TEX - 1)
    rough = orm[row, col, 1] / 255.0
    metal = orm[row, col, 2] / 255.0
    np.testing.assert_allclose(rough, ROUGHNESS, atol=1.0 / 255 + 1e-6)  # G = roughness
    np.testing.assert_allclose(metal, METALLIC, atol=1.0 / 255 + 1e-6)  # B = metallic
    assert np.all(orm[..., 0] == 255)  # R = occlusion, not computed
    # baseColor is sRGB-encoded: decode and compare with the known linear albedo at the vertex
    albedo = srgb_to_linear(base[row, col] / 255.0)
    q = run["q"]
    expected = albedo_numpy(_world_to_norm(run["m"], pos @ R_GLB), q.center.numpy(), q.radius)   # R^T x_glb
    err = np.abs(albedo - expected)
    # one texel spans ~ 1/(TEX * sqrt(util)) of the chart; albedo slope is 0.4/r per unit
    assert err.mean() < 0.01, err.mean()
    assert np.percentile(err, 99) < 0.04, np.percentile(err, 99)


def test_mesh_in_world_coordinates(run):
    q, m = run["q"], run["m"]
    centre_w = m[:3, :3] @ q.center.numpy() + m[:3, 3]
    radius_w = q.radius * SCALE
    mesh = trimesh.load(run["dir"] / "mesh.ply", process=False)
    d = np.linalg.norm(mesh.vertices - centre_w, axis=-1)
    h_w = 2.0 / (RES - 1) * SCALE  # voxel size in world units
    assert abs(d.mean() - radius_w) < 0.05 * h_w + 1e-3 * radius_w, (d.mean(), radius_w)
    assert np.abs(d - radius_w).max() < 0.5 * h_w
    # normals are rotated (unit, outward), not scaled
    n = np.asarray(mesh.vertex_normals)
    radial = (mesh.vertices - centre_w) / d[:, None]
    assert np.min((n * radial).sum(-1)) > 0.99
    assert mesh.volume > 0  # outward winding
    # the GLB holds the same geometry, rotated into glTF's +Y-up frame (world units and origin)
    gltf = pygltflib.GLTF2().load_binary(str(run["dir"] / "asset.glb"))
    pos = _accessor(gltf, gltf.binary_blob(), gltf.meshes[0].primitives[0].attributes.POSITION)
    dg = np.linalg.norm(pos - R_GLB @ centre_w, axis=-1)
    assert abs(dg.mean() - radius_w) < 0.05 * h_w + 1e-3 * radius_w


def test_light_field_and_fitted_point_light(run):
    q, m = run["q"], run["m"]
    lf = json.loads((run["dir"] / "light_field.json").read_text())
    glb_lights = json.loads((run["dir"] / "lights.json").read_text())
    assert glb_lights["frame"] == "glb"
    lights = glb_lights["world"]   # the world-frame summary; the top level is the same rotated
    assert lights["frame"] == "world"
    np.testing.assert_allclose(glb_lights["point_light"]["position"], R_GLB @ np.array(lights["point_light"]["position"]),
                               atol=1e-12)
    assert (run["dir"] / "light_field.json").stat().st_size < 2 * 2**20
    pts = np.array(lf["points"]) @ R_GLB   # R^T x_glb: back to the world
    dirs = np.array(lf["directions"]) @ R_GLB
    nrm = np.array(lf["normals"]) @ R_GLB
    inten = np.array(lf["intensity"])
    assert lf["frame"] == "glb" and lf["count"] == len(pts) == len(dirs) == len(nrm) == len(inten)
    assert len(pts) >= 2000
    for a in (pts, dirs, nrm, inten):
        assert np.all(np.isfinite(a))
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=-1), 1.0, atol=1e-5)
    assert np.all(inten >= 0)

    light_w = m[:3, :3] @ q.light_pos.numpy() + m[:3, 3]
    assert lights["type"] == "point"
    p = np.array(lights["point_light"]["position"])
    assert np.linalg.norm(p - light_w) < 1e-2 * SCALE, (p, light_w)
    # inverse-square intensity in world units: I0 * scale^2
    assert lights["point_light"]["intensity"] == pytest.approx(q.light_intensity * SCALE**2, rel=1e-2)
    dom = np.array(lights["dominant_direction"])
    assert np.linalg.norm(dom) == pytest.approx(1.0, abs=1e-6)
    centre_w = m[:3, :3] @ q.center.numpy() + m[:3, 3]
    to_light = (light_w - centre_w) / np.linalg.norm(light_w - centre_w)
    assert dom @ to_light > 0.95
    assert lights["point_light"]["residual_relative"] < 1e-3
    assert lights["confidence"] > 0.9  # exact lines through one point, well spread


def _content_fraction(img: np.ndarray) -> float:
    return float(np.mean(np.abs(img[..., :3].astype(int) - np.array(BACKGROUND)).max(-1) > 8))


def test_previews_rendered_with_content(run):
    prev = run["dir"] / "previews"
    frames = sorted(prev.glob("turntable_*.png"))
    assert len(frames) == 4, (list(prev.iterdir()) if prev.exists() else "no previews/", run["logs"])
    imgs = [np.asarray(Image.open(f).convert("RGB")) for f in frames]
    for img in imgs:
        assert img.shape == (128, 128, 3)
        assert 0.05 < _content_fraction(img) < 0.90
        assert img.std() > 5  # not blank
    # textured turntable: opposite views of the spatially varying albedo differ
    assert np.abs(imgs[0].astype(int) - imgs[2].astype(int)).mean() > 2
    relit = np.asarray(Image.open(prev / "relit.png").convert("RGB"))
    assert 0.05 < _content_fraction(relit) < 0.90
    assert np.abs(relit.astype(int) - imgs[0].astype(int)).mean() > 1  # other lighting
    thumb = Image.open(prev / "thumb.png")
    assert thumb.format == "PNG" and max(thumb.size) <= 128


def test_manifest_lists_every_artifact_with_hashes(run, tmp_path):
    d = run["dir"]
    manifest = json.loads((d / "manifest.json").read_text())
    listed = {e["path"]: e for e in manifest["artifacts"]}
    on_disk = {p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file()} - {"manifest.json"}
    assert set(listed) == on_disk
    for e in manifest["artifacts"]:
        assert not PurePosixPath(e["path"]).is_absolute() and ".." not in e["path"]
        f = d / e["path"]
        assert e["bytes"] == f.stat().st_size
        assert e["sha256"] == hashlib.sha256(f.read_bytes()).hexdigest()
        assert e["kind"] in ARTIFACT_KINDS
    kinds = {e["kind"] for e in manifest["artifacts"]}
    assert {"glb", "mesh", "texture", "light_field", "lights", "preview"} <= kinds
    # export_asset's own return value matches the manifest rows
    for e in run["entries"]:
        assert listed[e["path"]] == e

    # a full run folder: fit outputs are listed, checkpoints and progress are not
    full = tmp_path / "run"
    shutil.copytree(d, full)
    (full / "checkpoints").mkdir()
    (full / "checkpoints" / "latest.pt").write_bytes(b"x" * 10)
    for name, text in (("config.json", "{}"), ("metrics.jsonl", "{}\n"), ("report.json", "{}"),
                       ("progress.json", "{}")):
        (full / name).write_text(text)
    Image.new("RGB", (4, 4)).save(full / "error_vs_time.png")
    kinds = {e["path"]: e["kind"] for e in write_manifest(full)["artifacts"]}
    assert kinds["config.json"] == "config" and kinds["metrics.jsonl"] == "metrics"
    assert kinds["report.json"] == "report" and kinds["error_vs_time.png"] == "plot"
    assert "progress.json" not in kinds and not any(k.startswith("checkpoints/") for k in kinds)
    assert json.loads((full / "manifest.json").read_text())["artifacts"][0]["path"] in kinds
