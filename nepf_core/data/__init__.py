"""Datasets: loaders for DTU/IDR/NeuS, NeRF-synthetic/Blender, nerfstudio, instant-ngp and COLMAP layouts.

This subpackage is torch-free on purpose: the service validates uploads with it
in a subprocess (``python -m nepf_core.data.validate``) without importing torch.
(``nepf_core.data.synth``, the synthetic scene maker, uses torch and is not exported here.)

The loaders are exported lazily (PEP 562), so ``import nepf_core.data`` stays cheap.
"""

from nepf_core.data.errors import DatasetError
from nepf_core.data.scene import Scene

_LAZY = {
    "load_scene": "nepf_core.data.detect",
    "detect_format": "nepf_core.data.detect",
    "resolve_dataset": "nepf_core.data.detect",
    "load_dtu": "nepf_core.data.dtu",
    "load_blender": "nepf_core.data.blender",
    "load_ingp": "nepf_core.data.ingp",
    "load_nerfstudio": "nepf_core.data.nerfstudio",
    "load_colmap": "nepf_core.data.colmap",
    "validate_dataset": "nepf_core.data.validate",
    "read_image": "nepf_core.data.images",
    "srgb_to_linear": "nepf_core.color",
    "linear_to_srgb": "nepf_core.color",
}

__all__ = ["DatasetError", "Scene", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'nepf_core.data' has no attribute {name!r}")
