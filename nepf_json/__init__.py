"""The one JSON parser for every JSON document the service reads from a user: a job's ``config``
part (``api/job_config.py``), a dataset's ``transforms*.json`` (``nepf_core/data/blender.py``)
and a ``lights.json`` (``nepf_core/relight/lights.py``).

Why a package of its own: ``api/`` never imports ``nepf_core`` (nor torch), and the core must
not import the service stack; both may import this stdlib-only module.

Why not plain ``json.loads``: Python's parser recurses once per nesting level and raises
``RecursionError`` around 1,000 levels (an 8 KB input), refuses integers over 4,300 digits
with a ``ValueError`` only after reading them, and silently keeps the last of two equal keys.
Here every document is parsed under :class:`JsonLimits`:

* **nesting depth**: checked by one linear scan *before* the recursive parser runs;
* **string length** (as written, between the quotes): same scan;
* **number length** (characters of one literal): ``parse_int`` / ``parse_float`` hooks, so the
  text is never converted when it is too long;
* **duplicate keys**: refused (``object_pairs_hook``), naming the key;
* **document size**: ``max_bytes`` (files are not read past it).

Every failure is a :class:`JsonInputError` whose message names the document (``source``) and,
for a limit, the limit and its value; callers map it to their own error (a 422
``invalid_config``, a ``DatasetError``, a ``LightsError``).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

__all__ = ["JsonLimits", "JsonInputError", "DEFAULT_LIMITS", "loads", "load_file"]


@dataclass(frozen=True)
class JsonLimits:
    """Bounds on one JSON document (defaults: docs/SERVICE.md, "Limits")."""

    #: deepest nesting of arrays/objects: a job config needs 1, a transforms.json 4
    max_depth: int = 32
    #: characters of one number literal: a float64 written in full takes ~24
    max_number_chars: int = 100
    #: characters of one string as written (escapes counted as written): PATH_MAX is 4,096
    max_string_chars: int = 4096
    #: bytes of the whole document (None: no bound here; the caller caps it)
    max_bytes: Optional[int] = None


DEFAULT_LIMITS = JsonLimits()


class JsonInputError(ValueError):
    """A JSON document that is not valid JSON or breaks a :class:`JsonLimits` bound.

    Attributes: ``source`` (the document's name, e.g. ``"transforms_train.json"``), ``reason``
    (what is wrong), ``limit`` (``"max_depth=32"`` style, None for a syntax error), ``line`` and
    ``column`` (1-based, None when unknown)."""

    def __init__(self, source: str, reason: str, *, limit: Optional[str] = None,
                 line: Optional[int] = None, column: Optional[int] = None) -> None:
        self.source, self.reason, self.limit, self.line, self.column = source, reason, limit, line, column
        where = f" (line {line}, column {column})" if line is not None else ""
        super().__init__(f"{source}: {reason}{where}")


#: the next bracket or quote outside a string
_NEXT = re.compile(r'[\[\]{}"]')
#: the rest of a string literal after its opening quote ("unrolled loop": linear, no backtracking)
_STRING_REST = re.compile(r'[^"\\]*(?:\\.[^"\\]*)*"', re.DOTALL)


def _line_col(text: str, pos: int) -> tuple[int, int]:
    line = text.count("\n", 0, pos) + 1
    return line, pos - (text.rfind("\n", 0, pos) + 1) + 1


def _scan(text: str, source: str, limits: JsonLimits) -> None:
    """Depth and string length in one left-to-right pass over the brackets and strings (no
    recursion, each character looked at a bounded number of times). An unterminated string ends
    the scan: what follows it is inside it, and the parser reports the error."""
    depth, pos = 0, 0
    while (m := _NEXT.search(text, pos)) is not None:
        ch, start = m.group(), m.start()
        if ch == '"':
            rest = _STRING_REST.match(text, start + 1)
            if rest is None:
                return
            n = rest.end() - start - 2
            if n > limits.max_string_chars:
                line, col = _line_col(text, start)
                raise JsonInputError(source, f"a string of {n} characters is longer than the limit of "
                                             f"{limits.max_string_chars}",
                                     limit=f"max_string_chars={limits.max_string_chars}", line=line, column=col)
            pos = rest.end()
            continue
        if ch in "[{":
            depth += 1
            if depth > limits.max_depth:
                line, col = _line_col(text, start)
                raise JsonInputError(source, f"nesting is deeper than the limit of {limits.max_depth} levels",
                                     limit=f"max_depth={limits.max_depth}", line=line, column=col)
        else:
            depth -= 1
        pos = start + 1


def loads(text: str | bytes, *, source: str, limits: JsonLimits = DEFAULT_LIMITS) -> Any:
    """Parse ``text`` (``bytes`` are decoded as UTF-8, a BOM allowed) under ``limits``.

    Raises :class:`JsonInputError` for invalid UTF-8, invalid JSON, or any limit broken."""
    if isinstance(text, (bytes, bytearray)):
        if limits.max_bytes is not None and len(text) > limits.max_bytes:
            raise JsonInputError(source, f"the document is {len(text)} bytes, over the limit of {limits.max_bytes}",
                                 limit=f"max_bytes={limits.max_bytes}")
        try:
            text = bytes(text).decode("utf-8-sig")
        except UnicodeDecodeError as e:
            raise JsonInputError(source, f"not UTF-8 text (byte {e.start})") from None
    _scan(text, source, limits)

    def number(convert):
        def parse(s: str):
            if len(s) > limits.max_number_chars:
                raise JsonInputError(source, f"a number of {len(s)} characters ({s[:12]}...) is longer than the "
                                             f"limit of {limits.max_number_chars}",
                                     limit=f"max_number_chars={limits.max_number_chars}")
            return convert(s)
        return parse

    def pairs(items: list) -> dict:
        out = dict(items)
        if len(out) != len(items):
            seen: set = set()
            dup = next(k for k, _ in items if k in seen or seen.add(k))
            raise JsonInputError(source, f"the key {json.dumps(dup)[:80]} appears twice in one object",
                                 limit="duplicate_keys")
        return out

    try:
        return json.loads(text, parse_int=number(int), parse_float=number(float),
                          object_pairs_hook=pairs)
    except json.JSONDecodeError as e:
        raise JsonInputError(source, f"invalid JSON: {e.msg}", line=e.lineno, column=e.colno) from None
    except RecursionError:   # the scan bounds the depth; this is a second line of defence
        raise JsonInputError(source, "nesting is too deep", limit=f"max_depth={limits.max_depth}") from None


def load_file(path: str | Path, *, source: str, limits: JsonLimits = DEFAULT_LIMITS) -> Any:
    """:func:`loads` of a file, read no further than ``limits.max_bytes`` (+1, to see it is over).

    ``OSError`` is left to the caller (it knows how to name the file without a server path)."""
    with open(path, "rb") as f:
        data = f.read() if limits.max_bytes is None else f.read(limits.max_bytes + 1)
    return loads(data, source=source, limits=limits)
