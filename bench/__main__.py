"""``python -m bench run ...`` | ``python -m bench report DIR`` | ``python -m bench oracle SCENE...`` | ``python -m bench materials ...`` (see bench/README.md)."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: python -m bench {run,report,oracle,materials} ...\n\n"
              "  run     run the benchmark (python -m bench run --help)\n"
              "  report  rebuild table.md and plots from RESULTS_DIR/results.json\n"
              "  oracle  relight PSNR of the ground truth shaded with our BSDF (python -m bench oracle --help)\n"
              "  materials  the materials suite: fast on six scenes, relight gap table (python -m bench materials --help)\n\n"
              "See bench/README.md.")
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    if cmd == "run":
        from bench.run import main as run_main
        return run_main(rest)
    if cmd == "report":
        from bench.report import main as report_main
        return report_main(rest)
    if cmd == "materials":
        from bench.materials import main as materials_main
        return materials_main(rest)
    if cmd == "oracle":
        from bench.oracle import main as oracle_main
        return oracle_main(rest)
    print(f"unknown command {cmd!r}: use run, report, oracle or materials", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
