"""Reading the project's versioned JSON files (dataset manifests, capture sets, calibrations)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def read_versioned_json(path: Path, fmt: str, version: int,
                        error: type[ValueError] = ValueError) -> dict[str, Any]:
    """Parse `path`, which must declare ``"format": fmt`` and ``"version": version``.

    Raises FileNotFoundError when the file is missing, and `error` (a ValueError) for invalid
    JSON, another format or another version, each naming the file.
    """
    if not path.is_file():
        raise FileNotFoundError(f"no {path.name} in {path.parent}")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise error(f"{path}: invalid JSON ({e})") from e
    if not isinstance(data, dict) or data.get("format") != fmt:
        raise error(f"{path}: not a {fmt} file")
    if data.get("version") != version:
        raise error(f"{path}: {fmt} version {data.get('version')} is not supported (need {version})")
    return data
