"""NePF benchmarks.

* ``python -m bench run ...``: error-against-time benchmark harness (:mod:`bench.run`), one
  training run per (scene, config, variant, repeat) in its own subprocess, then
  ``results.json``, ``table.md`` and ``error_vs_time_<scene>.png`` (:mod:`bench.report`).
* ``python -m bench report DIR``: rebuild ``table.md`` and the plots from ``DIR/results.json``.
* ``python -m bench.baked_albedo RUN --scene SCENE``: albedo PSNR of an exported GLB's baked
  base-colour texture at the scene's held-out views.

See ``bench/README.md`` for the protocol and the exact commands.
"""
