"""Unit tests of the viewer's data handling, run in Node on the real source modules.

The inputs come from the Python side so that a schema change there shows up here:
``light_field.json`` / ``lights.json`` from ``nepf_core.export.light_field`` (analytic point
light), a ``JobPublic`` and a 422 ``ErrorBody`` from ``api.schemas``. Node is required (the
viewer cannot be built without it), so a missing ``node`` fails the test.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
SRC = REPO / "web" / "src"

SCRIPT = r"""
import { parseLightField, parseLights, colormap } from './viewer3d.js';
import { normJob, applyEvent } from './live.js';
import { validationErrors, errorSummary } from './api.js';
import { metricsToCsv, filenameFromDisposition } from './util.js';
const input = JSON.parse(await new Promise((res) => { let s = ''; process.stdin.on('data', (d) => s += d); process.stdin.on('end', () => res(s)); }));
const lf = parseLightField(input.light_field);
const lfRecords = parseLightField({ samples: input.light_field.points.map((p, i) => ({ position: p, direction: input.light_field.directions[i], intensity: input.light_field.intensity[i] })) });
const lp = parseLights(input.lights_point);
const ld = parseLights(input.lights_directional);
const job = normJob(input.job);
const after = applyEvent(job, { status: 'running', progress: { step: 7, total: 10, fraction: 0.7, stage: 'training', eta_s: 3 }, error: null, cancel_requested: true });
const out = {
  lf: { n: lf.positions.length, p0: lf.positions[0].toArray(), l0: lf.directions[0].toArray(), i0: lf.intensity[0], n0: lf.normals[0].toArray() },
  lfRecords: lfRecords.positions.length,
  lightsPoint: { position: lp.position.toArray(), intensity: lp.intensity, type: lp.type },
  lightsDir: { position: ld.position, direction: ld.direction.toArray(), atPoint: ld.atPoint, type: ld.type },
  job: { id: job.id, status: job.status, fraction: job.fraction, stage: job.stage, eta_s: job.eta_s, preset: job.preset, name: job.name, created: job.created, step: job.step, total: job.total, wall_s: job.wall_s, error: job.error },
  after: { status: after.status, fraction: after.fraction, step: after.step, stage: after.stage, cancel: after.raw.cancel_requested },
  errors: validationErrors(input.error_body), summary: errorSummary(input.error_body, 422),
  csv: metricsToCsv(input.records),
  cmap: [colormap(0), colormap(1)],
  names: input.dispositions.map(filenameFromDisposition),
};
process.stdout.write(JSON.stringify(out));
"""


def run_node(payload: dict) -> dict:
    node = shutil.which("node")
    assert node, "node is required to build and test the web viewer"
    assert (REPO / "web" / "node_modules" / "three").is_dir(), "run `cd web && npm ci` first"
    r = subprocess.run([node, "--input-type=module", "-e", SCRIPT], input=json.dumps(payload), cwd=SRC,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_viewer_parses_what_export_and_api_write(tmp_path):
    from nepf_core.export.light_field import fit_lights, write_light_field

    rng = np.random.default_rng(0)
    n = 64
    pts = rng.normal(size=(n, 3))
    pts /= np.linalg.norm(pts, axis=-1, keepdims=True)
    normals = pts.copy()
    light = np.array([1.5, 1.0, 2.0])
    d = light - pts
    dist = np.linalg.norm(d, axis=-1)
    dirs = d / dist[:, None]
    inten = 4.0 / dist ** 2
    field = {"points": pts, "normals": normals, "directions": dirs, "intensity": inten}
    write_light_field(tmp_path, field, fit_lights(pts, dirs, inten))
    lf = json.loads((tmp_path / "light_field.json").read_text())
    lights_point = json.loads((tmp_path / "lights.json").read_text())
    par = np.tile([0.0, 0.0, 1.0], (n, 1))  # parallel directions: a directional light
    lights_dir = fit_lights(pts, par, np.ones(n))
    assert lights_point["type"] == "point" and lights_dir["type"] == "directional"

    from api.schemas import ErrorBody, JobPublic

    job = JobPublic(id="a" * 32, name="scan", status="queued",
                    progress={"step": 3, "total": 10, "fraction": 0.25, "stage": "loading", "eta_s": None,
                              "wall_s": 1.5},
                    created_at="2026-01-02T03:04:05Z", config={"preset": "tiny"}, error="a message",
                    delivery={"attempts": 0}, links={}).model_dump(mode="json")
    err = ErrorBody(detail="dataset is invalid", code="invalid_dataset",
                    errors=[{"code": "corrupt_image", "message": "not a readable image",
                             "file": "scan/image/002.png", "view": 2}]).model_dump(mode="json")
    records = [{"step": 5, "wall_s": 1.0, "kind": "train", "loss": 0.5, "loss_r": 0.25},
               {"step": 50, "wall_s": 9.0, "kind": "sync", "psnr_r": 20.0, "note": "a, \"quoted\""}]

    from api.downloads import content_disposition
    dispositions = [content_disposition("Kürbis \"groß\" 50%; x", "a" * 32, "textures/orm.png"),
                    content_disposition(None, "b" * 32, "asset.glb"), 'attachment; filename="plain.txt"',
                    "attachment; filename=bare.bin", None]
    out = run_node({"light_field": lf, "lights_point": lights_point, "lights_directional": lights_dir,
                    "job": job, "error_body": err, "records": records, "dispositions": dispositions})
    # the viewer saves a download under the API's name (util.js filenameFromDisposition)
    assert out["names"] == ['Kürbis _groß_ 50%; x-textures-orm.png', "nepf-bbbbbbbb-asset.glb", "plain.txt",
                            "bare.bin", None]

    assert out["lf"]["n"] == n and out["lfRecords"] == n
    np.testing.assert_allclose(out["lf"]["p0"], pts[0], atol=1e-5)
    np.testing.assert_allclose(out["lf"]["l0"], dirs[0], atol=1e-5)
    np.testing.assert_allclose(out["lf"]["n0"], normals[0], atol=1e-5)
    assert abs(out["lf"]["i0"] - inten[0]) < 1e-5
    # the fitted point light is the analytic one (position and radiant intensity 4)
    np.testing.assert_allclose(out["lightsPoint"]["position"], light, atol=1e-4)
    assert abs(out["lightsPoint"]["intensity"] - 4.0) < 1e-3 and out["lightsPoint"]["type"] == "point"
    assert out["lightsDir"]["position"] is None and out["lightsDir"]["type"] == "directional"
    np.testing.assert_allclose(out["lightsDir"]["direction"], [0, 0, 1], atol=1e-6)
    assert out["lightsDir"]["atPoint"] == 1.0

    assert out["job"] == {"id": "a" * 32, "status": "queued", "fraction": 0.25, "stage": "loading",
                          "eta_s": None, "preset": "tiny", "name": "scan", "created": job["created_at"],
                          "step": 3, "total": 10, "wall_s": 1.5, "error": "a message"}
    assert out["after"] == {"status": "running", "fraction": 0.7, "step": 7, "stage": "training", "cancel": True}

    assert out["errors"] == [{"code": "corrupt_image", "message": "not a readable image",
                              "file": "scan/image/002.png", "view": 2}]
    assert out["summary"] == "dataset is invalid"

    lines = out["csv"].splitlines()
    assert lines[0] == "step,wall_s,kind,loss,loss_r,psnr_r,note"
    assert lines[1] == "5,1,train,0.5,0.25,,"
    assert lines[2] == '50,9,sync,,,20,"a, ""quoted"""'
    assert out["cmap"][0] != out["cmap"][1]


def _function_source(js: str, name: str) -> str:
    start = js.index(f"export function {name}(")
    return js[start:js.index("\n}\n", start)]


def test_job_normalisation_reads_only_fields_the_api_sends():
    """normJob / applyEvent read only fields of ``JobPublic`` (and its ``progress`` and
    ``config``): a name the API never sends is dead code, and a renamed API field shows up here."""
    import re

    from api.schemas import JobConfig, JobPublic, Progress

    live = (SRC / "live.js").read_text()
    norm = _function_source(live, "normJob")
    used = {"j": set(re.findall(r"\bj\.(\w+)", norm)), "p": set(re.findall(r"\bp\.(\w+)", norm)),
            "cfg": set(re.findall(r"\bcfg\.(\w+)", norm))}
    assert used["j"] and used["p"] and used["cfg"], used
    assert used["j"] <= set(JobPublic.model_fields), used["j"] - set(JobPublic.model_fields)
    assert used["p"] <= set(Progress.model_fields), used["p"] - set(Progress.model_fields)
    assert used["cfg"] <= set(JobConfig.model_fields), used["cfg"] - set(JobConfig.model_fields)
    event_keys = re.findall(r"'(\w+)'", re.search(r"for \(const k of \[([^\]]*)\]\)",
                                                   _function_source(live, "applyEvent")).group(1))
    assert event_keys and set(event_keys) <= set(JobPublic.model_fields), event_keys


FRAME_SCRIPT = r"""
import * as THREE from 'three';
import { frameRotation, upFromFrame } from './viewer3d.js';
const input = JSON.parse(await new Promise((res) => { let s = ''; process.stdin.on('data', (d) => s += d); process.stdin.on('end', () => res(s)); }));
const r = frameRotation(input.frame);
const p = new THREE.Vector3(...input.point).applyMatrix3(r);
process.stdout.write(JSON.stringify({ up: upFromFrame(input.frame), point: p.toArray(),
  none: frameRotation({}) === null && frameRotation({ gltf_from_world: [[1, 0], [0, 1]] }) === null,
  legacyUp: upFromFrame({}) }));
"""


def test_viewer_reads_the_manifest_frame_as_the_export_writes_it():
    """The manifest's ``frame`` (``UpFrame.to_json``) in the viewer: up +Y, and a world point
    through ``gltf_from_world`` as numpy maps it (three.js' Matrix3.set takes rows)."""
    from nepf_core.up_axis import UpFrame

    frame = UpFrame("+z", "cameras", (0.0, 0.1, 0.9)).to_json()
    node = shutil.which("node")
    assert node, "node is required to build and test the web viewer"
    point = [1.0, 2.0, 3.0]
    r = subprocess.run([node, "--input-type=module", "-e", FRAME_SCRIPT], input=json.dumps({"frame": frame, "point": point}),
                       cwd=SRC, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["up"] == "y" and out["none"] is True and out["legacyUp"] is None
    np.testing.assert_allclose(out["point"], np.asarray(frame["gltf_from_world"]) @ point)   # (1, 3, -2)


HELPERS_SCRIPT = r"""
import * as THREE from 'three';
import { anglesOf, directionOf } from './viewer/frame.js';
import { lightSliders } from './viewer/lighting.js';
import { glyphLength, glyphCountFor, intensityRange, shuffledIndices } from './viewer/glyphs.js';
import { bestViewDirection } from './viewer/framing.js';
import { dragDirection, GIZMO_RADIUS } from './viewer/gizmo.js';
import { environmentIntensity } from './viewer/environment.js';
import { patchTouches, initialState } from './viewer3d.js';
import { metaItems, statusNote } from './views/job.js';
import { groupArtifacts } from './views/job_results.js';
const V = (a) => new THREE.Vector3(...a);
const out = {};
// azimuth / elevation about each up axis, and back
out.roundTrip = ['y', 'z', '-y'].map((up) => {
  const d = directionOf(30, 40, up);
  const { az, el } = anglesOf(d, up);
  return [up, az, el, d.length()];
});
out.dirY = directionOf(0, 90, 'y').toArray();
out.dirZ = directionOf(90, 0, 'z').toArray();   // +Z up: azimuth 90 is the y-like axis
// a light 10 radii away on +x (asset radius 2 at the origin): onto the slider's range [1.2, 20]
const state = { lightAz: 45, lightEl: 35, lightDist: 3, baseLightIntensity: 28 };
out.far = lightSliders({ position: V([20, 0, 0]), intensity: 100 }, { center: V([0, 0, 0]), radius: 2, up: 'y', current: state });
out.beyond = lightSliders({ position: V([0, 50, 0]), intensity: 100 }, { center: V([0, 0, 0]), radius: 2, up: 'y', current: state });
out.directional = lightSliders({ direction: V([0, 0, 1]), atPoint: 2 }, { center: V([0, 0, 0]), radius: 2, up: 'y', current: state });
out.nothing = lightSliders({}, { center: V([0, 0, 0]), radius: 2, up: 'y', current: state });
out.glyph = [glyphLength(1, 4 * Math.PI / 0.01), glyphLength(1, 1), glyphLength(1, 1e6), glyphCountFor(100, 0.25), glyphCountFor(3, 0.01)];
out.range = [intensityRange([3, NaN, -1, 7]), intensityRange([NaN])];
const order = shuffledIndices(50);
out.shuffle = [order.length, new Set(order).size, JSON.stringify(order) === JSON.stringify(shuffledIndices(50))];
// a box 2 long in x, 0.6 high, 0.2 deep, up +y: seen from the side (a view direction nearly
// perpendicular to x: its silhouette 2 x 0.6 against 0.2 x 0.6 end-on)
const box = [];
for (const x of [-1, 1]) for (const y of [-0.3, 0.3]) for (const z of [-0.1, 0.1]) box.push(V([x, y, z]));
out.rodView = bestViewDirection(box, V([0, 1, 0]), V([0, 0, 1]), V([1, 0, 0])).toArray();
// a ray from z=10 down the -z axis through the centre: the handle's near side (+z) or far side (-z)
const ray = new THREE.Ray(V([0, 0, 10]), V([0, 0, -1]));
out.drag = [dragDirection(ray, V([0, 0, 0]), GIZMO_RADIUS, false).toArray(), dragDirection(ray, V([0, 0, 0]), GIZMO_RADIUS, true).toArray(),
  dragDirection(new THREE.Ray(V([5, 0, 10]), V([0, 0, -1])), V([0, 0, 0]), 1, false).toArray()];
out.env = [environmentIntensity('dim', 0.8), environmentIntensity('room', 0.8)];
out.touches = [patchTouches({ tint: '#fff' }), patchTouches({ density: 0.5, exposure: 2 })];
out.state = initialState();
out.meta = metaItems({ created: null, step: 5, total: 10, wall_s: null, raw: { dataset: { format: 'dtu', n_views: 16, width: 32, height: 32, working_width: 16, working_height: 16, held_out_views: 2 }, config: { holdout_every: 8 } } })
  .map(([k, v, id]) => [k, v, id ?? null]);
out.notes = [statusNote('cancelled') !== null, statusNote('queued'), statusNote('running')];
out.groups = groupArtifacts([{ path: 'asset.glb', kind: 'glb' }, { path: 'previews/thumb.png', kind: 'preview' },
  { path: 'textures/albedo.png', kind: 'texture' }, { path: 'mesh.ply', kind: 'mesh' }]).map(([g, a]) => [g, a.map((x) => x.path)]);
process.stdout.write(JSON.stringify(out));
"""


def test_viewer_and_job_page_helpers():
    """The pure helpers the 3D view and the job page are built from, on hand-worked values."""
    node = shutil.which("node")
    assert node, "node is required to build and test the web viewer"
    assert (REPO / "web" / "node_modules" / "three").is_dir(), "run `cd web && npm ci` first"
    r = subprocess.run([node, "--input-type=module", "-e", HELPERS_SCRIPT], cwd=SRC, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    for up, az, el, norm in out["roundTrip"]:
        assert abs(az - 30) < 1e-9 and abs(el - 40) < 1e-9 and abs(norm - 1) < 1e-12, up
    np.testing.assert_allclose(out["dirY"], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(out["dirZ"], [0, 1, 0], atol=1e-12)   # UP_AXES.z: ax = +x, ay = +y
    # 20 / 2 = 10 radii: inside [1.2, 20], kept as it is, azimuth of +x about +y (ax = +z, ay = +x) is 90
    far = out["far"]
    assert far["lightDist"] == 10 and far["baseLightIntensity"] == 100 and far["lightIntensity"] == 1
    assert abs(far["lightAz"] - 90) < 1e-9 and abs(far["lightEl"]) < 1e-9
    # 50 / 2 = 25 radii: moved onto 20 radii, the intensity scaled by (20/25)^2 = 0.64: same irradiance
    beyond = out["beyond"]
    assert beyond["lightDist"] == 20 and abs(beyond["baseLightIntensity"] - 64) < 1e-9 and abs(beyond["lightEl"] - 90) < 1e-9
    # a directional fit: I = atPoint * d^2 at the slider's distance, 2 * (3 * 2)^2 = 72; azimuth of +z is 0
    d = out["directional"]
    assert d["lightDist"] == 3 and abs(d["baseLightIntensity"] - 72) < 1e-9 and abs(d["lightAz"]) < 1e-9
    assert out["nothing"] == {"lightAz": 45, "lightEl": 35, "lightDist": 3, "baseLightIntensity": 28, "lightIntensity": 1}
    # spacing sqrt(4 pi / n): n = 4 pi / 0.01 gives 0.1, x 0.8 = 0.08; one glyph: capped at 0.15; 1e6: floor 0.025
    g = out["glyph"]
    assert abs(g[0] - 0.08) < 1e-12 and g[1] == 0.15 and g[2] == 0.025 and g[3] == 25 and g[4] == 1
    assert out["range"] == [[-1, 7], [0, 1]]
    assert out["shuffle"] == [50, 50, True]
    # the 12 azimuths (30 degrees apart from 0.6 rad, 20 degrees up) give bounding-box areas from
    # 0.44 (end-on, dir = (+-0.937, 0.342, -+0.072)) to 1.775 (dir = (0.531, 0.342, 0.776), the first of the largest)
    np.testing.assert_allclose(out["rodView"], [0.5306, 0.3420, 0.7756], atol=1e-4)
    np.testing.assert_allclose(out["drag"][0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(out["drag"][1], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(out["drag"][2], [1, 0, 0], atol=1e-12)   # a miss: the closest point, on the sphere
    assert out["env"] == [0.2, 0.8]
    assert out["touches"][0] == {"materials": True, "env": False, "light": False, "lightField": False}
    assert out["touches"][1] == {"materials": False, "env": True, "light": False, "lightField": True}
    assert out["state"]["up"] == "y" and out["state"]["channel"] == "pbr" and out["state"]["density"] == 0.25
    assert ["Trains at", "16×16 px", "meta-working-size"] in out["meta"]
    assert ["Held-out views", "2 (views 0, 8, 16, …), scored during training", "meta-held-out"] in out["meta"]
    assert ["Step", "5 / 10", None] in out["meta"] and ["Dataset", "dtu, 16 views, 32×32", None] in out["meta"]
    assert out["notes"] == [True, "Waiting for a worker.", None]
    assert out["groups"] == [["Asset (GLB)", ["asset.glb"]], ["Material maps", ["textures/albedo.png"]],
                             ["Metrics", []], ["Mesh", ["mesh.ply"]], ["Previews", ["previews/thumb.png"]]]
