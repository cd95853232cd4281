"""Incremental line index of ``metrics.jsonl`` files: serving ``?since=N`` or an SSE tail costs
O(new + returned bytes), not a re-read of a file that grows for hours."""

from __future__ import annotations

import json
import os
import threading
from collections import OrderedDict
from pathlib import Path


class _Index:
    __slots__ = ("ino", "size", "offsets", "lock")

    def __init__(self) -> None:
        self.ino = -1
        self.size = 0          # bytes indexed (always the end of a complete line)
        self.offsets = [0]     # offsets[i] = start of record i; offsets[-1] = end of indexed data
        self.lock = threading.Lock()


class MetricsIndex:
    def __init__(self, max_files: int = 512) -> None:
        self._files: "OrderedDict[str, _Index]" = OrderedDict()
        self._lock = threading.Lock()
        self.max_files = max_files

    def _index(self, key: str) -> _Index:
        with self._lock:
            idx = self._files.get(key)
            if idx is None:
                idx = self._files[key] = _Index()
                while len(self._files) > self.max_files:
                    self._files.popitem(last=False)
            else:
                self._files.move_to_end(key)
            return idx

    def read(self, path: Path, since: int, limit: int) -> tuple[list[dict], int]:
        """Records ``since .. since+limit`` (complete lines only) and the next cursor."""
        try:
            st = os.stat(path)
        except FileNotFoundError:
            return [], since
        idx = self._index(str(path))
        with idx.lock:
            with open(path, "rb") as f:
                if st.st_ino != idx.ino or st.st_size < idx.size:   # replaced or truncated: start over
                    idx.ino, idx.size, idx.offsets = st.st_ino, 0, [0]
                if st.st_size > idx.size:
                    f.seek(idx.size)
                    new = f.read(st.st_size - idx.size)
                    end = new.rfind(b"\n")
                    if end >= 0:
                        pos = 0
                        while True:
                            nl = new.find(b"\n", pos, end + 1)
                            if nl < 0:
                                break
                            idx.offsets.append(idx.size + nl + 1)
                            pos = nl + 1
                        idx.size += end + 1
                n = len(idx.offsets) - 1
                if since >= n:
                    return [], since
                stop = min(n, since + limit)
                f.seek(idx.offsets[since])
                chunk = f.read(idx.offsets[stop] - idx.offsets[since])
        out = []
        for raw in chunk.split(b"\n")[:-1]:
            try:
                out.append(json.loads(raw))
            except json.JSONDecodeError:
                out.append({"invalid": raw.decode("utf-8", "replace")})
        return out, stop


METRICS = MetricsIndex()
