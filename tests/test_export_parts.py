"""Unit tests of the export pieces: empty SDF, floaters, decimation budget, rasteriser,
push-pull padding, sRGB, world transform, light fit, preview failure isolation."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # export_fixtures, any pytest import mode
from export_fixtures import SphereQuery, similarity
from nepf_core.export import EmptyMeshError, export_asset
from nepf_core.export.light_field import fit_lights
from nepf_core.export.manifest import artifact_kind
from nepf_core.export.mesh import decimate_mesh, extract_mesh, mesh_to_world
from nepf_core.export.previews import render_previews
from nepf_core.color import linear_to_srgb, srgb_to_linear
from nepf_core.export.uv_bake import fill_push_pull, rasterize_uv


def test_empty_sdf_raises_clear_error(tmp_path):
    with pytest.raises(EmptyMeshError, match="no zero crossing.*everything is outside"):
        export_asset(SphereQuery(empty=True), np.eye(4), tmp_path, mesh_resolution=32,
                     previews=False)
    inside = SphereQuery(radius=5.0)  # the whole box is inside the object
    with pytest.raises(EmptyMeshError, match="everything is inside"):
        extract_mesh(inside.sdf, 16)
    nan_sdf = lambda x: torch.full(x.shape[:1], float("nan"))  # noqa: E731  (diverged fit)
    with pytest.raises(EmptyMeshError):
        extract_mesh(nan_sdf, 16)
    assert not any(tmp_path.iterdir())  # nothing half-written


def test_floaters_dropped_and_budget_respected():
    big, small = SphereQuery(radius=0.5, center=(-0.2, 0, 0)), SphereQuery(radius=0.08, center=(0.7, 0.6, 0))

    def two(x):
        return torch.minimum(big.sdf(x), small.sdf(x))

    kept_all = extract_mesh(two, 64, min_component_ratio=0.0)
    cleaned = extract_mesh(two, 64)  # default: drop components < 5% of the largest
    assert len(cleaned.faces) < len(kept_all.faces)
    d = np.linalg.norm(cleaned.vertices - np.array([-0.2, 0, 0]), axis=-1)
    assert np.abs(d - 0.5).max() < 0.03  # only the big sphere is left
    dec = decimate_mesh(cleaned, 1000)
    assert len(dec.faces) <= 1000 and dec.volume > 0


def test_rasterize_uv_covers_triangle_area():
    # right triangle covering the lower-left half of the unit square (texel centres)
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], np.float32)
    faces = np.array([[0, 1, 2]])
    tri, bary = rasterize_uv(uv, faces, 64, 64, margin_px=0.0)
    cov = tri >= 0
    # texel (r, c) has centre ((c+.5)/64, (r+.5)/64): inside iff c + r + 1 <= 64 -> 64*65/2 texels
    assert cov.sum() == 64 * 65 // 2
    np.testing.assert_allclose(bary[cov].sum(-1), 1.0, atol=1e-6)
    # barycentric b1 is u: at texel (r=0, c=10) u = 10.5/64
    assert bary[0, 10, 1] == pytest.approx(10.5 / 64, abs=1e-6)
    # the conservative margin adds the border texels, clamped onto the triangle
    tri_m, bary_m = rasterize_uv(uv, faces, 64, 64, margin_px=0.75)
    assert (tri_m >= 0).sum() > cov.sum() and np.all(bary_m[tri_m >= 0] >= 0)


def test_push_pull_fills_holes_and_keeps_valid():
    img = np.zeros((32, 32, 1), np.float32)
    mask = np.zeros((32, 32), bool)
    mask[8:16, 8:16] = True
    img[mask] = 0.7
    out = fill_push_pull(img, mask)
    np.testing.assert_allclose(out[mask], 0.7)
    np.testing.assert_allclose(out, 0.7, atol=1e-5)  # a constant chart pads with its colour


def test_srgb_round_trip():
    x = np.linspace(0, 1, 101)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-9)
    assert linear_to_srgb(np.array(0.5)) == pytest.approx(0.7354, abs=1e-4)


def test_mesh_to_world_rotates_normals_without_scaling():
    m = similarity(scale=2.5)
    v = np.array([[0.0, 0.0, 1.0]])
    n = np.array([[0.0, 0.0, 1.0]])
    vw, nw = mesh_to_world(v, m, n)
    np.testing.assert_allclose(vw[0], m[:3, 2] + m[:3, 3])
    np.testing.assert_allclose(np.linalg.norm(nw), 1.0, atol=1e-6)
    np.testing.assert_allclose(nw[0], m[:3, 2] / 2.5, atol=1e-6)


def test_fit_lights_point_and_directional():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(500, 3))
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    p = np.array([3.0, -2.0, 4.0])
    lvec = p - x
    d2 = (lvec ** 2).sum(-1)
    l = lvec / np.sqrt(d2)[:, None]
    fit = fit_lights(x, l, 10.0 / d2)
    assert fit["type"] == "point"
    np.testing.assert_allclose(fit["point_light"]["position"], p, atol=1e-6)
    assert fit["point_light"]["intensity"] == pytest.approx(10.0, rel=1e-6)
    # parallel directions: a directional (sun) light, no point estimate
    sun = np.tile([0.0, 0.0, 1.0], (500, 1))
    fit = fit_lights(x, sun, np.ones(500))
    assert fit["type"] == "directional" and fit["point_light"] is None
    np.testing.assert_allclose(fit["dominant_direction"], [0, 0, 1], atol=1e-9)
    assert fit["direction_concentration"] == pytest.approx(1.0)


def test_learned_emitters_written_as_they_are_in_both_frames():
    """emitters_to_world by hand (scale 2, translation t: p -> 2 p + t, I -> 4 I, brightest first)
    and lights_to_frame moving their positions into the GLB's frame (x, y, z) -> (x, z, -y)."""
    from nepf_core.export.light_field import emitters_to_world, lights_to_frame
    from nepf_core.up_axis import gltf_from_world
    m = np.diag([2.0, 2.0, 2.0, 1.0])
    m[:3, 3] = [1.0, -1.0, 0.5]
    world = emitters_to_world(torch.tensor([[0.0, 0.0, 3.0], [1.0, 0.0, 0.0]]), torch.tensor([5.0, 7.0]), m)
    assert [e["intensity"] for e in world] == pytest.approx([28.0, 20.0])
    np.testing.assert_allclose([e["position"] for e in world], [[3.0, -1.0, 0.5], [1.0, -1.0, 6.5]])
    summary = {"dominant_direction": [0.0, 0.0, 1.0], "object_center": [0.0, 0.0, 0.0], "point_light": None,
               "emitters": world}
    glb = lights_to_frame(summary, gltf_from_world("+z"))
    np.testing.assert_allclose([e["position"] for e in glb["emitters"]], [[3.0, 0.5, 1.0], [1.0, 6.5, 1.0]])
    assert [e["intensity"] for e in glb["emitters"]] == pytest.approx([28.0, 20.0])
    assert summary["emitters"][0]["position"] == [3.0, -1.0, 0.5]  # the world copy is not moved


class _EmitterSphereQuery(SphereQuery):
    """The analytic sphere lit by its point light, reported as one learned emitter."""

    def emitters(self):
        return self.light_pos[None].clone(), torch.tensor([self.light_intensity])


def test_lights_json_lists_the_learned_emitters_beside_the_fitted_light(tmp_path):
    import json

    import trimesh

    from nepf_core.export import _write_lights
    from nepf_core.up_axis import gltf_from_world
    q, m, rot = _EmitterSphereQuery(), similarity(scale=2.5), gltf_from_world("+z")
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=q.radius)
    mesh.apply_translation(q.center.numpy())
    _write_lights(q, mesh, m, tmp_path, rot, light_samples=500, chunk=4096, device="cpu")
    lights = json.loads((tmp_path / "lights.json").read_text())
    light_w = m[:3, :3] @ q.light_pos.numpy() + m[:3, 3]
    (emitter,) = lights["world"]["emitters"]
    np.testing.assert_allclose(emitter["position"], light_w, atol=1e-5)
    assert emitter["intensity"] == pytest.approx(q.light_intensity * 2.5 ** 2, rel=1e-6)
    np.testing.assert_allclose(lights["emitters"][0]["position"], rot @ light_w, atol=1e-5)
    # the fit from the light field finds the same light
    np.testing.assert_allclose(lights["world"]["point_light"]["position"], light_w, atol=1e-2 * 2.5)


def test_model_query_reports_emitters_only_with_the_emitter_light():
    from nepf_core.model import ModelConfig, ModelFieldQuery, NePFModel
    model = NePFModel(ModelConfig(sdf_kind="grid", light="emitters", emitters=2))
    with torch.no_grad():
        model.photon.positions.copy_(torch.tensor([[0.0, 0.0, 4.0], [3.0, 0.0, 0.0]]))
        model.photon.log_intensity.copy_(torch.log(torch.tensor([9.0, 0.5])))
    positions, intensity = ModelFieldQuery(model).emitters()
    np.testing.assert_allclose(positions.numpy(), [[0.0, 0.0, 4.0], [3.0, 0.0, 0.0]])
    np.testing.assert_allclose(intensity.numpy(), [9.0, 0.5], rtol=1e-6)
    assert ModelFieldQuery(NePFModel(ModelConfig(sdf_kind="grid"))).emitters() is None


CRASHING_RENDERER = """
import os, signal, sys
print("about to crash", file=sys.stderr, flush=True)
os.kill(os.getpid(), signal.SIGSEGV)   # what a VTK / GL driver crash looks like to the parent
"""


def test_preview_failure_is_logged_not_raised(tmp_path):
    from PIL import Image

    from nepf_core.export.previews import BACKENDS

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    args = (v, np.array([[0, 1, 2]]), v[:, :2], np.tile([0, 0, 1.0], (3, 1)))
    logs = []
    out = render_previews(*args, tmp_path / "missing_texture.png", tmp_path, frames=1, size=32,
                          log=logs.append)
    assert out == [] and "previews failed" in logs[0] and "texture not found" in logs[0]
    # a native crash (SIGSEGV) of the renderer child on every backend: logged, caller survives
    tex = tmp_path / "t.png"
    Image.new("RGB", (4, 4)).save(tex)
    crash = tmp_path / "crashing_renderer.py"
    crash.write_text(CRASHING_RENDERER)
    logs = []
    out = render_previews(*args, tex, tmp_path, frames=1, size=32, log=logs.append, renderer_script=crash)
    assert out == [] and len(logs) == 1
    assert logs[0].count("killed by signal 11") >= len(BACKENDS) and "about to crash" in logs[0]


def test_manifest_kinds():
    assert artifact_kind("asset.glb") == "glb"
    assert artifact_kind("textures/orm.png") == "texture"
    assert artifact_kind("previews/turntable_00.png") == "preview"
    assert artifact_kind("checkpoints/latest.pt") is None
    assert artifact_kind("manifest.json") is None
    assert artifact_kind("asset.glb.tmp") is None
    assert artifact_kind("summary.json") == "report" and artifact_kind("eval.json") == "metrics"
    assert artifact_kind("progress.json") is None and artifact_kind("notes/readme.txt") is None


def test_autograd_normals_work_under_no_grad():
    from nepf_core.export.mesh import vertex_normals_from_field

    q = SphereQuery()

    def autograd_normal(x):  # how a network computes normals: the SDF's gradient
        x = x.detach().requires_grad_(True)
        (g,) = torch.autograd.grad(q.sdf(x).sum(), x)
        return torch.nn.functional.normalize(g, dim=-1)

    v = np.array([[0.65, -0.02, 0.03], [0.05, -0.02, -0.55]], np.float32)
    with torch.no_grad():  # e.g. a caller that wraps the whole export
        n = vertex_normals_from_field(autograd_normal, v)
    np.testing.assert_allclose(n, [[1, 0, 0], [0, 0, -1]], atol=1e-5)


def test_narrow_band_grid_matches_dense_near_surface():
    from nepf_core.export.mesh import sdf_grid_from_field

    q = SphereQuery()
    calls = []

    def counted(x):
        calls.append(len(x))
        return q.sdf(x)

    dense = sdf_grid_from_field(counted, 96, narrow_band=False)
    n_dense = sum(calls)
    calls.clear()
    band = sdf_grid_from_field(counted, 96)
    assert sum(calls) < 0.6 * n_dense  # 96³ dense vs centres + near-surface blocks
    h = 2.0 / 95
    near = np.abs(dense) < 3 * h
    np.testing.assert_array_equal(band[near], dense[near])  # exact where marching cubes looks
    assert np.array_equal(np.sign(band), np.sign(dense))  # filled blocks keep the sign


def test_export_to_a_relative_run_folder(tmp_path, monkeypatch):
    """`nepf export runs/x` (a path relative to the working directory) used to join the written
    paths to the run folder a second time when building the manifest entries."""
    monkeypatch.chdir(tmp_path)
    rel = Path("runs") / "x"
    rel.mkdir(parents=True)
    entries = export_asset(SphereQuery(), np.eye(4), rel, texture_size=64, max_faces=800, mesh_resolution=24,
                           previews=False)
    paths = {e["path"] for e in entries}
    assert {"mesh.ply", "asset.glb", "textures/base_color.png"} <= paths
    assert all(not p.startswith("runs/") for p in paths)
    assert (tmp_path / "runs" / "x" / "manifest.json").is_file()
