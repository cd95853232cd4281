"""The benchmark harness end to end on a generated tiny scene (``python -m bench run``), its
variants and its comparison arithmetic.

Fast: one ``tiny`` run of a ~2 s budget in a subprocess, no Chamfer during training and a
coarse final Chamfer; the rest is arithmetic on hand-made records.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scenes_root(tmp_path_factory):
    """``ROOT/tiny_sphere/{input/dtu, gt/...}``: the layout of /work/shared/scenes/<name>."""
    from nepf_core.data.synth import make_scene
    base = tmp_path_factory.mktemp("bench_scene")
    make_scene(base / "src", shape="sphere", material="diffuse", n_views=6, n_test=2, resolution=24)
    scene = base / "scenes" / "tiny_sphere"
    (scene / "input").mkdir(parents=True)
    os.symlink(base / "src" / "dtu", scene / "input" / "dtu")
    os.symlink(base / "src" / "gt", scene / "gt")
    return base / "scenes"


def test_bench_run_end_to_end(scenes_root, tmp_path):
    out = tmp_path / "res"
    cmd = [sys.executable, "-m", "bench", "run", "--scenes-root", str(scenes_root), "--scenes", "tiny_sphere",
           "--configs", "tiny", "--variants", "adaptive", "--budget", "1.5", "--eval-every", "0.7",
           "--eval-stride", "2", "--threads", "1", "--no-fit-chamfer", "--chamfer-resolution", "32",
           "--chamfer-samples", "5000", "--out", str(out)]
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    for name in ("results.json", "table.md", "error_vs_time_tiny_sphere.png", "machine.json", "command.txt"):
        assert (out / name).exists(), name
    assert (out / "error_vs_time_tiny_sphere.png").stat().st_size > 1000
    res = json.loads((out / "results.json").read_text())
    assert res["command"].startswith("python -m bench run ") and "--budget 1.5" in res["command"]
    assert res["machine"]["cpu_count"] >= 1 and res["machine"]["torch"]
    (run,) = res["runs"]
    assert run["status"] == "succeeded", run.get("error")
    assert run["steps"] > 0 and run["peak_rss_mb_process"] > 50
    curve = run["test_curve"]
    assert curve and curve[-1]["final"]
    walls = [t["wall_s"] for t in curve]
    assert walls == sorted(walls) and walls[-1] <= run["train_wall_s"] + 1e-6
    for key in ("test_psnr", "test_psnr_full", "albedo_psnr"):
        assert math.isfinite(curve[-1][key]), key
    assert math.isfinite(run["chamfer_final"]) and run["chamfer_resolution"] == 32
    (row,) = res["summary"]["rows"]
    for key in ("test_psnr", "test_psnr_full", "albedo_psnr", "chamfer", "peak_rss_mb", "s_per_step", "t_to_X"):
        assert row[key] is not None and math.isfinite(row[key]), key
    table = (out / "table.md").read_text()
    assert "| tiny_sphere | tiny | adaptive |" in table and "time to X" in table
    # report rebuilds from results.json alone
    from bench.report import main as report_main
    (out / "table.md").unlink()
    assert report_main([str(out)]) == 0
    assert "| tiny_sphere | tiny | adaptive |" in (out / "table.md").read_text()


def test_report_merges_benchmarks_run_side_by_side(tmp_path):
    """Two results folders (one variant each) -> one table with the adaptive comparison."""
    from bench.report import main as report_main
    for name, variant, curve in (("a", "adaptive", [(60, 24.0), (120, 27.0)]), ("b", "all_on", [(60, 20.0), (120, 26.0)])):
        d = tmp_path / name
        d.mkdir()
        (d / "results.json").write_text(json.dumps({"command": f"bench {name}", "machine": {}, "settings": {},
                                                    "runs": [_rec("s", "fast", variant, curve)]}))
    out = tmp_path / "merged"
    assert report_main([str(out), "--merge", str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    merged = json.loads((out / "results.json").read_text())
    assert [r["variant"] for r in merged["runs"]] == ["adaptive", "all_on"]
    assert merged["command"] == "bench a & bench b"
    table = (out / "table.md").read_text()
    # target = min(27, 26) = 26: adaptive reaches it at 120 s, all_on at 120 s -> 0% saved
    assert "| s | fast | all_on | 26.00 |" in table
    with pytest.raises(SystemExit, match="not found"):
        report_main([str(out), "--merge", str(tmp_path / "missing")])


def _rec(scene, config, variant, curve, repeat=0, **kw):
    pts = [{"step": i + 1, "wall_s": float(w), "test_psnr": float(v), "final": i == len(curve) - 1}
           for i, (w, v) in enumerate(curve)]
    return {"scene": scene, "config": config, "variant": variant, "repeat": repeat, "test_curve": pts,
            "steps": 100, "train_wall_s": float(curve[-1][0]), "budget_s": 1.0, **kw}


def test_comparisons_arithmetic():
    from bench.report import summarize
    runs = [
        _rec("s", "paper", "adaptive", [(60, 20.0), (120, 25.0), (180, 24.0)]),   # best 25 at 120 s
        _rec("s", "fast", "adaptive", [(60, 24.0), (120, 26.0), (180, 27.0)]),    # reaches 25 at 120 s
        _rec("s", "fast", "all_on", [(60, 22.0), (120, 25.5), (180, 26.0)]),
        _rec("s", "fast", "naive", [(60, 27.5), (120, 28.0), (180, 28.0)]),
        _rec("t", "paper", "adaptive", [(60, 30.0)]),
        _rec("t", "fast", "adaptive", [(60, 20.0), (120, 29.0)]),                   # never reaches 30
    ]
    s = summarize({"runs": runs})
    fp = {x["scene"]: x for x in s["fast_vs_paper"]}
    assert fp["s"]["paper_best"] == 25.0 and fp["s"]["t_paper"] == 120 and fp["s"]["t_fast"] == 120
    assert fp["s"]["ratio"] == pytest.approx(1.0)
    assert fp["t"]["t_fast"] is None and fp["t"]["ratio"] is None
    aa, ao = s["adaptive_vs_all_on"]
    assert (aa["baseline"], ao["baseline"]) == ("all_on", "naive")
    # against naive: target = min(27, 28) = 27, adaptive at 180 s, the baseline at 60 s
    assert ao["target"] == 27.0 and ao["t_adaptive"] == 180 and ao["t_all_on"] == 60
    assert ao["saved_pct"] == pytest.approx(100 * (60 - 180) / 60)
    # target = min(27, 26) = 26: adaptive first >= 26 at 120 s, all_on at 180 s
    assert aa["target"] == 26.0 and aa["t_adaptive"] == 120 and aa["t_all_on"] == 180
    assert aa["diff"] == pytest.approx(1.0) and aa["saved_pct"] == pytest.approx(100 * 60 / 180)
    rows = {(r["scene"], r["config"], r["variant"]): r for r in s["rows"]}
    # X for scene s = lowest final among its rows = 24 (paper): paper reaches it at 60... no, 25 at 120 >= 24
    assert rows[("s", "paper", "adaptive")]["target_X"] == 24.0
    assert rows[("s", "paper", "adaptive")]["t_to_X"] == 120 and rows[("s", "fast", "adaptive")]["t_to_X"] == 60
    # medians over repeats
    reps = [_rec("m", "fast", "adaptive", [(10, v)], repeat=i) for i, v in enumerate((20.0, 22.0, 30.0))]
    (row,) = summarize({"runs": reps})["rows"]
    assert row["test_psnr"] == 22.0 and row["n"] == 3


def test_variants_build_their_baselines():
    """`all_on` switches adaptivity off and drops the occupancy grid (no empty ray is left out);
    `naive` is the brief's dense-grid reference (one 96^3 level, 48 uniform samples, FD normals,
    nothing adaptive); `adaptive` changes nothing in the preset."""
    from bench.run import VARIANTS
    from nepf_core.config import fast
    from nepf_core.jobs import build_config
    base = fast()
    assert base.model.occupancy_resolution > 0 and base.train.adaptive
    on = build_config("fast", None, VARIANTS["all_on"])
    assert on.model.occupancy_resolution == 0 and not on.train.adaptive
    assert on.render == base.render and on.model.sdf_grid == base.model.sdf_grid
    nv = build_config("fast", None, VARIANTS["naive"])
    g = nv.model.sdf_grid   # a GridSDFConfig
    assert (g.n_levels, g.base_resolution, g.max_resolution) == (1, 96, 96) and not nv.train.adaptive
    assert (nv.render.n_samples, nv.render.n_importance, nv.render.normals) == (48, 0, "fd")
    assert nv.model.occupancy_resolution == 0 and nv.train.batch_rays == 1024
    ad = build_config("fast", None, VARIANTS["adaptive"])
    assert ad.render == base.render and ad.model == base.model and ad.train.adaptive
    for cfg in (on, nv, ad):
        cfg.check()                      # each variant is a config fit() accepts


def test_pairs_match_by_seed_and_tail_means(tmp_path):
    """Runs merged from one-repeat benchmarks (seed set by --override) pair by seed, whatever
    the merge order; the tail mean is over the last 10 % of the training time."""
    from bench.curves import tail_mean
    from bench.report import summarize, write_table
    a1 = _rec("s", "fast", "adaptive", [(100, 20.0), (800, 24.0), (900, 26.0), (1000, 25.0)],
              overrides={"train.seed": 1})
    a0 = _rec("s", "fast", "adaptive", [(100, 22.0), (200, 23.0)], overrides={"train.seed": 0})
    b0 = _rec("s", "fast", "all_on", [(100, 21.0), (200, 22.5)], overrides={"train.seed": 0})
    b1 = _rec("s", "fast", "all_on", [(100, 19.0), (500, 24.5), (1000, 25.5)], overrides={"train.seed": 1})
    # tail of a1: evaluations at >= 900 s -> (26 + 25) / 2; of a0: >= 180 s -> 23
    assert tail_mean(a1) == pytest.approx(25.5) and tail_mean(a0) == 23.0 and tail_mean({"test_curve": []}) is None
    (row,) = summarize({"runs": [a1, b0, a0, b1]})["adaptive_vs_all_on"]
    p0, p1 = row["per_repeat"]
    assert (p0["seed"], p1["seed"]) == (0, 1)
    # seed 0: lower final 22.5: adaptive at 200 s, all_on at 200 s; tails 23 / 22.5 -> same
    assert p0["t_adaptive"] == 200 and p0["t_all_on"] == 200 and p0["saved_pct"] == 0.0
    # seed 1: finals 25 / 25.5 -> target 25: adaptive at 900 s, all_on at 1000 s (10 % saved);
    # tails 25.5 / 25.5 -> adaptive first >= 25.5 at 900 s, all_on at 1000 s
    assert p1["target"] == 25.0 and p1["saved_pct"] == pytest.approx(10.0)
    assert p1["tail_adaptive"] == pytest.approx(25.5) and p1["tail_saved_pct"] == pytest.approx(10.0)
    # within 0.3 dB of the baseline's final (25.5): adaptive first >= 25.2 at 900 s; all_on reaches
    # 25.5 at 1000 s
    assert p1["t_adaptive_tol"] == 900 and p1["t_all_on_tol"] == 1000 and p1["tol_saved_pct"] == pytest.approx(10.0)
    # seed 0: baseline final 22.5 -> adaptive >= 22.2 first at 200 s (22.0 at 100 s), all_on
    # 22.5 at 200 s: 0 %
    assert p0["t_adaptive_tol"] == 200 and p0["tol_saved_pct"] == 0.0
    write_table({"runs": [a1, b0, a0, b1]}, summarize({"runs": [a1, b0, a0, b1]}), tmp_path / "t.md")
    table = (tmp_path / "t.md").read_text()
    assert "| s | all_on | 1 | 100 / 100 | 1000 / 1000 | 25.00 / 25.50 | -0.50 | 900 / 1000 | 10% | 25.50 / 25.50 | 10% | 900 / 1000 | 10% |" in table


def test_smoothed_pair_comparison_uses_running_means_of_three(tmp_path):
    """A spike in one evaluation decides a raw first crossing but not the smoothed one.
    Adaptive: 20, 26 (spike), 23, 24, 25 at 100..500 s; all_on: 21, 22, 24, 25, 25.3.
    Running means of 3 from the third evaluation: adaptive 23.0 (300 s), 24.333 (400), 24.0 (500);
    all_on 22.333, 23.667, 24.767. Smoothed finals 24.0 / 24.767 -> target 24.0: adaptive first
    at 400 s, all_on at 500 s (20 % saved); within 0.3 dB of 24.767 (24.467): adaptive never,
    all_on at 500 s."""
    from bench.curves import smoothed_curve, time_to_reach_smoothed
    from bench.report import summarize, write_table
    a = _rec("s", "fast", "adaptive", [(100, 20.0), (200, 26.0), (300, 23.0), (400, 24.0), (500, 25.0)])
    b = _rec("s", "fast", "all_on", [(100, 21.0), (200, 22.0), (300, 24.0), (400, 25.0), (500, 25.3)])
    sa = smoothed_curve(a)
    assert [t for t, _ in sa] == [300.0, 400.0, 500.0]
    assert [v for _, v in sa] == pytest.approx([23.0, 73 / 3, 24.0])
    assert smoothed_curve(_rec("s", "fast", "adaptive", [(100, 20.0), (200, 21.0)])) == []
    assert time_to_reach_smoothed(a, 25.0) is None and time_to_reach_smoothed(a, 23.0) == 300.0
    (row,) = summarize({"runs": [a, b]})["adaptive_vs_all_on"]
    (p,) = row["per_repeat"]
    # raw: finals 25 / 25.3 -> target 25: the spike (26 at 200 s) is the adaptive run's first crossing
    assert p["t_adaptive"] == 200
    assert p["smooth_final_adaptive"] == pytest.approx(24.0) and p["smooth_final_all_on"] == pytest.approx(74.3 / 3)
    assert p["smooth_t_adaptive"] == 400 and p["smooth_t_all_on"] == 500
    assert p["smooth_saved_pct"] == pytest.approx(20.0)
    assert p["smooth_t_adaptive_tol"] is None and p["smooth_t_all_on_tol"] == 500 and p["smooth_tol_saved_pct"] is None
    write_table({"runs": [a, b]}, summarize({"runs": [a, b]}), tmp_path / "t.md")
    # levels: first smoothed points 23.0 / 22.333 -> from 24 dB; the lower final 24.0 is the only level
    assert p["levels_n"] == 1 and p["levels_saved_median_pct"] == pytest.approx(20.0) and p["levels_saved_30_n"] == 0
    assert "| s | all_on | 0 | 24.00 / 24.77 | -0.77 | 400 / 500 | 20% | not reached / 500 | n/a% | 20% (0 / 1) |" in \
        (tmp_path / "t.md").read_text()


def test_level_savings_at_every_shared_whole_db_level_up_to_the_lower_final():
    """Baseline: 30, 36, 37, 37, 37, 37 at 30..180 s (smoothed 34.333 @90, 36.667 @120, 37 from 150);
    adaptive: 30, 31, 32, 36, 39, 33 (a dip), 40, 41 (smoothed 31 @90, 33 @120, 35.667 @150,
    36 @180, 37.333 @210, 38 @240). Levels from floor(34.333) + 1 = 35 dB to the lower final 37:
    35 -> 150 / 120 s (-25 %), 36 -> 180 / 120 s (-50 %), 37 -> 210 / 150 s (-40 %)."""
    from bench.curves import level_savings
    b = _rec("s", "fast", "all_on", [(30 * k, v) for k, v in enumerate((30, 36, 37, 37, 37, 37), 1)])
    a = _rec("s", "fast", "adaptive", [(30 * k, v) for k, v in enumerate((30, 31, 32, 36, 39, 33, 40, 41), 1)])
    lv = level_savings(a, b)
    assert [x["level"] for x in lv] == pytest.approx([35.0, 36.0, 37.0])
    assert [(x["t_a"], x["t_b"]) for x in lv] == [(150.0, 120.0), (180.0, 120.0), (210.0, 150.0)]
    assert [x["saved_pct"] for x in lv] == pytest.approx([-25.0, -50.0, -40.0])
    # swapped roles: the same levels, the opposite sign of the time difference
    assert [x["saved_pct"] for x in level_savings(b, a)] == pytest.approx([20.0, 100 / 3, 200 / 7])
    assert level_savings(a, _rec("s", "fast", "all_on", [(30, 30.0)])) == []


def _scene_root(tmp_path):
    """A scenes root holding one scene ``s`` in the layout the runner checks (no data: planning only)."""
    for sub in ("input/dtu", "gt/dtu_test"):
        (tmp_path / "s" / sub).mkdir(parents=True, exist_ok=True)
    return tmp_path


def _plan(tmp_path, *extra):
    from bench.run import build_parser, plan_runs
    _scene_root(tmp_path)
    return plan_runs(build_parser().parse_args(["--scenes", "s", "--scenes-root", str(tmp_path), "--configs", "fast",
                                                "--out", str(tmp_path / "out"), *extra]))


def test_seeds_are_the_ones_asked_for(tmp_path):
    """``--seeds 2,3`` trains seeds 2 and 3 (not the repeat indices 0 and 1); ``--repeats N`` keeps
    seeds 0..N-1; a second source of seeds is refused instead of silently winning."""
    assert [r["overrides"]["train.seed"] for r in _plan(tmp_path, "--seeds", "2,3")] == [2, 3]
    assert [r["overrides"]["train.seed"] for r in _plan(tmp_path, "--seeds", "5")] == [5]
    assert [r["overrides"]["train.seed"] for r in _plan(tmp_path, "--repeats", "2")] == [0, 1]
    for bad in (["--seeds", "2,2"], ["--seeds", "a"], ["--seeds", "2,3", "--repeats", "2"],
                ["--seeds", "2", "--override", "train.seed=4"]):
        with pytest.raises(SystemExit):
            _plan(tmp_path, *bad)


def test_the_materials_suite_passes_its_seeds_through(tmp_path, monkeypatch):
    """``python -m bench materials --seeds 2,3`` hands the runner exactly those seeds."""
    import bench.run
    from bench.materials import main
    seen = {}

    def fake_run(argv):
        seen["argv"] = argv
        return 1   # stop before the table
    monkeypatch.setattr(bench.run, "main", fake_run)
    assert main(["--seeds", "2,3", "--out", str(tmp_path / "o"), "--scenes", "s", "--scenes-root", str(tmp_path)]) == 1
    argv = seen["argv"]
    assert argv[argv.index("--seeds") + 1] == "2,3" and "--repeats" not in argv


def test_skip_done_reuses_a_run_only_with_the_same_overrides(tmp_path, monkeypatch):
    """``--skip-done`` reuses a finished run by its id only when its overrides (the seed among them)
    are the ones asked for: ``--seeds 1`` after ``--seeds 0`` has the same id (``r0``) and must train."""
    import bench.report
    import bench.run
    trained = []

    def fake_run_one(spec, out, timeout_s, log=print):
        trained.append(spec["overrides"]["train.seed"])
        child = out / "runs" / spec["id"] / "bench_child.json"
        child.parent.mkdir(parents=True, exist_ok=True)
        child.write_text("{}")
        return {"id": spec["id"], "status": "succeeded", "overrides": spec["overrides"], "process_wall_s": 1.0,
                "peak_rss_mb_process": 1.0}
    monkeypatch.setattr(bench.run, "run_one", fake_run_one)
    monkeypatch.setattr(bench.report, "final_test", lambda rec: {})
    monkeypatch.setattr(bench.report, "write_all", lambda res, out: (out / "results.json").write_text(json.dumps(res)))
    base = ["--scenes", "s", "--scenes-root", str(_scene_root(tmp_path)), "--configs", "fast", "--out", str(tmp_path / "o"),
            "--skip-done"]
    for seed in ("0", "0", "1", "1"):
        assert bench.run.main(base + ["--seeds", seed]) == 0
    assert trained == [0, 1]
