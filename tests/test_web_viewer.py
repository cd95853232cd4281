"""Browser tests of the web viewer against the real service (Playwright + Debian's Chromium).

One module-scoped backend: ``nepf serve`` with its embedded default (SQLite job store and
broker, one local worker running the real pipeline). At start-up a
``tiny`` job on a rendered sphere (``web_fixtures.make_sphere_dtu``) is submitted through the
API; the tests that need its results wait for it to succeed. Screenshots of the main screens
go to ``test-artifacts/web/``.

Pixel checks use screenshots of the WebGL canvas: the asset covers the centre (not the
background colour); switching to the albedo channel, moving the light and showing the light
field glyphs each change the pixels by a clear margin. The tests read the app's state from the
DOM, as a user's tools would: the canvas's ``data-*`` attributes say what the 3D view drew last
(frame count, channel, light position, glyphs; ``viewer3d.js``), each chart's ``<figure>`` what
it plots (compared with ``GET /jobs/{id}/metrics``; ``charts.js``), and the job page's
``data-status`` / ``data-live`` how it follows the job.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np
import pytest

from web_fixtures import (ARTIFACTS, CHROMIUM_ARGS, Backend, asset_change, chromium_path,
                          ensure_web_built, invalid_dataset_zip, make_sphere_dtu, png_stats, wait_for,
                          zip_dir_bytes)

# Training steps of the fixture job: the tiny preset writes its first sync record at step 50,
# few enough for a 2-core CPU (the export sizes are web_fixtures.WEB_TEST_EXPORT).
FIXTURE_ITERS = 50
JOB_TIMEOUT_S = 420
BACKGROUND = np.array([0x15, 0x19, 0x1E], np.float32) / 255.0


# ------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def shots() -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_sphere_dtu(tmp_path_factory.mktemp("webds") / "sphere_scan", n_views=8, size=32)


@pytest.fixture(scope="module")
def backend(tmp_path_factory):
    ensure_web_built()
    tmp = tmp_path_factory.mktemp("webserve")
    be = Backend(tmp / "data", tmp / "serve.log")
    yield be
    be.stop()


@pytest.fixture(scope="module")
def tiny_job(backend, dataset) -> dict:
    """Submitted at module start (the tests before the wait overlap with its training)."""
    return backend.submit(zip_dir_bytes(dataset, prefix="sphere_scan/"),
                          {"preset": "tiny", "iters": FIXTURE_ITERS, "name": "sphere (web test)"})


@pytest.fixture(scope="module")
def finished_job(backend, tiny_job) -> dict:
    return backend.wait_status(tiny_job["id"], ("succeeded",), JOB_TIMEOUT_S)


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    exe = chromium_path()  # raises (the test fails) when Chromium is missing
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS, headless=True)
        yield b
        b.close()


class Console:
    """Collects console errors and uncaught page errors."""

    def __init__(self, page) -> None:
        self.errors: list[str] = []
        page.on("console", lambda m: self.errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: self.errors.append(f"pageerror: {e}"))

    def assert_clean(self) -> None:
        assert not self.errors, "browser console errors:\n" + "\n".join(self.errors)


def new_page(browser, backend, *, logged_in=True, viewport=(1280, 800)):
    ctx = browser.new_context(viewport={"width": viewport[0], "height": viewport[1]}, accept_downloads=True)
    if logged_in:
        ctx.add_init_script(f"localStorage.setItem('nepf.token', {json.dumps(backend.token)});")
    page = ctx.new_page()
    page.set_default_timeout(30_000)
    return page, Console(page)


def canvas_png(page) -> bytes:
    return page.locator("#viewer-canvas").screenshot()


def viewer_state(page) -> dict:
    """What the 3D view drew last: the data-* attributes of its canvas (``describeFrame``)."""
    d = page.locator("#viewer-canvas").evaluate("el => ({...el.dataset})")
    return {"state": d.get("state"), "frame": int(d.get("frame", 0)), "channel": d.get("channel"),
            "wireframe": d.get("wireframe") == "true", "glyphs": int(d.get("glyphs", 0)),
            "light": [float(v) for v in d.get("lightPosition", "").split()],
            "gizmo": (float(d.get("gizmoX", "nan")), float(d.get("gizmoY", "nan")))}


def wait_frame_after(page, frame: int) -> int:
    page.wait_for_function("f => Number(document.querySelector('#viewer-canvas')?.dataset.frame) > f", arg=frame)
    page.wait_for_timeout(150)  # let the compositor present the frame
    return viewer_state(page)["frame"]


def wait_viewer_loaded(page, timeout: float = 60_000) -> None:
    """The asset is loaded and drawn (``data-state`` is written with each frame)."""
    page.locator('#viewer-canvas[data-state="loaded"]').wait_for(timeout=timeout)


def chart_state(page, cid: str) -> dict:
    """What a chart plots: the data-* attributes of its ``<figure id="chart-CID">``."""
    d = page.locator(f"#chart-{cid}").evaluate("el => ({...el.dataset})")
    keys = [k for k in d["series"].split(",") if k]
    counts = [int(n) for n in d["seriesPoints"].split(",") if n]
    assert len(keys) == len(counts), d
    return {"points": int(d["points"]), "series": dict(zip(keys, counts)), "rendered": d["rendered"] == "true"}


def chart_records(page) -> int:
    return int(page.locator("#charts").get_attribute("data-records"))


def open_job(page, backend, job_id: str):
    page.goto(f"{backend.base}/#/jobs/{job_id}")
    wait_viewer_loaded(page)
    page.wait_for_timeout(300)


UNLABELLED_JS = """() => [...document.querySelectorAll('input, select, textarea, button')]
  .filter(el => el.type !== 'hidden' && !el.closest('[hidden]'))
  .filter(el => !(el.labels && el.labels.length) && !el.getAttribute('aria-label') && !el.getAttribute('aria-labelledby')
                && !(el.tagName === 'BUTTON' && el.textContent.trim()))
  .map(el => el.outerHTML.slice(0, 120))"""


DROP_FILE_JS = """(zone, f) => {
  const bytes = Uint8Array.from(atob(f.b64), (c) => c.charCodeAt(0));
  const dt = new DataTransfer();
  dt.items.add(new File([bytes], f.name, { type: 'application/zip' }));
  for (const type of ['dragenter', 'dragover', 'drop']) {
    zone.dispatchEvent(new DragEvent(type, { dataTransfer: dt, bubbles: true, cancelable: true }));
  }
}"""


def assert_labelled(page) -> None:
    """Every form control has an accessible name (label, aria-label or button text)."""
    missing = page.evaluate(UNLABELLED_JS)
    assert not missing, f"controls without a label: {missing}"


def list_jobs(backend) -> list[dict]:
    with backend.client() as c:
        return c.get("/jobs").json()["items"]


# ------------------------------------------------------------------------------ tests
def test_login_with_pasted_token_and_login_url(browser, backend, tiny_job, shots):
    page, con = new_page(browser, backend, logged_in=False)
    page.goto(backend.base + "/")
    page.wait_for_url("**/#/login")
    page.get_by_label("API token").fill("nepf_wrong-token")
    page.get_by_role("button", name="Sign in").click()
    page.locator("#login-error").wait_for(state="visible")
    assert "not accepted" in page.locator("#login-error").inner_text()
    page.screenshot(path=str(shots / "login.png"))
    page.get_by_label("API token").fill(backend.token)
    page.get_by_role("button", name="Sign in").click()
    page.wait_for_url("**/#/jobs")
    page.locator(f'.job-row[data-job-id="{tiny_job["id"]}"]').wait_for()
    assert page.evaluate("localStorage.getItem('nepf.token')") == backend.token
    page.context.close()

    # the login URL printed by `nepf serve` signs in and drops the token from the address bar
    page, con2 = new_page(browser, backend, logged_in=False)
    page.goto(backend.login_url)
    page.locator(f'.job-row[data-job-id="{tiny_job["id"]}"]').wait_for()
    assert "token=" not in page.url
    assert page.evaluate("localStorage.getItem('nepf.token')") == backend.token
    page.context.close()
    # the failed sign-in above is an expected 401 (Chromium logs the failed request)
    assert all("401" in e for e in con.errors), con.errors
    con2.assert_clean()


def test_invalid_upload_shows_per_file_errors(browser, backend, tmp_path, shots):
    page, con = new_page(browser, backend)
    page.goto(backend.base + "/#/upload")
    # drop the zip on the drop zone (a synthetic drag-and-drop with a real File)
    page.locator("#dropzone").evaluate(DROP_FILE_JS, {"name": "broken_scan.zip",
                                                      "b64": base64.b64encode(invalid_dataset_zip(tmp_path)).decode()})
    page.wait_for_function("() => /broken_scan\\.zip/.test(document.querySelector('#dataset-chosen').textContent)")
    assert page.get_by_label("Job name").input_value() == "broken_scan"
    page.get_by_label("Preset").select_option("tiny")
    assert_labelled(page)
    page.get_by_role("button", name="Upload and start").click()
    box = page.locator("#upload-errors")
    box.wait_for(state="visible")
    text = box.inner_text()
    assert "rejected" in text and "image/002.png" in text
    item = box.locator('.error-item[data-file$="image/002.png"]')
    assert item.count() == 1, text
    assert page.url.endswith("#/upload")
    page.screenshot(path=str(shots / "upload-invalid.png"), full_page=True)
    page.context.close()
    # the 422 itself is logged by Chromium as a failed resource; nothing else may be
    assert all("422" in e for e in con.errors), con.errors


def test_job_list_shows_the_finished_job(browser, backend, finished_job, shots):
    page, con = new_page(browser, backend)
    page.goto(backend.base + "/#/jobs")
    row = page.locator(f'.job-row[data-job-id="{finished_job["id"]}"]')
    row.wait_for()
    page.wait_for_function("id => document.querySelector(`.job-row[data-job-id=\"${id}\"]`).dataset.status === 'succeeded'",
                           arg=finished_job["id"])
    assert "sphere (web test)" in row.inner_text()
    assert row.get_by_role("progressbar").get_attribute("aria-valuenow") == "100"
    assert row.locator("time").inner_text().strip() not in ("", "—")
    # thumbnail preview, when the export rendered one
    with backend.client() as c:
        arts = [a["path"] for a in c.get(f"/jobs/{finished_job['id']}/artifacts").json()["artifacts"]]
    if "previews/thumb.png" in arts:
        page.wait_for_function("id => { const i = document.querySelector(`.job-row[data-job-id=\"${id}\"] img.thumb`);"
                               " return i && i.complete && i.naturalWidth > 0; }", arg=finished_job["id"])
    assert row.get_by_role("button", name=f"Cancel job {finished_job['id']}").is_disabled()
    assert row.get_by_role("button", name=f"Delete job {finished_job['id']}").is_enabled()
    assert_labelled(page)
    page.screenshot(path=str(shots / "jobs.png"))
    page.context.close()
    con.assert_clean()


def test_job_page_charts_3d_channels_light_lightfield_download(browser, backend, finished_job, shots):
    job_id = finished_job["id"]
    page, con = new_page(browser, backend)
    page.goto(backend.base + "/#/jobs")
    page.locator(f'.job-row[data-job-id="{job_id}"] a.job-link').click()
    page.wait_for_url(f"**/#/jobs/{job_id}")
    wait_viewer_loaded(page)

    # --- charts: their data equals the API's metrics, and uPlot drew them
    with backend.client() as c:
        recs = c.get(f"/jobs/{job_id}/metrics").json()["records"]
    n_sync = len({r["step"] for r in recs if r.get("kind") == "sync"})
    n_loss = len({r["step"] for r in recs if any(k.startswith("loss") for k in r)})
    assert n_sync > 0 and n_loss > 0, "the fixture job wrote no sync / loss records"
    page.wait_for_function("n => Number(document.querySelector('#chart-loss').dataset.points) >= n", arg=n_loss)
    charts = {cid: chart_state(page, cid) for cid in ("sync", "loss", "error")}
    assert charts["sync"]["points"] == n_sync
    assert set(charts["sync"]["series"]) <= {"psnr_r", "psnr_surf", "psnr_vol"}
    assert charts["sync"]["series"].get("psnr_r") == n_sync
    assert charts["loss"]["points"] == n_loss
    assert "loss" in charts["loss"]["series"]
    assert charts["sync"]["rendered"] and charts["loss"]["rendered"]
    assert chart_records(page) == len(recs)
    for cid in ("sync", "loss"):
        fig = page.locator(f"#chart-{cid}")
        assert fig.locator("canvas").count() >= 1
        assert fig.locator(".u-legend").is_visible()
    n_test = len([r for r in recs if r.get("kind") == "test"])
    if n_test:
        assert charts["error"]["points"] > 0
    else:
        assert page.locator("#chart-error .chart-empty").is_visible()

    # --- adaptivity decisions: one table row per decision the API reports, with its reason
    with backend.client() as c:
        decisions = c.get(f"/jobs/{job_id}").json()["decisions"]
    assert decisions, "the fixture job reported no adaptivity decisions"
    rows = page.locator("#decisions-table tbody tr")
    assert rows.count() == len(decisions)
    assert [rows.nth(i).get_attribute("data-decision") for i in range(rows.count())] == \
        [str(d["decision"]) for d in decisions]
    assert decisions[0]["reason"] in rows.nth(0).inner_text()

    # --- 3D view: the asset covers the centre of the canvas
    page.wait_for_timeout(300)
    pbr = canvas_png(page)
    img = png_stats(pbr)
    h, w, _ = img.shape
    centre = img[int(h * 0.35):int(h * 0.65), int(w * 0.35):int(w * 0.65)]
    not_bg = np.abs(centre - BACKGROUND).max(-1) > 0.04
    assert not_bg.mean() > 0.5, f"only {not_bg.mean():.2f} of the centre differs from the background"
    page.screenshot(path=str(shots / "job-pbr.png"), full_page=True)

    # --- channel: albedo changes the pixels
    f0 = viewer_state(page)["frame"]
    page.locator("label.seg-item", has_text="Albedo").click()
    assert page.locator("#channel-albedo").is_checked()
    wait_frame_after(page, f0)
    assert viewer_state(page)["channel"] == "albedo"
    albedo = canvas_png(page)
    d_albedo = asset_change(pbr, albedo, BACKGROUND)
    assert d_albedo > 0.2, d_albedo
    page.locator("#viewer-canvas").screenshot(path=str(shots / "channel-albedo.png"))
    for ch in ("roughness", "metallic", "normal"):
        f0 = viewer_state(page)["frame"]
        page.locator(f"#channel-{ch}").check(force=True)
        wait_frame_after(page, f0)
        assert viewer_state(page)["channel"] == ch
    page.locator("#viewer-canvas").screenshot(path=str(shots / "channel-normal.png"))
    f0 = viewer_state(page)["frame"]
    page.locator("#channel-pbr").check(force=True)
    wait_frame_after(page, f0)
    before_light = canvas_png(page)

    # --- relighting: the azimuth slider (keyboard) moves the light and changes the pixels
    pos0, f0 = viewer_state(page)["light"], viewer_state(page)["frame"]
    assert len(pos0) == 3
    az = page.locator("#light-lightAz")
    az.focus()
    start = float(az.input_value())
    for _ in range(5):  # PageUp / PageDown step a range input by a tenth of its span: 36 degrees
        page.keyboard.press("PageUp" if start < 0 else "PageDown")
    assert abs(float(az.input_value()) - start) == pytest.approx(180, abs=1)
    wait_frame_after(page, f0)
    pos1 = viewer_state(page)["light"]
    assert np.linalg.norm(np.subtract(pos1, pos0)) > 1e-3
    after_light = canvas_png(page)
    d_light = asset_change(before_light, after_light, BACKGROUND)
    assert d_light > 0.1, d_light
    page.locator("#viewer-canvas").screenshot(path=str(shots / "relit.png"))

    # ... and dragging the sphere gizmo moves it too
    gx, gy = viewer_state(page)["gizmo"]
    box = page.locator("#viewer-canvas").bounding_box()
    assert 0 <= gx <= box["width"] and 0 <= gy <= box["height"], (gx, gy, box)
    x, y = box["x"] + gx, box["y"] + gy
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x - 60, y + 40, steps=6)
    page.mouse.up()
    page.wait_for_timeout(300)
    pos2 = viewer_state(page)["light"]
    assert np.linalg.norm(np.subtract(pos2, pos1)) > 1e-3, "dragging the light gizmo did not move the light"

    # --- material editing: roughness scale and tint change the picture live
    f0 = viewer_state(page)["frame"]
    base_mat = canvas_png(page)
    page.locator("#albedo-tint").evaluate("(el) => { el.value = '#ff3000'; el.dispatchEvent(new Event('input', {bubbles: true})); }")
    wait_frame_after(page, f0)
    d_tint = asset_change(base_mat, canvas_png(page), BACKGROUND)
    assert d_tint > 0.2, d_tint
    page.get_by_role("button", name="Reset material").click()

    # --- light field: the toggle adds glyphs; density changes their number
    page.wait_for_function("() => !document.querySelector('#lightfield-toggle').disabled", timeout=30_000)
    assert viewer_state(page)["glyphs"] == 0
    f0 = viewer_state(page)["frame"]
    no_glyphs = canvas_png(page)
    page.get_by_label("Show light glyphs").check()
    wait_frame_after(page, f0)
    n_glyphs = viewer_state(page)["glyphs"]
    assert n_glyphs > 0
    assert page.locator("#lightfield-legend").is_visible()
    with_glyphs = canvas_png(page)
    d_glyphs = asset_change(no_glyphs, with_glyphs, BACKGROUND)
    assert d_glyphs > 0.05, d_glyphs
    print(f"pixel change on the asset: albedo {d_albedo:.2f}, light {d_light:.2f}, tint {d_tint:.2f}, "
          f"glyphs {d_glyphs:.2f}")
    page.screenshot(path=str(shots / "job-page.png"), full_page=True)
    dens = page.locator("#lightfield-density")
    dens.focus()
    page.keyboard.press("End")
    page.wait_for_function("n => Number(document.querySelector('#viewer-canvas').dataset.glyphs) > n", arg=n_glyphs)
    page.wait_for_timeout(200)
    page.locator("#viewer-canvas").screenshot(path=str(shots / "light-field.png"))

    assert_labelled(page)

    # --- wireframe toggle
    f0 = viewer_state(page)["frame"]
    assert viewer_state(page)["wireframe"] is False
    page.get_by_label("Wireframe").check()
    wait_frame_after(page, f0)
    assert viewer_state(page)["wireframe"] is True

    # --- downloads: the GLB button saves the same bytes as the API serves
    with backend.client() as c:
        api_glb = c.get(f"/jobs/{job_id}/artifacts/asset.glb").content
    with page.expect_download() as dl:
        page.locator('[data-download="asset.glb"]').click()
    got = Path(dl.value.path()).read_bytes()
    # saved under the API's Content-Disposition name: "<job name>-<artifact>"
    assert dl.value.suggested_filename == "sphere (web test)-asset.glb"
    assert got == api_glb and got[:4] == b"glTF"
    for p in ("textures/base_color.png", "textures/orm.png", "light_field.json", "metrics.jsonl"):
        assert page.locator(f'[data-download="{p}"]').count() == 1, p
    with page.expect_download() as dl:
        page.locator('[data-download="metrics.csv"]').click()
    csv = Path(dl.value.path()).read_text()
    assert csv.splitlines()[0].split(",").count("step") == 1 and len(csv.splitlines()) == len(recs) + 1

    page.context.close()
    con.assert_clean()


def test_relit_previews_beside_the_viewer_set_its_light_and_camera(browser, backend, finished_job, shots):
    """The export's three canonical relit previews show beside the 3D view (images decoded,
    azimuth labels from the record), and "Use this light" puts the viewer's light at the preview
    light's world position mapped into the GLB's +Y-up frame (the manifest's ``frame``), with its
    intensity, and the camera at the preview camera. The Z-up sphere comes in upright: the up axis
    follows from the manifest, +Y, without touching the selector."""
    job_id = finished_job["id"]
    with backend.client() as c:
        rec = c.get(f"/jobs/{job_id}/artifacts/previews/relit_canonical.json").json()
        manifest = c.get(f"/jobs/{job_id}/artifacts/manifest.json").json()
    assert manifest["relit_previews"] == rec
    frame = manifest["frame"]
    assert (frame["world_up"], frame["up_source"], frame["glb_up"]) == ("+z", "cameras", "+y")
    rot = np.asarray(frame["gltf_from_world"], float)
    assert len(rec["images"]) == len(rec["lights"]) == 3
    page, con = new_page(browser, backend)
    open_job(page, backend, job_id)
    strip = page.locator('#relit-previews[data-state="loaded"]')
    strip.wait_for()
    figs = page.locator("#relit-previews figure.relit-preview")
    assert figs.count() == 3
    page.wait_for_function("() => [...document.querySelectorAll('#relit-previews img')]"
                           ".every(i => i.complete && i.naturalWidth > 0)")
    sizes = page.locator("#relit-previews img").evaluate_all("ims => ims.map(i => [i.naturalWidth, i.naturalHeight])")
    assert sizes == [[rec["camera"]["width"], rec["camera"]["height"]]] * 3
    for k, az in enumerate(rec["canonical"]["azimuths_deg"]):
        assert float(figs.nth(k).get_attribute("data-azimuth")) == az
        assert f"azimuth {round(az)}°" in figs.nth(k).locator("figcaption").inner_text()
        light_attr = [float(v) for v in figs.nth(k).get_attribute("data-light-world").split()]
        np.testing.assert_allclose(light_attr, rec["lights"][k]["position_world"], rtol=0, atol=1e-12)

    scale = float(rec["canonical"]["radius_world"])
    for k in (1, 2):
        before = viewer_state(page)
        f0 = before["frame"]
        page.locator(f'[data-relit-apply="{k}"]').click()
        wait_frame_after(page, f0)
        assert strip.get_attribute("data-applied") == str(k)
        d = page.locator("#viewer-canvas").evaluate("el => ({...el.dataset})")
        assert d["up"] == "y" and page.locator("#up-axis").input_value() == "y"
        light = rec["lights"][k]
        np.testing.assert_allclose([float(v) for v in d["lightPositionWorld"].split()], light["position_world"],
                                   rtol=0, atol=1e-5 * scale)
        np.testing.assert_allclose([float(v) for v in d["lightPosition"].split()], rot @ light["position_world"],
                                   rtol=0, atol=1e-5 * scale)
        assert float(d["lightIntensity"]) == pytest.approx(float(np.mean(light["intensity_rgb"])), rel=1e-6)
        np.testing.assert_allclose([float(v) for v in d["cameraPositionWorld"].split()],
                                   rec["camera"]["position_world"], rtol=0, atol=1e-5 * scale)
        assert d["env"] == "none" and page.locator("#env-preset").input_value() == "none"
    # the sliders show the applied light: azimuth 240 deg (the record's, about the world's +Z, which is the
    # viewer's +Y) is -120 deg on the (-180, 180] slider
    assert float(page.locator("#light-lightAz").input_value()) == pytest.approx(-120, abs=1)
    assert float(page.locator("#light-lightEl").input_value()) == pytest.approx(rec["canonical"]["elevation_deg"], abs=1)
    img = png_stats(canvas_png(page))
    h, w, _ = img.shape
    centre = img[int(h * 0.4):int(h * 0.6), int(w * 0.4):int(w * 0.6)]
    assert (np.abs(centre - BACKGROUND).max(-1) > 0.04).mean() > 0.5, "the asset is not in view from the preview camera"
    page.screenshot(path=str(shots / "relit-previews.png"), full_page=True)
    assert_labelled(page)
    page.context.close()
    con.assert_clean()


def test_phone_layout_is_readable(browser, backend, finished_job, shots):
    page, con = new_page(browser, backend, viewport=(390, 844))
    page.goto(backend.base + "/#/jobs")
    page.locator(f'.job-row[data-job-id="{finished_job["id"]}"]').wait_for()
    page.screenshot(path=str(shots / "phone-jobs.png"), full_page=True)
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth + 1")
    open_job(page, backend, finished_job["id"])
    assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth + 1")
    canvas = page.locator("#viewer-canvas").bounding_box()
    assert canvas["width"] >= 300
    page.screenshot(path=str(shots / "phone-job.png"), full_page=True)
    # keyboard: the channel radios and sliders are reachable with Tab
    page.locator("#channel-pbr").focus()
    page.keyboard.press("ArrowRight")
    assert page.locator("#channel-albedo").is_checked()
    page.context.close()
    con.assert_clean()


def test_upload_folder_through_ui_then_watch_and_cancel(browser, backend, finished_job, dataset, shots):
    """Pick a dataset folder (zipped in the browser), watch the job appear and progress, follow
    it live on its page, cancel it there, and see its partial results."""
    page, con = new_page(browser, backend)
    page.goto(backend.base + "/#/upload")
    page.locator("#dir-input").set_input_files(str(dataset))
    page.wait_for_function("() => /zipped here/.test(document.querySelector('#dataset-chosen').textContent)")
    page.get_by_label("Preset").select_option("tiny")
    page.get_by_label("Time budget (minutes)").fill("5")
    before = {j["id"] for j in list_jobs(backend)}
    page.get_by_role("button", name="Upload and start").click()
    page.wait_for_url("**/#/jobs")
    new_id = wait_for(lambda: ({j["id"] for j in list_jobs(backend)} - before), 30,
                      what="the uploaded job in GET /jobs").pop()
    row = page.locator(f'.job-row[data-job-id="{new_id}"]')
    row.wait_for()
    cfg = backend.job(new_id)["config"]
    assert cfg["preset"] == "tiny" and cfg["time_budget_s"] == 300
    # progress: the bar moves (SSE, or polling) while the job trains
    page.wait_for_function(
        "id => { const b = document.querySelector(`.job-row[data-job-id=\"${id}\"] [role=progressbar]`);"
        " return b && Number(b.getAttribute('aria-valuenow')) > 0; }", arg=new_id, timeout=180_000)
    assert row.get_attribute("data-status") == "running"
    page.screenshot(path=str(shots / "jobs-running.png"))

    # the job page follows it live over SSE: progress and new metric records arrive; a browser
    # without EventSource gets the same through polling
    row.locator("a.job-link").click()
    page.wait_for_url(f"**/#/jobs/{new_id}")
    page.locator('.job-page[data-live="sse"]').wait_for(timeout=15_000)
    poll_page, poll_con = new_page(browser, backend)
    poll_page.context.add_init_script("delete window.EventSource;")
    poll_page.goto(f"{backend.base}/#/jobs/{new_id}")
    poll_page.locator('.job-page[data-live="polling"]').wait_for(timeout=15_000)
    more_records = "n => Number(document.querySelector('#charts').dataset.records) > n"
    n0, m0 = chart_records(page), chart_records(poll_page)
    page.wait_for_function(more_records, arg=n0, timeout=180_000)
    poll_page.wait_for_function(more_records, arg=m0, timeout=30_000)
    assert chart_state(page, "loss")["points"] > 0
    page.screenshot(path=str(shots / "job-running.png"), full_page=True)
    poll_page.context.close()
    poll_con.assert_clean()
    page.get_by_role("button", name="Cancel").click()
    wait_for(lambda: backend.job(new_id)["cancel_requested"] or backend.job(new_id)["status"] == "cancelled", 20,
             what="the cancel request")
    # the core stops at the next step and still exports the partial model: the page says so
    # and shows the partial asset
    backend.wait_status(new_id, ("cancelled",), 240)
    try:
        page.locator("#job-note").wait_for(state="visible", timeout=30_000)
    except Exception:
        raise AssertionError(f"status shown: {page.locator('.job-page').get_attribute('data-status')}, "
                             f"API: {backend.job(new_id)['status']}") from None
    assert "partial results" in page.locator("#job-note").inner_text()
    assert page.locator(".job-page").get_attribute("data-status") == "cancelled"
    with backend.client() as c:
        has_glb = any(a["path"] == "asset.glb" for a in c.get(f"/jobs/{new_id}/artifacts").json()["artifacts"])
    if has_glb:
        wait_viewer_loaded(page)
    else:
        page.locator("#viewer-msg", has_text="cancelled before an asset").wait_for()
    page.screenshot(path=str(shots / "job-cancelled.png"), full_page=True)

    # a finished job can be deleted from its page (after a confirmation)
    page.once("dialog", lambda d: d.accept())
    page.locator("#job-delete").click()
    page.wait_for_url("**/#/jobs")
    with backend.client() as c:
        wait_for(lambda: c.get(f"/jobs/{new_id}").status_code == 404, 15, what="the job to be deleted")
    page.wait_for_function("id => !document.querySelector(`.job-row[data-job-id=\"${id}\"]`)", arg=new_id)
    page.context.close()
    con.assert_clean()
