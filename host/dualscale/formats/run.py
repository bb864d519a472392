"""A digitize run folder: ``run.json`` and one stage record per stage (``stages/<stage>.json``).
The one reader and writer of both; what the stages write is described in docs/DIGITIZE.md.

``run.json``: ``{"format": "dualscale-run", "version": 1, "input": str, "options": {...},
"stages": [names in order]}``.

``stages/<stage>.json``: ``{"format": "dualscale-stage", "version": 1, "stage": str,
"key": sha256 of (stage, inputs, params, versions), "inputs": {name: sha256}, "params": {...},
"versions": {package: version}, "seconds": float, "finished": ISO-8601 UTC, "warnings": [str],
"outputs": [paths relative to the run], "outputs_sha256": sha256 of the stage folder,
"summary": {...}}``.  A record is written last, atomically: a stage whose record is present and
whose key and outputs still match is done.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from .atomic import TMP_PREFIX, write_json
from .versioned import read_versioned_json

RUN_FORMAT, STAGE_FORMAT, VERSION = "dualscale-run", "dualscale-stage", 1
#: the stages of ``dualscale digitize``, in order (:mod:`dualscale.pipeline`)
STAGES = ("calibrate", "fit", "flyouts", "propagate", "export", "report")
#: the stage of ``digitize --rig`` before the listed stages (``stages/capture.json``; not in
#: ``run.json``'s ``stages``): :mod:`dualscale.capture.stage`
CAPTURE_STAGE = "capture"
_CHUNK = 1 << 20


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def tree_sha256(root: str | Path) -> str:
    """SHA-256 over every file under ``root`` (relative path and content), temporary files
    excluded; a missing folder hashes as the empty string's hash of its name."""
    root = Path(root)
    h = hashlib.sha256()
    if root.is_file():
        h.update(file_sha256(root).encode())
        return h.hexdigest()
    for p in sorted(root.rglob("*")) if root.is_dir() else []:
        if p.is_file() and not p.name.startswith(TMP_PREFIX):
            h.update(str(p.relative_to(root)).encode())
            h.update(file_sha256(p).encode())
    return h.hexdigest()


def json_sha256(value: Any) -> str:
    """SHA-256 of a JSON-able value in canonical form (sorted keys)."""
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()


def write_run(run: str | Path, doc: dict[str, Any]) -> Path:
    """Write ``run.json`` (format and version added)."""
    return write_json(Path(run) / "run.json", {"format": RUN_FORMAT, "version": VERSION, **doc})


def read_run(run: str | Path) -> dict[str, Any]:
    return read_versioned_json(Path(run) / "run.json", RUN_FORMAT, VERSION)


def stage_path(run: str | Path, stage: str) -> Path:
    return Path(run) / "stages" / f"{stage}.json"


def write_stage(run: str | Path, stage: str, record: dict[str, Any]) -> Path:
    """Write the record of ``stage`` (format, version and stage name added)."""
    return write_json(stage_path(run, stage), {"format": STAGE_FORMAT, "version": VERSION, "stage": stage,
                                               **record})


def read_stage(run: str | Path, stage: str) -> dict[str, Any] | None:
    """The record of ``stage``, or ``None`` when the stage has not finished."""
    p = stage_path(run, stage)
    if not p.is_file():
        return None
    return read_versioned_json(p, STAGE_FORMAT, VERSION)
