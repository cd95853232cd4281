"""Upload safety: stream the multipart body to disk under a cap, check the zip and extract it
safely (:mod:`api.zip_safety`), guard against image bombs, then validate the dataset in a subprocess.

Every check raises :class:`api.errors.ApiError` (4xx with a specific code and message); the
caller deletes the staging folder on any error, so a rejected upload leaves nothing behind.

Nothing here imports ``nepf_core``: the loader runs as ``python -m nepf_core.data.validate``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import AsyncIterator, Optional

from PIL import Image, UnidentifiedImageError
from python_multipart.multipart import MultipartParser, parse_options_header

from .errors import ApiError
from jobstore.settings import Settings
from .zip_safety import MB

log = logging.getLogger("nepf.api")
REPO_ROOT = Path(__file__).resolve().parent.parent
MAX_CONFIG_BYTES = 64 * 1024

#: image formats the core's loader reads (``nepf_core.data.images.read_image``): suffix -> Pillow format
IMAGE_FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}
#: image suffixes we recognise but the loader does not read: rejected with a clear message
OTHER_IMAGE_SUFFIXES = {".tif", ".tiff", ".bmp", ".gif", ".webp", ".heic", ".heif", ".exr", ".hdr",
                        ".jp2", ".tga", ".ppm", ".pgm", ".avif", ".jxl", ".dng", ".raw", ".cr2"}


@dataclass
class ReceivedUpload:
    zip_path: Optional[Path] = None
    zip_bytes: int = 0
    config_raw: Optional[bytes] = None
    sha256: str = ""
    fields: list = field(default_factory=list)


# --------------------------------------------------------------------------- multipart
class _PartWriter:
    """python-multipart callbacks: the ``dataset`` part streams to ``staging/upload.zip`` (hashed,
    capped at ``max_bytes``), the ``config`` part is kept in memory (capped at 64 KiB). A
    problem is kept in ``error`` and raised by the reader between chunks."""

    def __init__(self, out: ReceivedUpload, staging: Path, max_bytes: int) -> None:
        self.out, self.staging, self.max_bytes = out, staging, max_bytes
        self.sha = hashlib.sha256()
        self.headers: dict = {}
        self.hfield, self.hvalue = b"", b""
        self.name: Optional[str] = None
        self.sink = None
        self.cfg = bytearray()
        self.error: Optional[ApiError] = None

    def callbacks(self) -> dict:
        return {"on_part_begin": self.on_part_begin, "on_part_data": self.on_part_data,
                "on_part_end": self.on_part_end, "on_header_field": self.on_header_field,
                "on_header_value": self.on_header_value, "on_header_end": self.on_header_end,
                "on_headers_finished": self.on_headers_finished}

    def on_part_begin(self):
        self.headers, self.name, self.sink = {}, None, None

    def on_header_field(self, data, start, end):
        self.hfield += data[start:end]

    def on_header_value(self, data, start, end):
        self.hvalue += data[start:end]

    def on_header_end(self):
        self.headers[self.hfield.lower()] = self.hvalue
        self.hfield, self.hvalue = b"", b""

    def on_headers_finished(self):
        _, p = parse_options_header(self.headers.get(b"content-disposition", b""))
        self.name = p.get(b"name", b"").decode("utf-8", "replace")
        self.out.fields.append(self.name)
        if self.name == "dataset":
            if self.out.zip_path is not None:
                self.error = ApiError(422, "duplicate_field", "the 'dataset' part appears twice")
                return
            self.out.zip_path = self.staging / "upload.zip"
            self.sink = open(self.out.zip_path, "wb")

    def on_part_data(self, data, start, end):
        if self.error is not None:
            return
        chunk = data[start:end]
        if self.name == "dataset":
            self.out.zip_bytes += len(chunk)
            if self.out.zip_bytes > self.max_bytes:
                self.error = ApiError(413, "upload_too_large",
                                      f"upload exceeds the {self.max_bytes / MB:g} MB cap (NEPF_MAX_UPLOAD_MB)")
                return
            self.sha.update(chunk)
            self.sink.write(chunk)
        elif self.name == "config":
            self.cfg += chunk
            if len(self.cfg) > MAX_CONFIG_BYTES:
                self.error = ApiError(413, "config_too_large", "the 'config' part exceeds 64 KiB")

    def on_part_end(self):
        self.close()
        if self.name == "config":
            self.out.config_raw = bytes(self.cfg)

    def close(self):
        if self.sink is not None:
            self.sink.close()
            self.sink = None


async def receive_multipart(stream: AsyncIterator[bytes], content_type: str, staging: Path,
                            max_bytes: int) -> ReceivedUpload:
    """Parse ``multipart/form-data`` from ``stream``; write the ``dataset`` part to
    ``staging/upload.zip`` as it arrives, abort with 413 past ``max_bytes``."""
    ctype, params = parse_options_header(content_type or "")
    if ctype != b"multipart/form-data" or b"boundary" not in params:
        raise ApiError(415, "unsupported_media_type",
                       "POST /jobs takes multipart/form-data with a 'dataset' .zip file part")
    out = ReceivedUpload()
    parts = _PartWriter(out, staging, max_bytes)
    parser = MultipartParser(params[b"boundary"], callbacks=parts.callbacks())
    try:
        async for chunk in stream:
            if not chunk:
                continue
            parser.write(chunk)
            if parts.error is not None:
                raise parts.error
        parser.finalize()
    except ApiError:
        raise
    except Exception as exc:  # noqa: BLE001 - malformed multipart framing
        raise ApiError(400, "bad_multipart", f"malformed multipart body: {exc}") from None
    finally:
        parts.close()
    if out.zip_path is None:
        raise ApiError(422, "missing_dataset", "the multipart body has no 'dataset' file part")
    parts.sha.update(b"\0config\0" + (out.config_raw or b""))
    out.sha256 = parts.sha.hexdigest()
    return out


# --------------------------------------------------------------------------- zip
def dataset_root(extracted: Path) -> Path:
    """Descend through a single wrapping folder (``scan24.zip`` -> ``scan24/...``)."""
    root = extracted
    for _ in range(4):
        children = [p for p in root.iterdir()]
        if len(children) == 1 and children[0].is_dir():
            root = children[0]
        else:
            break
    return root


# --------------------------------------------------------------------------- images
def check_images(root: Path, members: list[PurePosixPath], settings: Settings) -> int:
    """Only loader formats; header-level pixel cap (image bomb); structural verify."""
    Image.MAX_IMAGE_PIXELS = settings.max_image_pixels
    n = 0
    for rel in members:
        suffix = rel.suffix.lower()
        if suffix in OTHER_IMAGE_SUFFIXES:
            raise ApiError(422, "unsupported_image_format",
                           f"{rel}: {suffix} images are not supported; use PNG or JPEG",
                           errors=[{"code": "unsupported_image_format", "file": str(rel), "view": None,
                                    "message": f"{suffix} images are not supported; use PNG or JPEG"}])
        fmt = IMAGE_FORMATS.get(suffix)
        if fmt is None:
            continue
        path = root.joinpath(*rel.parts)
        n += 1

        def bad(code: str, msg: str) -> ApiError:
            return ApiError(422, code, f"{rel}: {msg}",
                            errors=[{"code": code, "message": msg, "file": str(rel), "view": None}])
        try:
            with Image.open(path) as im:
                if im.format != fmt:
                    raise bad("image_format_mismatch", f"file is {im.format}, not {fmt} as its name says")
                w, h = im.size
                if w * h > settings.max_image_pixels:
                    raise bad("image_bomb", f"image is {w}x{h} = {w * h} pixels; the cap is "
                                            f"{settings.max_image_pixels} (NEPF_MAX_IMAGE_PIXELS)")
                im.verify()
        except ApiError:
            raise
        except Image.DecompressionBombError:   # Pillow's own limit (twice ours) names its number: state ours
            raise bad("image_bomb", f"image has more than {settings.max_image_pixels} pixels, the cap "
                                    "(NEPF_MAX_IMAGE_PIXELS)") from None
        except UnidentifiedImageError:
            raise bad("corrupt_image", "not a readable image (corrupt or wrong format)") from None
        except Exception as exc:  # noqa: BLE001 - Pillow raises many types for corrupt data
            raise bad("corrupt_image", f"corrupt image: {exc}") from None
    return n


# --------------------------------------------------------------------------- loader validation
def _limit_memory(mb: int):
    """Cap the validator's address space: a decoder bomb that slips past the header checks
    fails inside the subprocess instead of exhausting the API host."""
    if not mb or mb <= 0:
        return None

    def apply():
        import resource
        limit = int(mb) * MB
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    return apply


def validate_dataset(root: Path, settings: Settings, max_side: Optional[int] = None) -> dict:
    """Run the core's validator in a subprocess (the API imports no nepf_core module but the constants of nepf_core.limits).

    It checks the decoded-pixel cap ``NEPF_MAX_TOTAL_PIXELS`` from the image headers and
    reports the working size at ``max_side`` (default: what a job that asks none trains at,
    :meth:`Settings.job_max_side`)."""
    py = settings.python_executable or sys.executable
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env.setdefault("OMP_NUM_THREADS", "1")
    try:
        side = settings.job_max_side(None) if max_side is None else max_side
        cmd = [py, "-m", "nepf_core.data.validate", "--max-side", str(side),
               "--max-total-pixels", str(settings.max_total_pixels), str(root)]
        proc = subprocess.run(cmd, capture_output=True,
                              timeout=settings.validate_timeout_s, env=env, cwd=str(root), stdin=subprocess.DEVNULL,
                              preexec_fn=_limit_memory(settings.validate_max_memory_mb))
    except subprocess.TimeoutExpired:
        raise ApiError(422, "validation_timeout",
                       f"validating the dataset took longer than {settings.validate_timeout_s:g} s") from None
    out = proc.stdout.decode("utf-8", "replace").strip()
    data = None
    for line in reversed(out.splitlines()):   # last JSON line wins (tolerates stray prints)
        try:
            data = json.loads(line)
            break
        except json.JSONDecodeError:
            continue
    if proc.returncode == 0 and isinstance(data, dict) and data.get("ok") is True:
        return data
    if proc.returncode == 2 and isinstance(data, dict) and data.get("ok") is False:
        raise _dataset_error(data, settings)
    tail = proc.stderr.decode("utf-8", "replace").strip().splitlines()
    if "MemoryError" in " ".join(tail[-3:]):
        raise ApiError(422, "dataset_too_large", _memory_message(settings))
    # a bug (exit 3) or a crash: the traceback goes to the server's log, never into the answer
    log.error("dataset validator failed (exit %s):\n%s", proc.returncode, "\n".join(tail[-60:]))
    raise ApiError(500, "internal_error", "validating the dataset failed on an internal error; "
                                          "it is logged on the server")


def _memory_message(settings: Settings) -> str:
    return (f"validating the dataset needed more than {settings.validate_max_memory_mb} MB "
            "(NEPF_VALIDATE_MAX_MEMORY_MB)")


def _dataset_error(data: dict, settings: Settings) -> ApiError:
    """The 422 for the validator's ``{"ok": false, "errors": [...]}``: the first error's code and
    message (with the setting that sets a limit named), all of them in ``errors``."""
    errors = [e for e in data.get("errors") or [] if isinstance(e, dict)]
    if not errors:
        errors = [{"code": "invalid_dataset", "message": "the dataset is invalid", "file": None, "view": None}]
    first = errors[0]
    if first.get("code") == "too_many_pixels":
        first["message"] = f"{first.get('message')} (NEPF_MAX_TOTAL_PIXELS)"
    if first.get("code") == "dataset_too_large":
        first["message"] = _memory_message(settings)
    where = ", ".join(x for x in (f"file {first.get('file')}" if first.get("file") else "",
                                  f"view {first.get('view')}" if first.get("view") is not None else "") if x)
    msg = f"[{where}] {first.get('message')}" if where else str(first.get("message"))
    return ApiError(422, str(first.get("code") or "invalid_dataset"), msg, errors=errors)
