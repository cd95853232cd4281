"""The CLI's working side and decoded-pixel cap are the service's (issue 34): one pair of constants
(``nepf_core.limits``) read by ``nepf fit/eval/render/relight`` and by ``api.settings``; the
progress output says the working size; a dataset over the cap is refused with an error that
names the cap (not an out-of-memory kill). Data: the synthetic torus of ``tests/datagen.py``
(8 views at 40x32)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from datagen import synth_dir  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def test_cli_defaults_are_the_services():
    from api.settings import Settings
    from nepf_core.cli import build_parser
    from nepf_core.limits import DEFAULT_IMAGE_SIDE, MAX_TOTAL_PIXELS

    s = Settings(_env_file=None)
    assert (s.default_image_side, s.max_total_pixels) == (DEFAULT_IMAGE_SIDE, MAX_TOTAL_PIXELS) == (800, 400_000_000)
    ap = build_parser()
    for argv in (["fit", "D", "--out", "R"], ["eval", "R", "--test", "D"], ["render", "R", "--cameras", "D", "--out", "O"],
                 ["relight", "R", "--lights", "L", "--cameras", "D", "--out", "O"]):
        a = ap.parse_args(argv)
        assert (a.max_side, a.max_total_pixels) == (DEFAULT_IMAGE_SIDE, MAX_TOTAL_PIXELS), argv[0]
    assert ap.parse_args(["fit", "D", "--out", "R", "--max-side", "0"]).max_side == 0


def test_the_shared_constants_import_nothing_and_the_api_no_torch():
    tree = ast.parse((REPO / "nepf_core" / "limits.py").read_text())
    assert not [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert (REPO / "nepf_core" / "__init__.py").read_text().count("import") == 0
    script = ("import sys, api.settings, api.job_config; "
              "bad = sorted(m for m in sys.modules if m.split('.')[0] == 'torch' or "
              "(m.startswith('nepf_core.') and m != 'nepf_core.limits')); print(bad)")
    r = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr


def test_fit_says_the_working_size_and_render_follows_the_default(tmp_path, capsys):
    from nepf_core.cli import main

    data = synth_dir() / "dtu"
    run = tmp_path / "run"
    assert main(["fit", str(data), "--out", str(run), "--config", "tiny", "--iters", "2", "--device", "cpu",
                 "--no-export", "--max-side", "20", "--holdout-every", "0"]) == 0
    out = capsys.readouterr()
    text = out.out + out.err
    # 40x32 -> long side 20: 20x16; 8 views x 20 x 16 x 12 bytes = 30,720 B
    assert "data: 8 views at 20x16 px (long side at most 20 px; --max-side 0: full size), 0.00 GB of images" in text
    assert main(["render", str(run), "--cameras", str(data), "--out", str(tmp_path / "r"), "--device", "cpu",
                 "--stride", "4"]) == 0
    assert "rendered 8 views at 40x32 px (long side at most 800 px" in capsys.readouterr().out   # smaller: unchanged
    assert main(["render", str(run), "--cameras", str(data), "--out", str(tmp_path / "r0"), "--device", "cpu",
                 "--stride", "4", "--max-side", "0"]) == 0
    assert "rendered 8 views at 40x32 px (full resolution)" in capsys.readouterr().out


def test_a_dataset_over_the_cap_is_refused_naming_the_cap(tmp_path, capsys, monkeypatch):
    import nepf_core.limits
    from nepf_core.cli import main

    data = synth_dir() / "dtu"   # 8 views x 40 x 32 = 10,240 pixels
    rc = main(["fit", str(data), "--out", str(tmp_path / "a"), "--config", "tiny", "--max-total-pixels", "10000"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "the 8 images hold 10,240 pixels in all, above the limit of 10,000 decoded pixels" in err
    assert "the cap is --max-total-pixels 10,000 (default: the service's NEPF_MAX_TOTAL_PIXELS)" in err
    assert not (tmp_path / "a" / "checkpoints").exists()   # refused before any training
    # the default cap is the shared constant (lowered here: a real 400 Mpx dataset is too big for a test)
    monkeypatch.setattr(nepf_core.limits, "MAX_TOTAL_PIXELS", 5000)
    assert main(["fit", str(data), "--out", str(tmp_path / "b"), "--config", "tiny"]) == 2
    assert "the cap is --max-total-pixels 5,000" in capsys.readouterr().err


def test_a_negative_side_is_refused(tmp_path, capsys):
    from nepf_core.cli import main

    assert main(["fit", str(synth_dir() / "dtu"), "--out", str(tmp_path / "a"), "--max-side", "-1"]) == 2
    assert "max_side" in capsys.readouterr().err
