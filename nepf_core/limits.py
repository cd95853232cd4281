"""Default working side and decoded-pixel cap, shared by the CLI and the service (stdlib only).

One place for both: ``nepf fit`` / ``eval`` / ``render`` / ``relight`` use them as their defaults,
and the service's settings ``NEPF_DEFAULT_IMAGE_SIDE`` / ``NEPF_MAX_TOTAL_PIXELS``
(``api/settings.py``) take them as theirs. This module imports nothing, so the API reads it
without torch or the rest of the library (``nepf_core/__init__.py`` imports nothing either); it is
the one ``nepf_core`` module ``api/`` imports (``tests/test_cli_limits.py`` checks that).

Why these values:

* **800 px on the long side.** A step draws a fixed number of rays, so a larger working side
  buys no accuracy per step; it costs load time, memory (``3 x 4`` bytes of float32 RGB per
  pixel and view: 100 views at 800 x 600 hold 0.58 GB, at 4000 x 3000 14.4 GB) and held-out
  evaluation time. ``--max-side 0`` trains at full resolution.
* **400 million decoded pixels per dataset**, read from the image headers before anything is
  decoded (``nepf_core/data/budget.py``): at full resolution a run keeps 20 bytes per pixel
  (float32 RGB, the ray sampler's float16 copy, masks; docs/SERVICE.md, "Worker memory at the
  caps"), 8 GB at the cap, what a 16 GB machine holds beside the training. 100 twelve-megapixel
  photos (1.2 billion pixels, ~24 GB at full size) are refused with an error that names the cap
  instead of ending in an out-of-memory kill; ``--max-total-pixels 0`` lifts it. The cap counts
  full-size pixels whatever the working side, as the service does.
"""

DEFAULT_IMAGE_SIDE = 800
"""Working side (px, the long side) when none is asked (``nepf`` ``--max-side``, ``NEPF_DEFAULT_IMAGE_SIDE``)."""

MAX_TOTAL_PIXELS = 400_000_000
"""Decoded pixels of a dataset's images, all views together (``--max-total-pixels``, ``NEPF_MAX_TOTAL_PIXELS``)."""

BYTES_PER_PIXEL = 12
"""float32 linear RGB in memory (``Scene.images``), per pixel and view."""
