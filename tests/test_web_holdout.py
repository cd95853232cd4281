"""The job options in the viewer (issue 26): the upload form's checks (in Node, on the real
module), and in the browser an upload through the form with held-out views, whose job fills
the "Error against wall-clock time" chart while it trains and whose page shows the size it
trains at and how many views are held out.

The service is the real one (``nepf serve``, embedded); the training is a stand-in
(``web_fixtures.pipeline_held_out_standin`` through ``NEPF_PIPELINE``) that writes a
``kind: "test"`` record on a schedule only when the job's ``holdout_every`` reached it.
"""

from __future__ import annotations

import json
import shutil
import subprocess

import pytest

from test_web_viewer import (assert_labelled, browser, chart_state, list_jobs, new_page,  # noqa: F401 - fixtures
                             shots)
from web_fixtures import (STANDIN_EVAL_EVERY, STANDIN_HOLD_ENV, STANDIN_HOLD_STEP, STANDIN_STEPS, WEB, Backend,
                          ensure_web_built, make_sphere_dtu, release_standin, standin_holding, wait_for)

NODE_SCRIPT = r"""
import { jobOptions, limitsFromSchema } from './views/upload.js';
const input = JSON.parse(await new Promise((res) => { let s = ''; process.stdin.on('data', (d) => s += d); process.stdin.on('end', () => res(s)); }));
const out = input.schemas.map((schema) => input.cases.map((c) => jobOptions(c, limitsFromSchema(schema))));
process.stdout.write(JSON.stringify({ out, limits: limitsFromSchema(input.schemas[1]) }));
"""


def form_checks(cases: list, schemas: list) -> dict:
    """``jobOptions`` of the real upload module in Node, for each case under each schema."""
    node = shutil.which("node")
    assert node, "node is required to build and test the web viewer"
    r = subprocess.run([node, "--input-type=module", "-e", NODE_SCRIPT],
                       input=json.dumps({"cases": cases, "schemas": schemas}),
                       cwd=WEB / "src", capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_upload_form_checks_the_job_options():
    """The form's limits come from the API's JobConfig schema (GET /schemas/job-config), here
    made by the same function from the model: without a ceiling on max_image_side, and with one."""
    from api.job_config import job_config_schema
    from jobstore.settings import Settings

    cases = [
        {"holdoutEvery": "8", "maxImageSide": "400", "textureSize": "2048", "maxFaces": "1000", "upAxis": "-Y"},
        {},
        {"holdoutEvery": "0", "maxFaces": " 2000000 ", "upAxis": "auto"},
        {"holdoutEvery": "1", "maxImageSide": "4", "textureSize": "300", "maxFaces": "999", "upAxis": "up"},
        {"holdoutEvery": "2.5", "maxFaces": "2000001"},
        {"maxImageSide": "1601"},
    ]
    got = form_checks(cases, [job_config_schema(Settings(max_image_side=0)),
                              job_config_schema(Settings(max_image_side=1600))])
    out, capped = got["out"]
    assert got["limits"] == {"presets": ["fast", "paper", "tiny"], "defaultPreset": "fast", "maxNameLength": 200,
                             "maxBudgetS": 2592000, "minImageSide": 8, "maxImageSide": 1600,
                             "textureSizes": [256, 512, 1024, 2048], "maxFacesRange": [1000, 2000000],
                             "upAxes": ["auto", "+x", "-x", "+y", "-y", "+z", "-z"]}
    assert out[0] == {"options": {"holdout_every": 8, "max_image_side": 400, "texture_size": 2048, "max_faces": 1000,
                                  "up_axis": "-y"}, "problems": []}
    assert out[1] == {"options": {}, "problems": []}
    assert out[2] == {"options": {"holdout_every": 0, "max_faces": 2_000_000}, "problems": []}
    assert out[3]["options"] == {}
    assert [(p["file"], p["message"]) for p in out[3]["problems"]] == [
        ("Held-out views", "must be 0 (train on all views) or an integer ≥ 2 (got 1)"),
        ("Working resolution", "must be an integer ≥ 8 pixels (got 4)"),
        ("Texture size", "must be one of 256, 512, 1024, 2048 (got 300)"),
        ("Mesh faces", "must be an integer from 1000 to 2000000 (got 999)"),
        ("Up axis", "must be one of auto, +x, -x, +y, -y, +z, -z (got up)")]
    assert [p["file"] for p in out[4]["problems"]] == ["Held-out views", "Mesh faces"]
    assert out[5] == {"options": {"max_image_side": 1601}, "problems": []}          # no ceiling
    assert capped[:5] == [out[0], out[1], out[2], capped[3], out[4]]
    assert capped[3]["problems"][1]["message"] == "must be an integer from 8 to 1600 pixels (got 4)"
    assert capped[5]["problems"] == [{"code": "invalid_config", "file": "Working resolution", "view": None,
                                      "message": "must be an integer from 8 to 1600 pixels (got 1601)"}]


@pytest.fixture(scope="module")
def standin_backend(tmp_path_factory):
    ensure_web_built()
    tmp = tmp_path_factory.mktemp("webholdout")
    be = Backend(tmp / "data", tmp / "serve.log",
                 env_extra={"NEPF_PIPELINE": "web_fixtures:pipeline_held_out_standin", STANDIN_HOLD_ENV: "1"})
    yield be
    be.stop()


def _submit(page):
    page.get_by_role("button", name="Upload and start").click()


def test_upload_with_held_out_views_fills_the_error_chart(browser, standin_backend, tmp_path, shots):  # noqa: F811
    be = standin_backend
    data = make_sphere_dtu(tmp_path / "sphere16", n_views=16, size=32)
    page, con = new_page(browser, be)
    page.goto(be.base + "/#/upload")
    page.locator("#dir-input").set_input_files(str(data))
    page.wait_for_function("() => /zipped here/.test(document.querySelector('#dataset-chosen').textContent)")
    page.get_by_label("Preset").select_option("tiny")
    assert_labelled(page)

    # the form's own check: nothing is uploaded
    page.get_by_label("Held-out views: every N-th").fill("1")
    _submit(page)
    box = page.locator("#upload-errors")
    box.wait_for(state="visible")
    assert "The job options were rejected" in box.inner_text() and "Held-out views" in box.inner_text()
    assert list_jobs(be) == []
    # the API's check, which knows the view count: 9 > 16 / 2
    page.get_by_label("Held-out views: every N-th").fill("9")
    _submit(page)
    page.wait_for_function("() => /too large for this dataset's 16 training views/"
                           ".test(document.querySelector('#upload-errors').textContent)")
    assert "The job options were rejected" in box.inner_text() and "2..8" in box.inner_text()
    assert list_jobs(be) == []

    page.get_by_label("Held-out views: every N-th").fill("4")
    page.get_by_label("Working resolution (px, long side)").fill("16")
    page.get_by_label("Texture size").select_option("512")
    page.get_by_label("Mesh faces (at most)").fill("2000")
    page.screenshot(path=str(shots / "upload-options.png"), full_page=True)
    _submit(page)
    page.wait_for_url("**/#/jobs")
    job_id = wait_for(lambda: [j["id"] for j in list_jobs(be)], 30, what="the uploaded job").pop()
    job = be.job(job_id)
    assert job["config"]["holdout_every"] == 4 and job["config"]["max_image_side"] == 16
    assert job["config"]["texture_size"] == 512 and job["config"]["max_faces"] == 2000
    assert job["dataset"]["held_out_views"] == 4   # views 0, 4, 8, 12

    # its page: the working size, the held-out count, and the chart filling while it trains
    page.goto(f"{be.base}/#/jobs/{job_id}")
    page.locator("#meta-working-size").wait_for()
    assert page.locator("#meta-working-size").inner_text() == "16×16 px"
    assert page.locator("#meta-held-out").inner_text().startswith("4 (views 0, 4, 8")
    # the stand-in holds at step STANDIN_HOLD_STEP (after its 2nd held-out record) until released,
    # so the job is still training whenever the chart has filled, however slow the machine
    page.wait_for_function("() => Number(document.querySelector('#chart-error')?.dataset.points) >= 2",
                           timeout=60_000)
    wait_for(lambda: standin_holding(be.data_dir, job_id), 30, what=f"the stand-in's hold at step {STANDIN_HOLD_STEP}")
    running = be.job(job_id)
    mid = chart_state(page, "error")
    page.screenshot(path=str(shots / "job-held-out-running.png"), full_page=True)
    assert running["status"] == "running", "the chart should fill while the job trains"
    assert mid["series"].get("test_psnr", 0) >= 2
    release_standin(be.data_dir, job_id)

    be.wait_status(job_id, ("succeeded",), 120)
    with be.client() as c:
        recs = c.get(f"/jobs/{job_id}/metrics").json()["records"]
    tests = [r for r in recs if r.get("kind") == "test"]
    assert len(tests) == STANDIN_STEPS // STANDIN_EVAL_EVERY and all(r["test_views"] == 4 for r in tests)
    page.wait_for_function("n => Number(document.querySelector('#chart-error')?.dataset.points) === n",
                           arg=len(tests), timeout=30_000)
    final = chart_state(page, "error")
    assert final["series"]["test_psnr"] == len(tests) and final["rendered"]
    assert not page.locator("#chart-error .chart-empty").is_visible()
    page.screenshot(path=str(shots / "job-held-out-done.png"), full_page=True)
    page.context.close()
    # the one 422 (holdout_every 9) is logged by Chromium as a failed resource; nothing else may be
    assert len(con.errors) == 1 and "422" in con.errors[0], con.errors
