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
