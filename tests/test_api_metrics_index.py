"""The incremental metrics.jsonl index against a plain re-read, while the file grows."""

from __future__ import annotations

import json
import os
import random

from jobstore.storage.metrics_index import MetricsIndex


def plain(path, since, limit):
    lines = path.read_bytes().split(b"\n")[:-1]
    return [json.loads(x) for x in lines[since:since + limit]]


def test_index_matches_a_plain_read_while_growing(tmp_path):
    path = tmp_path / "metrics.jsonl"
    idx = MetricsIndex()
    rng = random.Random(0)
    assert idx.read(path, 0, 10) == ([], 0)
    written = 0
    with open(path, "wb") as f:
        for round_ in range(30):
            for _ in range(rng.randint(0, 7)):
                f.write(json.dumps({"step": written, "loss": rng.random()}).encode() + b"\n")
                written += 1
            f.write(b'{"step": ')            # a line still being written is never returned
            f.flush()
            for since in (0, max(written - 3, 0), written, written + 5):
                for limit in (1, 4, 1000):
                    recs, nxt = idx.read(path, since, limit)
                    assert recs == plain(path, since, limit)
                    assert nxt == (min(written, since + limit) if since < written else since)
            f.seek(f.tell() - len(b'{"step": '))
            f.truncate()
    # replaced by a shorter file (a new inode): the index starts over
    os.replace(tmp_path / "metrics.jsonl", tmp_path / "old.jsonl")
    path.write_text(json.dumps({"step": 0}) + "\n")
    assert idx.read(path, 0, 10) == ([{"step": 0}], 1)
