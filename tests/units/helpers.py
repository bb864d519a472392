"""Edit a dataset's manifest and check that a command wrote nothing."""

import json
from pathlib import Path


def edit_manifest(root: Path, fn) -> Path:
    """Apply ``fn(manifest)`` to ``root/manifest.json`` in place (it may edit records)."""
    path = root / "manifest.json"
    m = json.loads(path.read_text())
    fn(m)
    path.write_text(json.dumps(m, allow_nan=True))
    return root


def led_records(m: dict) -> list[dict]:
    return [r for r in m["images"] if r["light"]["kind"] == "led"]


def nothing_written(out: Path) -> bool:
    """True when ``out`` does not exist and no temporary sibling was left beside it."""
    stale = [p for p in out.parent.glob(f".tmp-{out.name}*")] if out.parent.exists() else []
    return not out.exists() and not stale
