"""The ``Content-Disposition`` of an artifact download: ``attachment`` with the name
``<job name>-<artifact>`` (RFC 6266), an ASCII ``filename`` for every client and ``filename*``
(RFC 8187, UTF-8) for the exact name.

Why both parameters: RFC 6266 §4.3 lets a client prefer ``filename*`` and fall back to
``filename`` when it does not know it; ``filename`` must be a quoted ISO-8859-1 string in
practice ASCII (§5, the RFC's own advice), so a job called ``Kürbis "groß"`` gets
``filename="Kurbis _gro__-asset.glb"`` and ``filename*=UTF-8''K%C3%BCrbis%20_gro%C3%9F_-asset.glb``.

The name: the job's name (else ``nepf-<first 8 characters of the id>``), ``-``, and the
artifact's path in the run folder with ``/`` written as ``-`` (``textures/orm.png`` ->
``textures-orm.png``), so two files of one job never share a name. Characters a file system or a
header cannot hold (``/ \\ : * ? " < > |``, controls) become ``_``; leading dots and spaces are
dropped (no hidden files); the result is at most :data:`MAX_NAME` characters, keeping the
artifact's extension.
"""

from __future__ import annotations

import re
import unicodedata
from typing import Optional
from urllib.parse import quote

__all__ = ["download_name", "content_disposition", "MAX_NAME"]

MAX_NAME = 200
"""Longest download name (characters); most file systems allow 255 bytes."""

_UNSAFE = re.compile(r'[\x00-\x1f\x7f/\\:*?"<>|]')
# a quoted string could hold more, but "%" (percent-decoded by some clients) and ";" (naive
# parameter splitting) are kept out
_NOT_ASCII_SAFE = re.compile(r"[^A-Za-z0-9 !#$&'()+,\-.=@\[\]^_`{}~]")
# RFC 8187 attr-char beyond alphanumerics ("-", ".", "_", "~" are always kept by quote())
_ATTR_CHAR_SAFE = "!#$&+^`|"


def download_name(job_name: Optional[str], job_id: str, artifact_path: str) -> str:
    """``<job name>-<artifact>`` made safe for a file name (module docstring)."""
    base = (job_name or "").strip() or f"nepf-{job_id[:8]}"
    name = _UNSAFE.sub("_", f"{base}-{artifact_path.replace('/', '-')}").lstrip(". ")
    if len(name) > MAX_NAME:
        stem, dot, ext = name.rpartition(".")
        keep = f".{ext}" if dot and len(ext) <= 16 else ""
        name = name[: MAX_NAME - len(keep)] + keep
    return name or "download"


def _ascii_fallback(name: str) -> str:
    """``name`` in printable ASCII: a letter with accents loses them (NFKD: ``ü`` -> ``u``), any
    other non-ASCII character (``日``, ``ß``) becomes ``_``, as does ASCII a quoted string may not hold."""
    out = []
    for c in name:
        base = unicodedata.normalize("NFKD", c).encode("ascii", "ignore").decode("ascii") if ord(c) > 127 else c
        out.append(base or "_")
    return _NOT_ASCII_SAFE.sub("_", "".join(out))


def content_disposition(job_name: Optional[str], job_id: str, artifact_path: str) -> str:
    """``attachment; filename="<ascii>"; filename*=UTF-8''<percent-encoded UTF-8>``."""
    name = download_name(job_name, job_id, artifact_path)
    fallback = _ascii_fallback(name)
    return f"attachment; filename=\"{fallback}\"; filename*=UTF-8''{quote(name, safe=_ATTR_CHAR_SAFE)}"
