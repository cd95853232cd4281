"""Job options (issues 26, 34): ``holdout_every``, ``texture_size``, ``max_faces``, ``up_axis`` in the job config:
their 422s, their defaults, and the job's value overriding the service default all the way
to the pipeline's JobRequest."""

from __future__ import annotations

import pytest

from test_api_dataset_limits import dtu_zip, post, service  # noqa: F401 - the fixture


@pytest.mark.parametrize("config, words", [
    ({"holdout_every": 1}, "1 would hold out every view"),
    ({"holdout_every": -2}, "holdout_every must be 0"),
    ({"holdout_every": "8"}, "holdout_every must be 0"),
    ({"holdout_every": True}, "holdout_every must be 0"),
    ({"texture_size": 300}, "texture_size must be one of 256, 512, 1024, 2048 (got 300)"),
    ({"texture_size": "1024"}, "texture_size must be one of"),
    ({"max_faces": 999}, "max_faces must be an integer in [1000, 2000000] (got 999)"),
    ({"max_faces": 2_000_001}, "max_faces must be an integer in [1000, 2000000]"),
    ({"max_faces": 5000.0}, "max_faces must be an integer"),
    ({"up_axis": "up"}, 'up_axis must be one of auto, +x, -x, +y, -y, +z, -z'),
    ({"up_axis": 2}, "up_axis must be one of"),
    ({"up_axis": "+w"}, '(got "+w")'),
])
def test_bad_options_are_422_naming_the_key(service, tmp_path, config, words):  # noqa: F811
    clients, svc, data = service()
    r = post(clients["alice"], dtu_zip(tmp_path), config=config)
    assert r.status_code == 422, r.text
    assert r.json()["code"] == "invalid_config" and words in r.json()["detail"], r.text
    assert not (data / "jobs").exists() or not any((data / "jobs").iterdir())   # nothing kept


def test_holdout_every_is_checked_against_the_view_count(service, tmp_path):  # noqa: F811
    clients, svc, data = service()
    r = post(clients["alice"], dtu_zip(tmp_path / "a", n=6), config={"holdout_every": 4})
    assert r.status_code == 422 and r.json()["code"] == "invalid_config", r.text
    assert "too large for this dataset's 6 training views: use 0 or 2..3" in r.json()["detail"]
    r = post(clients["alice"], dtu_zip(tmp_path / "b", n=3), config={"holdout_every": 2})
    assert r.status_code == 422 and "at least 4 views are needed" in r.json()["detail"], r.text
    r = post(clients["alice"], dtu_zip(tmp_path / "c", n=6), config={"holdout_every": 3})
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["config"]["holdout_every"] == 3
    assert (job["dataset"]["held_out_views"], job["dataset"]["training_views"]) == (2, 4)   # views 0 and 3


def test_holdout_default_follows_the_view_count(service, tmp_path):  # noqa: F811
    clients, svc, data = service()
    big = post(clients["alice"], dtu_zip(tmp_path / "a", n=16)).json()
    assert big["config"]["holdout_every"] == 8
    assert (big["dataset"]["held_out_views"], big["dataset"]["training_views"]) == (2, 14)
    small = post(clients["alice"], dtu_zip(tmp_path / "b", n=6)).json()
    assert small["config"]["holdout_every"] == 0 and small["dataset"]["held_out_views"] == 0
    off = post(clients["alice"], dtu_zip(tmp_path / "c", n=16), config={"holdout_every": 0}).json()
    assert off["config"]["holdout_every"] == 0 and off["dataset"]["training_views"] == 16
    # what the page shows: the size the job trains at is in the same answer
    assert (big["dataset"]["working_width"], big["dataset"]["working_height"]) == (24, 24)


def test_job_options_override_the_service_defaults_in_the_job_request(service, tmp_path):  # noqa: F811
    from worker.runner import JobRunner
    clients, svc, data = service(export_texture_size=512, export_max_faces=50_000)
    seen = {}

    def pipeline(request):
        seen[request.data_dir.parent.name] = (request.texture_size, request.max_faces, request.holdout_every,
                                              request.up_axis)
        return {"status": "succeeded", "step": 1, "total": 1}

    asked = post(clients["alice"], dtu_zip(tmp_path / "a", n=16),
                 config={"texture_size": 2048, "max_faces": 1000, "holdout_every": 4, "up_axis": "-Y"}).json()
    assert asked["config"]["up_axis"] == "-y"
    auto = post(clients["alice"], dtu_zip(tmp_path / "c", n=16), config={"up_axis": "auto"}).json()
    assert auto["config"]["up_axis"] is None   # detected from the cameras at export
    default = post(clients["alice"], dtu_zip(tmp_path / "b", n=16)).json()["id"]
    for jid in (asked["id"], auto["id"], default):
        assert JobRunner(svc.settings, svc.Session, jid, "w1", pipeline=pipeline).run() == "succeeded"
    assert seen == {asked["id"]: (2048, 1000, 4, "-y"), auto["id"]: (512, 50_000, 8, None),
                    default: (512, 50_000, 8, None)}


def test_up_axis_choices_are_the_cores():
    """The API validates ``up_axis`` without importing the core: the same choices."""
    from api.job_config import UP_AXIS_CHOICES
    from nepf_core.up_axis import UP_CHOICES
    assert UP_AXIS_CHOICES == UP_CHOICES


def test_the_documented_options_are_the_models():
    """docs/SERVICE.md's "Job options" table lists exactly the fields of ``JobConfig``, with the
    values its constraints allow (the model is the one source: the API, the schema the viewer's
    form reads, and this table)."""
    import re
    from pathlib import Path

    from api.job_config import JobConfig, job_config_schema
    from jobstore.settings import Settings

    doc = (Path(__file__).resolve().parent.parent / "docs" / "SERVICE.md").read_text()
    table = doc[doc.index("### Job options"):]
    table = table[:table.index("\n\n", table.index("| key |"))]
    rows = {m.group(1): m.group(2) for m in re.finditer(r"^\| `(\w+)` \| ([^|]*) \|", table, re.M)}
    assert set(rows) == set(JobConfig.model_fields), set(rows) ^ set(JobConfig.model_fields)
    props = job_config_schema(Settings())["properties"]

    def bounds(key):
        branch = next(b for b in props[key].get("anyOf", [props[key]]) if b.get("type") != "null")
        return {**props[key], **branch}

    def number(x):
        return f"{x:,}" if "," in rows["iters"] + rows["max_faces"] else str(x)

    assert rows["preset"] == ", ".join(f"`{p}`" for p in bounds("preset")["enum"])
    assert rows["iters"] == f"{number(bounds('iters')['minimum'])}..{number(bounds('iters')['maximum'])}"
    tb = bounds("time_budget_s")
    assert rows["time_budget_s"] == f"({tb['exclusiveMinimum']}, {tb['maximum']}]"
    assert str(bounds("name")["maxLength"]) in rows["name"]
    assert f">= {bounds('max_image_side')['minimum']}" in rows["max_image_side"]
    assert rows["texture_size"] == ", ".join(map(str, bounds("texture_size")["enum"]))
    assert rows["max_faces"] == f"{number(bounds('max_faces')['minimum'])}..{number(bounds('max_faces')['maximum'])}"
    assert all(f"`{a}`" in rows["up_axis"] for a in props["up_axis"]["enum"] if a is not None)
