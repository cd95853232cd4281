"""Relighting a recovered asset under user point lights (``nepf relight``), its scores against
ground truth (``nepf eval --relight``) and the export's canonical relit previews.

* :mod:`.lights`: ``lights.json``, the change of frame, the canonical preview lights;
* :mod:`.tracing`: sphere tracing (primary hits, shadow rays);
* :mod:`.shade`: the BSDF under point lights, with shadows;
* :mod:`.render`: whole views (model surfaces or a sphere-traced FieldQuery);
* :mod:`.run`: ``nepf relight`` on a run folder, and the files it writes;
* :mod:`.metrics`: relight / albedo PSNR (per-channel scale), material and normal errors;
* :mod:`.previews`: the export's three canonical relit previews.
"""
