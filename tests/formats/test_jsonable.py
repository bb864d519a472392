"""``formats.atomic.jsonable``: the one JSON normaliser of the journal and capture records
(capture.session, adaptive.options), equal to what ``write_json`` writes and reads back."""

from __future__ import annotations

import json
from enum import Enum
from pathlib import Path

import numpy as np

from dualscale.formats.atomic import jsonable, write_json


class _Kind(Enum):
    LED = 1


def test_jsonable_is_what_write_json_reads_back(tmp_path):
    rec = {"path": Path("/a/b"), "shape": (3, 4), "kind": _Kind.LED, "gain": np.float32(0.5), "n": np.int64(7),
           "nested": [{"t": (1, 2.5, None, True)}], "s": "x"}
    back = json.loads(write_json(tmp_path / "r.json", rec).read_text())
    assert jsonable(rec) == back
    assert back["path"] == "/a/b" and back["shape"] == [3, 4] and back["kind"] == "_Kind.LED"
    assert jsonable(back) == back  # a record read from disk is unchanged (the journal compares them)
