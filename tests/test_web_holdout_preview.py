"""The job page shows the latest held-out evaluation's picture (render | truth | error) beside
the error chart while the job trains, and replaces it as evaluations come (issue 34, item 7).

The service is the real one (``nepf serve``, embedded); the training is the stand-in
``web_fixtures.pipeline_held_out_standin``, which writes the picture with the real writer
(``nepf_core.holdout_preview``) at each held-out evaluation and names it in the record."""

from __future__ import annotations

import pytest

from test_web_viewer import browser, new_page, shots  # noqa: F401 - fixtures
from web_fixtures import Backend, ensure_web_built, make_sphere_dtu, wait_for, zip_dir_bytes


@pytest.fixture(scope="module")
def standin_backend(tmp_path_factory):
    ensure_web_built()
    tmp = tmp_path_factory.mktemp("webpreview")
    be = Backend(tmp / "data", tmp / "serve.log",
                 env_extra={"NEPF_PIPELINE": "web_fixtures:pipeline_held_out_standin"})
    yield be
    be.stop()


def test_job_page_shows_the_latest_held_out_picture(browser, standin_backend, tmp_path, shots):  # noqa: F811
    be = standin_backend
    data = make_sphere_dtu(tmp_path / "sphere8", n_views=8, size=16)
    job = be.submit(zip_dir_bytes(data), {"preset": "tiny", "holdout_every": 4})
    page, con = new_page(browser, be)
    page.goto(f"{be.base}/#/jobs/{job['id']}")
    fig = page.locator("#holdout-preview")
    page.wait_for_function("() => Number(document.querySelector('#holdout-preview')?.dataset.step) > 0",
                           timeout=60_000)
    first = int(fig.get_attribute("data-step"))
    assert first < 150   # shown while the stand-in trains (its last evaluation is at step 150)
    # the picture is the served PNG, decoded: three 16-px panels and two 2-px gaps
    size = page.evaluate("async () => { const i = document.querySelector('#holdout-preview img');"
                         " await i.decode(); return [i.naturalWidth, i.naturalHeight]; }")
    assert size == [3 * 16 + 2 * 2, 16]
    assert "step" in fig.locator("figcaption").inner_text()
    # a later evaluation replaces it
    page.wait_for_function(f"() => Number(document.querySelector('#holdout-preview').dataset.step) > {first}",
                           timeout=60_000)
    page.screenshot(path=str(shots / "job-held-out-preview.png"), full_page=True)
    wait_for(lambda: be.job(job["id"])["status"] == "succeeded", 60, what="the stand-in job to finish")
    page.wait_for_function("() => Number(document.querySelector('#holdout-preview').dataset.step) === 150",
                           timeout=30_000)
    con.assert_clean()
