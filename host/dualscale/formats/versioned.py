"""Reading the project's JSON files: versioned ones (dataset manifests, capture sets,
calibrations, maps, runs) and plain ones, with errors that name the file."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from dualscale.errors import FormatError


def read_json(path: str | Path, error: type[ValueError] = FormatError) -> dict[str, Any]:
    """Parse a JSON object from ``path``.  ``FileNotFoundError`` when missing; ``error`` (a
    ``ValueError``, by default :class:`~dualscale.errors.FormatError`) for invalid JSON or a
    non-object, naming the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no {path.name} in {path.parent}")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise error(f"{path}: invalid JSON ({e})") from e
    if not isinstance(data, dict):
        raise error(f"{path}: expected a JSON object")
    return data


def read_versioned_json(path: str | Path, fmt: str, version: int | tuple[int, ...],
                        error: type[ValueError] = FormatError) -> dict[str, Any]:
    """Parse ``path``, which must declare ``"format": fmt`` and ``"version": version`` (or one
    of ``version`` when a tuple).

    Raises FileNotFoundError when the file is missing, and ``error`` (a ValueError) for invalid
    JSON, another format or another version, each naming the file.
    """
    path = Path(path)
    data = read_json(path, error)
    if data.get("format") != fmt:
        raise error(f"{path}: not a {fmt} file")
    ok = version if isinstance(version, tuple) else (version,)
    if data.get("version") not in ok:
        raise error(f"{path}: {fmt} version {data.get('version')} is not supported (need {' or '.join(map(str, ok))})")
    return data
