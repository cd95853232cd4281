"""Where a ``fast`` step's time goes, and steps per second: ``python -m bench.profile_step``.

For each dataset folder (a scene's ``input/dtu`` or a real capture), at each torch thread count:

1. ``fit()`` with the ``fast`` preset for ``--steps`` steps under ``torch.profiler`` (CPU
   activities), held-out evaluation, sync-PSNR and checkpoints off; the table of the top ops by
   self CPU time (share of the total and calls per step);
2. ``fit()`` again without the profiler for ``--timed-steps`` steps: steps per second from the
   training records' ``wall_s`` after the first ``--warmup`` steps (the first steps include the
   occupancy grid's first update and the allocator's warm-up).

Prints Markdown (the tables of ``docs/FAST.md``) and writes ``--json``. Run it alone: two
benchmarks on a 2-core machine time each other. For a before/after comparison run this file
against the older checkout with ``PYTHONPATH=<that checkout>`` in the same session.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path


def _load(data_dir: str, max_side: int):
    from nepf_core.data.detect import load_scene
    return load_scene(data_dir, max_side=max_side)


OVERRIDES: dict = {}
"""``--override`` values for every fit of this process (section.field -> value)."""


def _config(steps: int):
    from nepf_core.jobs import build_config
    return build_config("fast", steps, {"train.eval_every_s": 0.0, "train.sync_every": 0,
                                        "train.checkpoint_every": 10 ** 9, "train.log_every": 10, **OVERRIDES})


def profile_table(scene, steps: int, top: int) -> list[dict]:
    """Top ``top`` ops by self CPU time over ``steps`` steps of ``fit()``."""
    import torch
    from nepf_core.train import fit

    with tempfile.TemporaryDirectory() as run:
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            fit(scene, run, _config(steps), device="cpu")
    events = prof.key_averages()
    total = sum(e.self_cpu_time_total for e in events)
    rows = sorted(events, key=lambda e: e.self_cpu_time_total, reverse=True)[:top]
    return [{"op": e.key, "share": e.self_cpu_time_total / total, "calls_per_step": e.count / steps,
             "self_ms_per_step": e.self_cpu_time_total / 1e3 / steps} for e in rows]


def steps_per_second(scene, steps: int, warmup: int) -> dict:
    """Training steps per second from the metrics records (after ``warmup`` steps)."""
    from nepf_core.train import fit

    with tempfile.TemporaryDirectory() as run:
        t0 = time.perf_counter()
        fit(scene, run, _config(steps), device="cpu")
        total_s = time.perf_counter() - t0
        recs = [json.loads(line) for line in (Path(run) / "metrics.jsonl").read_text().splitlines()]
    train = [r for r in recs if r.get("kind") == "train"]
    first = next(r for r in train if r["step"] >= warmup)
    last = train[-1]
    rate = (last["step"] - first["step"]) / max(last["wall_s"] - first["wall_s"], 1e-9)
    return {"steps": steps, "steps_per_s": rate, "s_per_step": 1.0 / rate, "fit_wall_s": total_s,
            "final_loss": last.get("loss"), "final_loss_r": last.get("loss_r")}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.profile_step", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", nargs="+", help="dataset folders (a scene's input/dtu, a capture)")
    p.add_argument("--max-side", type=int, default=0, help="working side for real captures (the fox: 540)")
    p.add_argument("--threads", default="1,2", help="comma-separated torch thread counts")
    p.add_argument("--steps", type=int, default=100, help="profiled steps")
    p.add_argument("--timed-steps", type=int, default=300, help="steps of the unprofiled timing run")
    p.add_argument("--warmup", type=int, default=50)
    p.add_argument("--top", type=int, default=12)
    p.add_argument("--no-profile", action="store_true", help="timing only")
    p.add_argument("--json", default=None)
    p.add_argument("--override", action="append", default=[], metavar="section.field=VALUE",
                   help="config override for every fit (JSON value), e.g. loss.w_material_evidence=1e-3")
    a = p.parse_args(argv)
    from bench.run import _parse_overrides
    OVERRIDES.update(_parse_overrides(a.override))

    import torch

    results = []
    for data in a.data:
        scene = _load(data, a.max_side)
        for threads in [int(t) for t in a.threads.split(",")]:
            torch.set_num_threads(threads)
            os.environ["OMP_NUM_THREADS"] = str(threads)
            row = {"data": data, "threads": threads, "timing": steps_per_second(scene, a.timed_steps, a.warmup)}
            if not a.no_profile:
                row["profile"] = profile_table(scene, a.steps, a.top)
            results.append(row)
            name = Path(data).parent.parent.name if Path(data).parent.name == "input" else Path(data).name
            t = row["timing"]
            print(f"\n### {name}, {threads} thread(s): {t['steps_per_s']:.2f} steps/s ({t['s_per_step']:.3f} s/step)\n")
            if "profile" in row:
                print("| op | share of CPU time | calls / step | self ms / step |\n|---|---|---|---|")
                for r in row["profile"]:
                    print(f"| `{r['op']}` | {100 * r['share']:.1f} % | {r['calls_per_step']:.1f} | "
                          f"{r['self_ms_per_step']:.1f} |")
    if a.json:
        Path(a.json).write_text(json.dumps({"torch": torch.__version__, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
