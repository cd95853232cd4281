"""Upload safety: stream the multipart body to disk under a cap, check the zip, extract it
safely, guard against image bombs, then validate the dataset in a subprocess.

Every check raises :class:`api.errors.ApiError` (4xx with a specific code and message); the
caller deletes the staging folder on any error, so a rejected upload leaves nothing behind.

Nothing here imports ``nepf_core``: the loader runs as ``python -m nepf_core.data.validate``.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
import subprocess
import sys
import zipfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import AsyncIterator, Optional

from PIL import Image, UnidentifiedImageError
from python_multipart.multipart import MultipartParser, parse_options_header

from .errors import ApiError
from .settings import Settings

REPO_ROOT = Path(__file__).resolve().parent.parent
MB = 1024 * 1024
MAX_CONFIG_BYTES = 64 * 1024

#: image formats the core's loader reads (``nepf_core.data.images.read_image``): suffix -> Pillow format
IMAGE_FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}
#: image suffixes we recognise but the loader does not read: rejected with a clear message
OTHER_IMAGE_SUFFIXES = {".tif", ".tiff", ".bmp", ".gif", ".webp", ".heic", ".heif", ".exr", ".hdr",
                        ".jp2", ".tga", ".ppm", ".pgm", ".avif", ".jxl", ".dng", ".raw", ".cr2"}
JUNK = ("__MACOSX/",)
JUNK_NAMES = {".DS_Store", "Thumbs.db", "desktop.ini"}


@dataclass
class ReceivedUpload:
    zip_path: Optional[Path] = None
    zip_bytes: int = 0
    config_raw: Optional[bytes] = None
    sha256: str = ""
    fields: list = field(default_factory=list)


# --------------------------------------------------------------------------- multipart
async def receive_multipart(stream: AsyncIterator[bytes], content_type: str, staging: Path,
                            max_bytes: int) -> ReceivedUpload:
    """Parse ``multipart/form-data`` from ``stream``; write the ``dataset`` part to
    ``staging/upload.zip`` as it arrives, abort with 413 past ``max_bytes``."""
    ctype, params = parse_options_header(content_type or "")
    if ctype != b"multipart/form-data" or b"boundary" not in params:
        raise ApiError(415, "unsupported_media_type",
                       "POST /jobs takes multipart/form-data with a 'dataset' .zip file part")
    boundary = params[b"boundary"]
    out = ReceivedUpload()
    h = hashlib.sha256()
    state: dict = {"headers": {}, "hfield": b"", "hvalue": b"", "name": None, "is_file": False,
                   "sink": None, "cfg": bytearray(), "error": None}

    def on_part_begin():
        state["headers"] = {}
        state["name"] = None
        state["sink"] = None

    def on_header_field(data, start, end):
        state["hfield"] += data[start:end]

    def on_header_value(data, start, end):
        state["hvalue"] += data[start:end]

    def on_header_end():
        state["headers"][state["hfield"].lower()] = state["hvalue"]
        state["hfield"] = b""
        state["hvalue"] = b""

    def on_headers_finished():
        disp = state["headers"].get(b"content-disposition", b"")
        _, p = parse_options_header(disp)
        name = p.get(b"name", b"").decode("utf-8", "replace")
        state["name"] = name
        state["is_file"] = b"filename" in p
        out.fields.append(name)
        if name == "dataset":
            if out.zip_path is not None:
                state["error"] = ApiError(422, "duplicate_field", "the 'dataset' part appears twice")
                return
            out.zip_path = staging / "upload.zip"
            state["sink"] = open(out.zip_path, "wb")

    def on_part_data(data, start, end):
        if state["error"] is not None:
            return
        chunk = data[start:end]
        if state["name"] == "dataset":
            out.zip_bytes += len(chunk)
            if out.zip_bytes > max_bytes:
                state["error"] = ApiError(
                    413, "upload_too_large",
                    f"upload exceeds the {max_bytes / MB:g} MB cap (NEPF_MAX_UPLOAD_MB)")
                return
            h.update(chunk)
            state["sink"].write(chunk)
        elif state["name"] == "config":
            state["cfg"] += chunk
            if len(state["cfg"]) > MAX_CONFIG_BYTES:
                state["error"] = ApiError(413, "config_too_large", "the 'config' part exceeds 64 KiB")

    def on_part_end():
        if state["sink"] is not None:
            state["sink"].close()
            state["sink"] = None
        if state["name"] == "config":
            out.config_raw = bytes(state["cfg"])

    parser = MultipartParser(boundary, callbacks={
        "on_part_begin": on_part_begin, "on_part_data": on_part_data, "on_part_end": on_part_end,
        "on_header_field": on_header_field, "on_header_value": on_header_value,
        "on_header_end": on_header_end, "on_headers_finished": on_headers_finished})
    try:
        async for chunk in stream:
            if not chunk:
                continue
            parser.write(chunk)
            if state["error"] is not None:
                raise state["error"]
        parser.finalize()
    except ApiError:
        raise
    except Exception as exc:  # noqa: BLE001 - malformed multipart framing
        raise ApiError(400, "bad_multipart", f"malformed multipart body: {exc}") from None
    finally:
        if state["sink"] is not None:
            state["sink"].close()
    if out.zip_path is None:
        raise ApiError(422, "missing_dataset", "the multipart body has no 'dataset' file part")
    h.update(b"\0config\0" + (out.config_raw or b""))
    out.sha256 = h.hexdigest()
    return out


# --------------------------------------------------------------------------- config
def parse_config(raw: Optional[bytes], settings: Settings) -> dict:
    """The job config: ``{"preset", "iters", "time_budget_s", "name"}`` (all optional)."""
    cfg: dict = {}
    if raw is not None and raw.strip():
        try:
            cfg = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ApiError(422, "invalid_config", f"'config' is not valid JSON: {exc}") from None
        if not isinstance(cfg, dict):
            raise ApiError(422, "invalid_config", "'config' must be a JSON object")
    allowed = {"preset", "iters", "time_budget_s", "name"}
    extra = sorted(set(cfg) - allowed)
    if extra:
        raise ApiError(422, "invalid_config",
                       f"unknown config key(s) {extra}; allowed: {sorted(allowed)}")
    preset = cfg.get("preset", settings.default_preset)
    if preset not in ("fast", "paper", "tiny"):
        raise ApiError(422, "invalid_config", "config.preset must be one of fast, paper, tiny")
    iters = cfg.get("iters")
    if iters is not None and (isinstance(iters, bool) or not isinstance(iters, int)
                              or not 1 <= iters <= 10_000_000):
        raise ApiError(422, "invalid_config", "config.iters must be an integer in [1, 10000000]")
    budget = cfg.get("time_budget_s")
    if budget is not None and (isinstance(budget, bool) or not isinstance(budget, (int, float))
                               or not 0 < float(budget) <= 30 * 24 * 3600 or budget != budget):
        raise ApiError(422, "invalid_config", "config.time_budget_s must be a number in (0, 2592000]")
    name = cfg.get("name")
    if name is not None and (not isinstance(name, str) or len(name) > 200 or not name.isprintable()):
        raise ApiError(422, "invalid_config", "config.name must be a printable string of at most 200 characters")
    return {"preset": preset, "iters": iters,
            "time_budget_s": float(budget) if budget is not None else None, "name": name}


# --------------------------------------------------------------------------- zip
def _safe_member_path(name: str) -> Optional[PurePosixPath]:
    """Normalised relative path of a zip member, or raise on zip-slip. None: skip (junk/dir)."""
    raw = name.replace("\\", "/")
    if raw.startswith("/") or (len(raw) > 1 and raw[1] == ":") or "\x00" in raw:
        raise ApiError(422, "zip_slip", f"zip entry {name!r} has an absolute path")
    parts = [p for p in raw.split("/") if p not in ("", ".")]
    if any(p == ".." for p in parts):
        raise ApiError(422, "zip_slip", f"zip entry {name!r} escapes the archive ('..')")
    if not parts or raw.endswith("/"):
        return None
    if raw.startswith(JUNK) or parts[-1] in JUNK_NAMES or parts[-1].startswith("._"):
        return None
    return PurePosixPath(*parts)


def check_and_extract_zip(zip_path: Path, dest: Path, settings: Settings) -> list[PurePosixPath]:
    """Check the archive against the caps and extract it into ``dest`` (which must not exist)."""
    try:
        zf = zipfile.ZipFile(zip_path)
    except zipfile.BadZipFile:
        raise ApiError(422, "not_a_zip", "the 'dataset' upload is not a zip archive") from None
    except OSError as exc:
        raise ApiError(422, "not_a_zip", f"the 'dataset' upload cannot be read as a zip: {exc}") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > settings.max_zip_entries:
            raise ApiError(422, "too_many_entries",
                           f"zip has {len(infos)} entries; the cap is {settings.max_zip_entries} "
                           "(NEPF_MAX_ZIP_ENTRIES)")
        max_total = int(settings.max_unzipped_mb * MB)
        members: list[tuple[zipfile.ZipInfo, PurePosixPath]] = []
        seen: set[str] = set()
        total = 0
        total_c = 0
        for info in infos:
            mode = info.external_attr >> 16
            ftype = stat.S_IFMT(mode) if info.create_system == 3 else 0
            if ftype == stat.S_IFLNK:
                raise ApiError(422, "zip_symlink", f"zip entry {info.filename!r} is a symbolic link")
            if ftype and ftype not in (stat.S_IFREG, stat.S_IFDIR):
                raise ApiError(422, "zip_special_file", f"zip entry {info.filename!r} is not a regular file")
            rel = _safe_member_path(info.filename)
            if rel is None:
                continue
            if info.flag_bits & 0x1:
                raise ApiError(422, "zip_encrypted", f"zip entry {info.filename!r} is encrypted")
            key = str(rel).lower()
            if key in seen:
                raise ApiError(422, "zip_duplicate", f"zip has two entries named {str(rel)!r}")
            seen.add(key)
            total += info.file_size
            total_c += info.compress_size
            if total > max_total:
                raise ApiError(422, "zip_bomb",
                               f"zip expands to more than {settings.max_unzipped_mb:g} MB "
                               "(NEPF_MAX_UNZIPPED_MB)")
            if info.file_size > MB and info.file_size > settings.max_zip_ratio * max(info.compress_size, 1):
                raise ApiError(422, "zip_bomb",
                               f"zip entry {str(rel)!r} has a compression ratio above "
                               f"{settings.max_zip_ratio:g} (NEPF_MAX_ZIP_RATIO)")
            members.append((info, rel))
        if total > 8 * MB and total > settings.max_zip_ratio * max(total_c, 1):
            raise ApiError(422, "zip_bomb", f"zip has a total compression ratio above {settings.max_zip_ratio:g}")
        if not members:
            raise ApiError(422, "empty_zip", "the zip archive contains no files")
        dest.mkdir(parents=True)
        root = dest.resolve()
        written = 0
        for info, rel in members:
            target = root.joinpath(*rel.parts)
            if root not in target.parents:
                raise ApiError(422, "zip_slip", f"zip entry {info.filename!r} escapes the archive")
            target.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
            n = 0
            try:
                with os.fdopen(fd, "wb") as out, zf.open(info) as src:
                    while True:
                        chunk = src.read(1 << 20)
                        if not chunk:
                            break
                        n += len(chunk)
                        written += len(chunk)
                        # headers can lie: enforce the caps on the bytes actually produced
                        if n > info.file_size or written > max_total:
                            raise ApiError(422, "zip_bomb",
                                           f"zip entry {str(rel)!r} expands beyond its declared size")
                        out.write(chunk)
            except ApiError:
                raise
            except (zipfile.BadZipFile, zlib_error(), OSError, EOFError, NotImplementedError) as exc:
                raise ApiError(422, "corrupt_zip", f"zip entry {str(rel)!r} cannot be extracted: {exc}") from None
        return [rel for _, rel in members]


def zlib_error():
    import zlib
    return zlib.error


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
        except Image.DecompressionBombError as exc:
            raise bad("image_bomb", str(exc)) from None
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


def validate_dataset(root: Path, settings: Settings) -> dict:
    """Run the core's validator in a subprocess (the API never imports nepf_core)."""
    py = settings.python_executable or sys.executable
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env.setdefault("OMP_NUM_THREADS", "1")
    try:
        proc = subprocess.run([py, "-m", "nepf_core.data.validate", str(root)], capture_output=True,
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
        errors = [e for e in data.get("errors") or [] if isinstance(e, dict)]
        if not errors:
            errors = [{"code": "invalid_dataset", "message": "the dataset is invalid", "file": None, "view": None}]
        first = errors[0]
        where = ", ".join(x for x in (f"file {first.get('file')}" if first.get("file") else "",
                                      f"view {first.get('view')}" if first.get("view") is not None else "") if x)
        msg = f"[{where}] {first.get('message')}" if where else str(first.get("message"))
        return_err = ApiError(422, str(first.get("code") or "invalid_dataset"), msg, errors=errors)
        raise return_err
    tail = proc.stderr.decode("utf-8", "replace").strip().splitlines()[-3:]
    if "MemoryError" in " ".join(tail):
        raise ApiError(422, "dataset_too_large",
                       f"validating the dataset needed more than {settings.validate_max_memory_mb} MB "
                       "(NEPF_VALIDATE_MAX_MEMORY_MB)")
    raise ApiError(500, "validator_failed",
                   f"the dataset validator failed (exit {proc.returncode}): {' | '.join(tail)}")
