"""NePF: Neural Photon Field, single-stage inverse rendering (library)."""

__version__ = "0.1.0"
