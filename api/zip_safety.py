"""Zip checks for an uploaded dataset: what the archive declares is checked before anything is
extracted, and what extraction really produces is counted while it runs.

Before extracting (every failure is a 422 :class:`api.errors.ApiError` naming the entry):

* entry names: no zip-slip (``..``, absolute or drive paths), each folder or file name at most
  ``MAX_NAME_BYTES`` bytes, the whole path at most ``MAX_PATH_BYTES``, no name that is both a file
  and a folder (``ds/image`` and ``ds/image/000.png``), no duplicates (case-insensitive);
* layout: every entry's bytes (local header + name + extra + compressed data + data descriptor)
  lie before the central directory and overlap no other entry's. Entries that share one deflate
  stream are the "overlapping zip bomb": each one's compressed size looks honest, so only the
  layout gives them away;
* sizes: total declared uncompressed size <= ``NEPF_MAX_UNZIPPED_MB`` and
  <= ``NEPF_MAX_ZIP_RATIO`` x the zip's size on disk; per entry and in total, uncompressed <=
  ratio x compressed (the ratio caps apply above ``RATIO_FLOOR_BYTES``).

While extracting, the bytes written are counted against
``extraction_budget = min(NEPF_MAX_UNZIPPED_MB, max(ratio x zip size, RATIO_FLOOR_BYTES))``
and each entry against its declared size, because headers can lie.
"""

from __future__ import annotations

import errno
import os
import stat
import struct
import zipfile
import zlib
from pathlib import Path, PurePosixPath
from typing import BinaryIO, Optional

from .errors import ApiError
from jobstore.settings import Settings

MB = 1024 * 1024
#: one folder or file name: NAME_MAX of Linux, macOS and NTFS
MAX_NAME_BYTES = 255
#: one entry's whole relative path; leaves room under PATH_MAX (4096) for DATA_DIR/jobs/<id>/dataset/
MAX_PATH_BYTES = 1024
#: below this uncompressed total the ratio caps do not apply (a tiny zip of text compresses well)
RATIO_FLOOR_BYTES = 8 * MB

JUNK_PREFIXES = ("__MACOSX/",)
JUNK_NAMES = {".DS_Store", "Thumbs.db", "desktop.ini"}

LOCAL_HEADER = struct.Struct("<4s5H3L2H")   # 30 bytes: signature ... name length, extra length
LOCAL_SIGNATURE = b"PK\x03\x04"
DESCRIPTOR_SIGNATURE = b"PK\x07\x08"
ZIP64_EXTRA_ID = 0x0001
FLAG_ENCRYPTED = 0x1
FLAG_DATA_DESCRIPTOR = 0x8


def shown(name: str, limit: int = 80) -> str:
    """An entry name short enough for a message (a 5000-character path is cut in the middle)."""
    return name if len(name) <= limit else f"{name[:limit // 2]}...{name[-(limit // 2 - 3):]}"


def member_path(name: str) -> Optional[PurePosixPath]:
    """Normalised relative path of a zip entry, or raise (zip-slip, over-long names).
    None: the entry is skipped (a folder entry or OS junk such as ``__MACOSX/``)."""
    raw = name.replace("\\", "/")
    if raw.startswith("/") or (len(raw) > 1 and raw[1] == ":") or "\x00" in raw:
        raise ApiError(422, "zip_slip", f"zip entry {shown(name)!r} has an absolute path")
    parts = [p for p in raw.split("/") if p not in ("", ".")]
    if any(p == ".." for p in parts):
        raise ApiError(422, "zip_slip", f"zip entry {shown(name)!r} escapes the archive ('..')")
    if not parts or raw.endswith("/"):
        return None
    if raw.startswith(JUNK_PREFIXES) or parts[-1] in JUNK_NAMES or parts[-1].startswith("._"):
        return None
    for part in parts:
        n = len(part.encode("utf-8", "surrogatepass"))
        if n > MAX_NAME_BYTES:
            raise ApiError(422, "zip_name_too_long",
                           f"zip entry {shown(name)!r} has a folder or file name of {n} bytes "
                           f"({shown(part, 40)!r}); the limit is {MAX_NAME_BYTES}")
    total = len("/".join(parts).encode("utf-8", "surrogatepass"))
    if total > MAX_PATH_BYTES:
        raise ApiError(422, "zip_path_too_long",
                       f"zip entry {shown(name)!r} has a path of {total} bytes; the limit is {MAX_PATH_BYTES}")
    return PurePosixPath(*parts)


def check_file_folder_conflicts(paths: list[PurePosixPath]) -> None:
    """No path may be both a file and a folder of other entries (case-insensitive, like the
    duplicate check: the archive must extract the same way on any file system)."""
    folders = {"/".join(p.parts[:i]).lower() for p in paths for i in range(1, len(p.parts))}
    for p in paths:
        if str(p).lower() in folders:
            raise ApiError(422, "zip_path_conflict",
                           f"zip entry {shown(str(p))!r} is a file, but other entries put files inside "
                           "a folder of the same name")


def _has_zip64_extra(extra: bytes) -> bool:
    i = 0
    while i + 4 <= len(extra):
        tag, size = struct.unpack_from("<HH", extra, i)
        if tag == ZIP64_EXTRA_ID:
            return True
        i += 4 + size
    return False


def entry_span(fp: BinaryIO, info: zipfile.ZipInfo) -> tuple[int, int]:
    """``[start, end)`` byte range of one entry in the archive: its local header, name, extra
    field, compressed data and (flag bit 3) data descriptor, of 12/16 bytes, or 20/24 with zip64."""
    start = info.header_offset
    fp.seek(start)
    head = fp.read(LOCAL_HEADER.size)
    if len(head) < LOCAL_HEADER.size or head[:4] != LOCAL_SIGNATURE:
        raise ApiError(422, "corrupt_zip", f"zip entry {shown(info.filename)!r} has no local header "
                                           "where the central directory says")
    name_len, extra_len = LOCAL_HEADER.unpack(head)[-2:]
    fp.seek(start + LOCAL_HEADER.size + name_len)
    extra = fp.read(extra_len)
    end = start + LOCAL_HEADER.size + name_len + extra_len + info.compress_size
    if info.flag_bits & FLAG_DATA_DESCRIPTOR:
        fp.seek(end)
        signed = fp.read(4) == DESCRIPTOR_SIGNATURE
        end += (4 if signed else 0) + 4 + (16 if _has_zip64_extra(extra) else 8)
    return start, end


def check_layout(zf: zipfile.ZipFile, fp: BinaryIO, data_end: int) -> None:
    """Every entry lies in ``[0, data_end)`` (the central directory starts at ``data_end``) and
    no two entries' spans overlap."""
    spans = sorted((*entry_span(fp, info), info.filename) for info in zf.infolist())
    prev_end, prev_name = 0, None
    for start, end, name in spans:
        if end > data_end:
            raise ApiError(422, "corrupt_zip", f"zip entry {shown(name)!r} runs past the end of the "
                                               "archive's data")
        if prev_name is not None and start < prev_end:
            raise ApiError(422, "zip_overlap",
                           f"zip entries {shown(prev_name)!r} and {shown(name)!r} overlap in the archive "
                           "(entries that share data are a zip-bomb technique)")
        if end >= prev_end:
            prev_end, prev_name = end, name


def extraction_budget(settings: Settings, zip_bytes: int) -> int:
    """Most bytes the archive may expand to: ``min(cap, max(ratio x zip size, floor))``."""
    cap = int(settings.max_unzipped_mb * MB)
    return min(cap, max(int(settings.max_zip_ratio * zip_bytes), RATIO_FLOOR_BYTES))


def plan_members(zf: zipfile.ZipFile, settings: Settings,
                 zip_bytes: int) -> list[tuple[zipfile.ZipInfo, PurePosixPath]]:
    """The entries to extract, after the name, type and size checks (nothing written yet)."""
    cap = int(settings.max_unzipped_mb * MB)
    ratio = settings.max_zip_ratio
    members: list[tuple[zipfile.ZipInfo, PurePosixPath]] = []
    seen: set[str] = set()
    total = total_compressed = 0
    for info in zf.infolist():
        mode = info.external_attr >> 16
        ftype = stat.S_IFMT(mode) if info.create_system == 3 else 0
        if ftype == stat.S_IFLNK:
            raise ApiError(422, "zip_symlink", f"zip entry {shown(info.filename)!r} is a symbolic link")
        if ftype and ftype not in (stat.S_IFREG, stat.S_IFDIR):
            raise ApiError(422, "zip_special_file", f"zip entry {shown(info.filename)!r} is not a regular file")
        rel = member_path(info.filename)
        if rel is None:
            continue
        if info.flag_bits & FLAG_ENCRYPTED:
            raise ApiError(422, "zip_encrypted", f"zip entry {shown(info.filename)!r} is encrypted")
        key = str(rel).lower()
        if key in seen:
            raise ApiError(422, "zip_duplicate", f"zip has two entries named {shown(str(rel))!r}")
        seen.add(key)
        total += info.file_size
        total_compressed += info.compress_size
        if total > cap:
            raise ApiError(422, "zip_bomb", f"zip expands to more than {settings.max_unzipped_mb:g} MB "
                                            "(NEPF_MAX_UNZIPPED_MB)")
        if info.file_size > MB and info.file_size > ratio * max(info.compress_size, 1):
            raise ApiError(422, "zip_bomb", f"zip entry {shown(str(rel))!r} has a compression ratio above "
                                            f"{ratio:g} (NEPF_MAX_ZIP_RATIO)")
        members.append((info, rel))
    if total > extraction_budget(settings, zip_bytes):
        raise ApiError(422, "zip_bomb",
                       f"zip declares {total / MB:.1f} MB uncompressed from {zip_bytes / MB:.2f} MB on disk, "
                       f"more than {ratio:g} times its size (NEPF_MAX_ZIP_RATIO)")
    if total > RATIO_FLOOR_BYTES and total > ratio * max(total_compressed, 1):
        raise ApiError(422, "zip_bomb", f"zip has a total compression ratio above {ratio:g} (NEPF_MAX_ZIP_RATIO)")
    if not members:
        raise ApiError(422, "empty_zip", "the zip archive contains no files")
    check_file_folder_conflicts([rel for _, rel in members])
    return members


def _write_error(rel: PurePosixPath, exc: OSError) -> ApiError:
    """An OS error while writing an entry; ``strerror`` only, never the server path."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return ApiError(507, "insufficient_storage", "the server ran out of disk space extracting the upload")
    return ApiError(422, "zip_unextractable",
                    f"zip entry {shown(str(rel))!r} cannot be extracted: {exc.strerror or type(exc).__name__}")


def extract_members(zf: zipfile.ZipFile, members: list[tuple[zipfile.ZipInfo, PurePosixPath]],
                    dest: Path, budget: int) -> None:
    """Write the members under ``dest`` (which must not exist) with ``O_EXCL|O_NOFOLLOW``,
    counting the bytes really produced against each declared size and ``budget``."""
    dest.mkdir(parents=True)
    root = dest.resolve()
    written = 0
    for info, rel in members:
        target = root.joinpath(*rel.parts)
        if root not in target.parents:
            raise ApiError(422, "zip_slip", f"zip entry {shown(info.filename)!r} escapes the archive")
        n = 0
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
            with os.fdopen(fd, "wb") as out, zf.open(info) as src:
                while chunk := src.read(MB):
                    n += len(chunk)
                    written += len(chunk)
                    if n > info.file_size:
                        raise ApiError(422, "zip_bomb",
                                       f"zip entry {shown(str(rel))!r} expands beyond its declared size")
                    if written > budget:
                        raise ApiError(422, "zip_bomb", f"zip expands beyond {budget / MB:.1f} MB, its "
                                                        "size cap (NEPF_MAX_ZIP_RATIO, NEPF_MAX_UNZIPPED_MB)")
                    out.write(chunk)
        except ApiError:
            raise
        except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
            raise ApiError(422, "corrupt_zip", f"zip entry {shown(str(rel))!r} cannot be extracted: {exc}") from None
        except OSError as exc:
            raise _write_error(rel, exc) from None


def check_and_extract_zip(zip_path: Path, dest: Path, settings: Settings) -> list[PurePosixPath]:
    """Check the archive, then extract it into ``dest``; returns the extracted relative paths."""
    try:
        zf = zipfile.ZipFile(zip_path)
    except zipfile.BadZipFile:
        raise ApiError(422, "not_a_zip", "the 'dataset' upload is not a zip archive") from None
    except OSError as exc:
        raise ApiError(422, "not_a_zip", f"the 'dataset' upload cannot be read as a zip: "
                                         f"{exc.strerror or type(exc).__name__}") from None
    zip_bytes = zip_path.stat().st_size
    with zf, open(zip_path, "rb") as fp:
        n_entries = len(zf.infolist())
        if n_entries > settings.max_zip_entries:
            raise ApiError(422, "too_many_entries", f"zip has {n_entries} entries; the cap is "
                                                    f"{settings.max_zip_entries} (NEPF_MAX_ZIP_ENTRIES)")
        check_layout(zf, fp, getattr(zf, "start_dir", zip_bytes))
        members = plan_members(zf, settings, zip_bytes)
        extract_members(zf, members, dest, extraction_budget(settings, zip_bytes))
    return [rel for _, rel in members]
