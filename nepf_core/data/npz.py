"""``.npz`` files of a dataset, read member by member with every ``.npy`` header checked first.

Why not ``numpy.load``: an ``.npz`` is a zip of ``.npy`` arrays, and ``np.load(...)[key]``
allocates whatever the member's header declares before reading a byte of data. A 3 MB camera
file holding a compressed ``zeros(3 * 2**27)`` member made the worker allocate 3.85 GB (the
upload's zip-ratio checks cannot see the npz's own compression), and a header declaring
``(100000, 100000)`` float64 ended in ``MemoryError``. Here:

* nothing is read but the zip's directory until a loader asks for a member by name, so a
  member no loader needs (``junk``, ``camera_mat_inv_3``) is never decompressed;
* a member's header (``numpy.lib.format.read_magic`` and ``read_array_header_1_0`` /
  ``_2_0`` on the zip member stream) is checked before its data: the dtype must hold real
  numbers (float or integer: complex, object, string, bool, structured, date dtypes are refused
  with ``unsupported_dtype``), the shape must be one the loader expects (``invalid_camera``
  otherwise), and the declared size must be at most :data:`MAX_ARRAY_BYTES`
  (``array_too_large``);
* then exactly the declared bytes are read (a short member is ``unreadable_cameras``).

Errors are :class:`~nepf_core.data.errors.DatasetError` naming the file and the member; the
view index is the caller's (it knows which view a member belongs to).
"""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np
from numpy.lib import format as npy_format

from nepf_core.data.errors import DatasetError

#: the most bytes one array of a dataset may declare (64 MiB; a camera matrix takes 128 bytes)
MAX_ARRAY_BYTES = 64 * 1024 * 1024
#: the most members one ``.npz`` may list (a 1,000-view capture with six matrices per view: 6,000)
MAX_NPZ_MEMBERS = 100_000
#: dtype kinds that hold real numbers: float, signed and unsigned integer
REAL_KINDS = "fiu"
#: the largest ``.npy`` header read (numpy's own default)
MAX_HEADER_BYTES = 10_000
_ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")


class NpzArrays:
    """An open ``.npz`` (use as a context manager): :attr:`names` (member names without
    ``.npy``), :meth:`read` one member under its checks. ``label`` names the file in errors."""

    def __init__(self, path: Path, label: str, code: str = "unreadable_cameras") -> None:
        self.label, self.code = label, code
        try:
            with open(path, "rb") as f:
                magic = f.read(4)
        except OSError as e:
            raise self._error(f"cannot read the file: {e.strerror}") from None
        # numpy.load would unpickle anything that is not a zip or .npy: test the zip magic first
        if magic not in _ZIP_MAGICS or not zipfile.is_zipfile(path):
            raise self._error("not a valid .npz file (expected a zip of .npy arrays, as numpy.savez writes)")
        try:
            self._zip = zipfile.ZipFile(path)
            infos = self._zip.infolist()
        except (OSError, zipfile.BadZipFile, ValueError, EOFError) as e:
            raise self._error(f"not a valid .npz file ({type(e).__name__})") from None
        if len(infos) > MAX_NPZ_MEMBERS:
            self.close()
            raise self._error(f"{len(infos)} members, over the limit of {MAX_NPZ_MEMBERS}")
        self._members: dict[str, zipfile.ZipInfo] = {}
        for info in infos:
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            if name in self._members:
                self.close()
                raise self._error(f"the member {name!r} appears twice; which one counts would be a guess")
            self._members[name] = info

    # ---------------------------------------------------------------- plumbing
    def __enter__(self) -> "NpzArrays":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._zip.close()

    def _error(self, message: str, code: str | None = None, view: int | None = None) -> DatasetError:
        return DatasetError(message, file=self.label, view=view, code=code or self.code)

    @property
    def names(self) -> list[str]:
        """Member names, ``.npy`` dropped (as ``numpy.load(...).files``)."""
        return list(self._members)

    def __contains__(self, name: str) -> bool:
        return name in self._members

    # ---------------------------------------------------------------- reading
    def header(self, name: str, view: int | None = None) -> tuple[tuple[int, ...], bool, np.dtype]:
        """``(shape, fortran_order, dtype)`` from the member's ``.npy`` header (no data read)."""
        with self._zip.open(self._members[name]) as f:
            return self._read_header(f, name, view)

    def _read_header(self, f, name: str, view: int | None):
        try:
            version = npy_format.read_magic(f)
            if version == (1, 0):
                return npy_format.read_array_header_1_0(f, max_header_size=MAX_HEADER_BYTES)
            if version == (2, 0):
                return npy_format.read_array_header_2_0(f, max_header_size=MAX_HEADER_BYTES)
            raise ValueError(f".npy format version {version[0]}.{version[1]} is not supported (1.0 or 2.0)")
        except (ValueError, OSError, EOFError, zipfile.BadZipFile, SyntaxError) as e:
            raise self._error(f"{name}: not a readable .npy array ({_short(e)})", view=view) from None

    def read(self, name: str, shapes: tuple[tuple[int, ...], ...] | None, *, view: int | None = None) -> np.ndarray:
        """The member ``name`` as a float64 array, after its header passed the checks of the module
        docstring; ``shapes``: the shapes the caller accepts (None: any, under the byte bound)."""
        with self._zip.open(self._members[name]) as f:
            shape, fortran, dtype = self._read_header(f, name, view)
            check_array_header(name, shape, dtype, shapes, file=self.label, view=view)
            nbytes = math.prod(shape) * dtype.itemsize
            try:
                data = f.read(nbytes)
            except (OSError, EOFError, zipfile.BadZipFile, ValueError) as e:
                raise self._error(f"{name}: cannot read its data ({_short(e)})", view=view) from None
        if len(data) != nbytes:
            raise self._error(f"{name}: its header declares {nbytes} bytes of data, the member holds "
                              f"{len(data)}", view=view)
        arr = np.frombuffer(data, dtype=dtype).reshape(shape, order="F" if fortran else "C")
        return arr.astype(np.float64)


def check_array_header(name: str, shape: tuple[int, ...], dtype: np.dtype,
                       shapes: tuple[tuple[int, ...], ...] | None, *, file: str, view: int | None) -> None:
    """Refuse a member from its header alone: a dtype that does not hold real numbers
    (``unsupported_dtype``), a shape not in ``shapes`` (``invalid_camera``), a declared size over
    :data:`MAX_ARRAY_BYTES` (``array_too_large``)."""
    if dtype.kind not in REAL_KINDS or dtype.fields is not None or dtype.subdtype is not None:
        raise DatasetError(f"{name} has dtype {dtype}: only real numbers (float or integer arrays) are "
                           "accepted; complex, object, string, bool and structured arrays are refused",
                           file=file, view=view, code="unsupported_dtype")
    if shapes is not None and tuple(shape) not in shapes:
        want = " or ".join("x".join(map(str, s)) for s in shapes)
        raise DatasetError(f"{name} has shape {tuple(shape)}, expected {want}", file=file, view=view,
                           code="invalid_camera")
    nbytes = math.prod(shape) * dtype.itemsize
    if nbytes > MAX_ARRAY_BYTES:
        raise DatasetError(f"{name} declares {nbytes} bytes ({tuple(shape)} of {dtype}), over the limit of "
                           f"{MAX_ARRAY_BYTES} bytes per array", file=file, view=view, code="array_too_large")


def _short(e: BaseException) -> str:
    """An exception's text, cut: a parser's message can quote a whole header back."""
    text = str(e).strip() or type(e).__name__
    return text if len(text) <= 200 else text[:200] + "..."
