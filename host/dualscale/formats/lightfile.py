"""Light files: one light direction (and optional intensity) per image.

Two formats, chosen by suffix in :func:`read_lights`:

``.lp`` (the RTI convention of RTIBuilder / relight / the CHI light-position files)
    First line the number of images ``N``, then ``N`` lines ``filename x y z``.  Read
    tolerantly: blank lines, surrounding whitespace, Windows line endings, a UTF-8 BOM and
    comments from ``#`` to the end of the line are ignored, and a file name may contain spaces
    (the last three fields are the direction).  Written strictly: ``N`` then one line per
    light, six-plus decimals, ``\\n`` line endings, names without whitespace.

``.json`` (ours)
    ``{"format": "dualscale-lights", "version": 1, "frame": "camera",
    "lights": [{"file": str, "direction": [x, y, z], "intensity": float | null}, ...],
    "source": {...}}`` where ``source`` says how the lights were recovered (e.g. the
    mirror-sphere centre and radius in pixels and a residual per light).

Frame (``"camera"``, the only one either format carries): unit direction from the scene
towards the light, ``+x`` image right, ``+y`` image up (image rows go *down*), ``+z`` towards
the camera.  For the rig's micro camera looking straight down this is the sample's macro frame
of Garces et al. 2023, Sec. 2 (``+z`` = macro normal).

Refusals (``ValueError`` naming file and line, or file and light index; on read and on write,
and a refused write leaves nothing on disk): a direction that is not finite, not unit (it is
renormalised silently when ``| |d| - 1 | <= 1e-3``), or at / below the horizon (``z <= 0``); a
duplicate file name; an intensity that is not finite or negative; in ``.lp``, a count that does
not match the number of lines.  Writes go through a temporary file in the target folder and
``os.replace``, so a reader never sees half a file.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

from dualscale.errors import GeometryError  # a ValueError: below-horizon directions

from .atomic import write_text

FORMAT = "dualscale-lights"
VERSION = 1
FRAME = "camera"
UNIT_TOL = 1e-3


@dataclass(frozen=True)
class LightRecord:
    """One image's light: ``file`` (name as written in the light file, usually relative to it),
    ``direction`` unit ``(x, y, z)`` in the camera frame (see the module docstring), and
    ``intensity`` (relative, ``None`` when unknown)."""

    file: str
    direction: tuple[float, float, float]
    intensity: float | None = None


@dataclass(frozen=True)
class LightFile:
    """The whole JSON light file: its records, frame and free-form ``source`` block."""

    records: list[LightRecord]
    frame: str = FRAME
    source: dict[str, Any] | None = None


def _unit(d: Iterable[Any], where: str) -> tuple[float, float, float]:
    try:
        v = [float(c) for c in d]
    except (TypeError, ValueError):
        raise ValueError(f"{where}: direction {d!r} is not three numbers") from None
    if len(v) != 3:
        raise ValueError(f"{where}: direction has {len(v)} components, expected 3")
    if not all(math.isfinite(c) for c in v):
        raise ValueError(f"{where}: direction {v} is not finite")
    n = math.sqrt(sum(c * c for c in v))
    if abs(n - 1.0) > UNIT_TOL:
        raise ValueError(f"{where}: direction {v} is not unit (norm {n:.6g}; tolerance {UNIT_TOL})")
    v = [c / n for c in v]
    if v[2] <= 0.0:
        raise GeometryError(f"{where}: direction {v} is at or below the horizon (z = {v[2]:.6g} <= 0)")
    return (v[0], v[1], v[2])


def _intensity(x: Any, where: str) -> float | None:
    if x is None:
        return None
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise ValueError(f"{where}: intensity {x!r} is not a number or null")
    x = float(x)
    if not math.isfinite(x) or x < 0:
        raise ValueError(f"{where}: intensity {x!r} must be finite and >= 0")
    return x


def _check_records(records: Iterable[LightRecord], path: Path, wheres: list[str] | None = None) -> list[LightRecord]:
    out: list[LightRecord] = []
    seen: dict[str, str] = {}
    for i, r in enumerate(records):
        where = wheres[i] if wheres else f"{path}: light {i}"
        if not isinstance(r.file, str) or not r.file.strip():
            raise ValueError(f"{where}: empty file name")
        if r.file in seen:
            raise ValueError(f"{where}: duplicate file name {r.file!r} (first at {seen[r.file]})")
        seen[r.file] = where
        out.append(LightRecord(r.file, _unit(r.direction, where), _intensity(r.intensity, where)))
    return out


# ----------------------------------------------------------------------------------------- .lp
def read_lp(path: str | Path) -> list[LightRecord]:
    """Read an RTI ``.lp`` file (tolerant, see the module docstring) into ``LightRecord`` s
    (``intensity`` None).  Raises ``ValueError`` naming ``path:line``, ``FileNotFoundError``."""
    path = Path(path)
    lines = path.read_text(encoding="utf-8-sig").splitlines()  # handles \r\n and \r
    count: int | None = None
    count_line = 0
    records: list[LightRecord] = []
    wheres: list[str] = []
    for no, raw in enumerate(lines, 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"{path}:{no}"
        if count is None:
            fields = line.split()
            if len(fields) != 1 or not fields[0].lstrip("+-").isdigit():
                raise ValueError(f"{where}: expected the number of images, got {raw.strip()!r}")
            count = int(fields[0])
            if count < 0:
                raise ValueError(f"{where}: negative image count {count}")
            count_line = no
            continue
        fields = line.split()
        if len(fields) < 4:
            raise ValueError(f"{where}: expected 'filename x y z', got {raw.strip()!r}")
        name = " ".join(fields[:-3])
        try:
            d = tuple(float(c) for c in fields[-3:])
        except ValueError:
            raise ValueError(f"{where}: direction {fields[-3:]} is not three numbers") from None
        records.append(LightRecord(name, d))  # type: ignore[arg-type]
        wheres.append(where)
    if count is None:
        raise ValueError(f"{path}: empty light file (no image count)")
    if count != len(records):
        raise ValueError(f"{path}:{count_line}: count mismatch: header says {count} images, "
                         f"the file lists {len(records)}")
    return _check_records(records, path, wheres)


def write_lp(path: str | Path, records: Iterable[LightRecord]) -> Path:
    """Write an RTI ``.lp`` file atomically; validates first (nothing is written when refused).
    File names must not contain whitespace or ``#`` (the format cannot carry them)."""
    path = Path(path)
    recs = _check_records(list(records), path)
    for i, r in enumerate(recs):
        if any(c.isspace() for c in r.file) or "#" in r.file:
            raise ValueError(f"{path}: light {i}: file name {r.file!r} contains whitespace or '#', "
                             "which .lp cannot carry")
    body = [f"{len(recs)}"] + [f"{r.file} {r.direction[0]:.9f} {r.direction[1]:.9f} {r.direction[2]:.9f}"
                               for r in recs]
    write_text(path, "\n".join(body) + "\n")
    return path


# --------------------------------------------------------------------------------------- .json
def read_lights_json(path: str | Path) -> LightFile:
    """Read our JSON light file.  Raises ``ValueError`` naming the file and light index."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}:{e.lineno}: not valid JSON ({e.msg})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"{path}: not a {FORMAT!r} file (format = "
                         f"{data.get('format') if isinstance(data, dict) else None!r})")
    if data.get("version") != VERSION:
        raise ValueError(f"{path}: unsupported version {data.get('version')!r} (this reader knows {VERSION})")
    if data.get("frame") != FRAME:
        raise ValueError(f"{path}: unsupported frame {data.get('frame')!r} (expected {FRAME!r})")
    lights = data.get("lights")
    if not isinstance(lights, list):
        raise ValueError(f"{path}: 'lights' must be a list")
    records, wheres = [], []
    for i, e in enumerate(lights):
        where = f"{path}: lights[{i}]"
        if not isinstance(e, dict) or "file" not in e or "direction" not in e:
            raise ValueError(f"{where}: expected an object with 'file' and 'direction'")
        if not isinstance(e["file"], str):
            raise ValueError(f"{where}: 'file' must be a string")
        d = e["direction"]
        if not isinstance(d, list):
            raise ValueError(f"{where}: 'direction' must be a list [x, y, z]")
        records.append(LightRecord(e["file"], tuple(d), e.get("intensity")))  # type: ignore[arg-type]
        wheres.append(where)
    source = data.get("source")
    if source is not None and not isinstance(source, dict):
        raise ValueError(f"{path}: 'source' must be an object or absent")
    return LightFile(_check_records(records, path, wheres), FRAME, source)


def write_lights_json(path: str | Path, records: Iterable[LightRecord], source: dict[str, Any] | None = None) -> Path:
    """Write our JSON light file atomically; validates first (nothing is written when refused).
    ``source`` must be JSON-serialisable with finite numbers (NaN / inf are refused)."""
    path = Path(path)
    recs = _check_records(list(records), path)
    doc = {"format": FORMAT, "version": VERSION, "frame": FRAME,
           "lights": [{"file": r.file, "direction": list(r.direction), "intensity": r.intensity} for r in recs],
           "source": source or {}}
    try:
        text = json.dumps(doc, indent=1, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: 'source' is not JSON-serialisable with finite numbers ({e})") from None
    write_text(path, text + "\n")
    return path


def read_lights(path: str | Path) -> list[LightRecord]:
    """Read a light file, ``.lp`` or ``.json`` by suffix (case-insensitive)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".lp":
        return read_lp(path)
    if suffix == ".json":
        return read_lights_json(path).records
    raise ValueError(f"{path}: unknown light-file suffix {path.suffix!r} (expected .lp or .json)")
