"""The capture journal: one JSON line per completed unit of work, appended and fsynced.

``DATASET/journal.jsonl`` is the record a resumed capture trusts (issue 14 §3 "write as you
go").  A unit's files are written first (each through a temporary file and a rename), then its
line; a process killed at any moment leaves either both or a file without a line (redone on
resume, its file replaced atomically), never a line without its files.  A torn last line (the
process died inside ``write``) is ignored on reading, and the next append starts on a fresh
line.

Entry kinds (``"kind"``): ``start`` (the plan, cameras, rig), ``dark`` (a dark frame),
``meter`` (a shot's metered bracket plan), ``shot`` (a shot's frames, matched to their device
events), ``retake`` (a frame refused, with the reason), ``merged`` (a sample plan's dataset was
written), ``written`` (a calibration-target plan's part of the capture set was written); an
adaptive capture (:mod:`dualscale.adaptive.loop`) adds ``adaptive`` (its options), ``round`` (a
decision: the LEDs to take and why, every candidate's score, or the stop and its reason; written
before its shots) and ``fit`` (a round's fit: shots, device time, the median sigma per map).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from dualscale.errors import FormatError

JOURNAL = "journal.jsonl"


class Journal:
    """Append-only JSON-lines journal at ``path`` (read back at construction: :attr:`entries`)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.entries: list[dict[str, Any]] = []
        self._good = 0  # bytes up to the end of the last complete line
        if self.path.exists():
            data = self.path.read_bytes()
            lines = data.split(b"\n")
            for i, line in enumerate(lines):
                if not line.strip():
                    continue
                try:
                    entry = json.loads(line)
                except json.JSONDecodeError as e:
                    if i == len(lines) - 1:  # the last, unterminated line: a write cut short
                        break
                    raise FormatError(f"{self.path}:{i + 1}: not a JSON line ({e.msg}); the journal is damaged") from e
                if not isinstance(entry, dict) or "kind" not in entry:
                    raise FormatError(f"{self.path}:{i + 1}: a journal line is an object with a 'kind'")
                self.entries.append(entry)
            self._good = data.rfind(b"\n") + 1

    def of(self, kind: str) -> list[dict[str, Any]]:
        """The entries of one kind, in order."""
        return [e for e in self.entries if e["kind"] == kind]

    def append(self, kind: str, **fields: Any) -> dict[str, Any]:
        """Append one entry and flush it to disk (fsync) before returning."""
        entry = {"kind": kind, **fields}
        line = json.dumps(entry, separators=(",", ":"), default=str).encode() + b"\n"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            if os.fstat(fd).st_size != self._good:  # a torn last line: cut it off
                os.ftruncate(fd, self._good)
            os.write(fd, line)
            os.fsync(fd)
            self._good += len(line)
        finally:
            os.close(fd)
        self.entries.append(entry)
        return entry
