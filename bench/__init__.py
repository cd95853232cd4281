"""NePF benchmarks (not part of the installed library).

* ``python -m bench run ...``: error-against-time benchmark harness (:mod:`bench.run`), one
  training run per (scene, config, variant, repeat) in its own subprocess, then
  ``results.json``, ``table.md`` and ``error_vs_time_<scene>.png`` (:mod:`bench.report`).
* ``python -m bench report DIR``: rebuild ``table.md`` and the plots from ``DIR/results.json``.
* ``python -m bench.api_pollers``: the job service under many pollers (docs/SERVICE.md).

See ``bench/README.md`` for the protocol and the exact commands, ``bench/RESULTS.md`` for the
current numbers.
"""
