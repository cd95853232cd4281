"""``python -m bench run ...`` | ``python -m bench report DIR`` (see bench/README.md)."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: python -m bench {run,report} ...\n\n"
              "  run     run the benchmark (python -m bench run --help)\n"
              "  report  rebuild table.md and plots from RESULTS_DIR/results.json\n\n"
              "See bench/README.md.")
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    if cmd == "run":
        from bench.run import main as run_main
        return run_main(rest)
    if cmd == "report":
        from bench.report import main as report_main
        return report_main(rest)
    print(f"unknown command {cmd!r}: use run or report", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
