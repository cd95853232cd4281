"""What the working resolution costs before training: load time and peak memory.

``python -m bench.load_cost DATASET --sides 540,800,1080,0`` loads ``DATASET`` once per side, each
in a fresh subprocess (so the peak RSS is that load's), and prints one JSON line per side:
``max_side``, working ``width x height``, views, decoded megapixels, load seconds, peak RSS MB.
A training step's cost does not depend on the resolution (a fixed number of rays per step), so
these and the held-out evaluation are what a larger working size costs on the CPU.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time


def _child(path: str, side: int) -> None:
    from nepf_core.data.detect import load_scene
    t0 = time.perf_counter()
    scene = load_scene(path, max_side=side or None)
    dt = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(json.dumps({"max_side": side, "width": scene.width, "height": scene.height, "views": scene.n_views,
                      "megapixels": round(scene.n_views * scene.width * scene.height / 1e6, 1),
                      "load_s": round(dt, 2), "peak_rss_mb": round(rss)}))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--sides", default="540,800,1080,0", help="comma-separated max sides (0: full size)")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child is not None:
        _child(a.dataset, a.child)
        return
    for side in (int(s) for s in a.sides.split(",")):
        out = subprocess.run([sys.executable, "-m", "bench.load_cost", a.dataset, "--child", str(side)],
                             capture_output=True, text=True, check=True)
        print(out.stdout.strip(), flush=True)


if __name__ == "__main__":
    main()
