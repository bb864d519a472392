"""The sample list of ``dualscale batch`` (:func:`read_list`): CSV or YAML, every row checked
before anything runs (see :mod:`dualscale.batch`)."""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dualscale.errors import InputError
from dualscale.pipeline import QUALITIES, DigitizeOptions


#: the columns (CSV) or keys (YAML) of a sample
FIELDS = ("name", "input", "calibration", "guidance", "transfer", "guidance_texel_mm", "quality", "export",
          "tile", "seed")
#: names a sample cannot take: the batch's own files in OUTDIR
RESERVED = ("summary.csv", "summary.html", "summary.json")
SUMMARY_FORMAT, SUMMARY_VERSION = "dualscale-batch-summary", 1
_TRUE, _FALSE = {"true", "yes", "1", "on"}, {"false", "no", "0", "off", ""}


@dataclass(frozen=True)
class Sample:
    """One row of the list, checked: absolute paths, a known quality, known export formats.
    ``where``: ``"LIST row N"`` for messages."""

    name: str
    input: Path
    calibration: Path | None = None
    guidance: Path | None = None
    transfer: str | None = None
    guidance_texel_mm: float | None = None
    quality: str = "standard"
    export: tuple[str, ...] = ()
    tile: bool = False
    seed: int = 0
    where: str = ""

    def options(self, outdir: str | Path, threads: int | None = None) -> DigitizeOptions:
        """The :class:`~dualscale.pipeline.DigitizeOptions` of this sample's run folder
        ``OUTDIR/<name>`` (no progress bars: the batch draws its own; no engine: the sample's
        fit runs whole in its task)."""
        return DigitizeOptions(input=self.input, run=Path(outdir) / self.name, calibration=self.calibration,
                               guidance=self.guidance, guidance_transfer=self.transfer,
                               guidance_texel_mm=self.guidance_texel_mm, quality=self.quality, threads=threads,
                               progress=False, seed=self.seed, export=self.export, tile=self.tile, name=self.name,
                               source=self.where or None)


# ---------------------------------------------------------------------------------------- the list

class _Row:
    """Where a value came from, for the one-line errors."""

    def __init__(self, path: Path, index: int, line: int | None = None) -> None:
        self.path, self.index, self.line = path, index, line

    def error(self, column: str | None, message: str) -> InputError:
        at = f"row {self.index}" + (f" (line {self.line})" if self.line is not None else "")
        col = f", column {column!r}" if column is not None else ""
        return InputError(f"{self.path}: {at}{col}: {message}")


def _text(row: _Row, col: str, v: Any) -> str | None:
    if v is None:
        return None
    if not isinstance(v, str):
        raise row.error(col, f"expected text, got {v!r} (quote it in YAML)")
    v = v.strip()
    return v or None


def _path(row: _Row, col: str, v: Any, base: Path) -> Path | None:
    t = _text(row, col, v)
    if t is None:
        return None
    p = Path(t).expanduser()
    return Path(os.path.abspath(p if p.is_absolute() else base / p))  # '..' folded, links kept


def _bool(row: _Row, col: str, v: Any) -> bool:
    if v is None or isinstance(v, bool):
        return bool(v)
    if isinstance(v, str) and v.strip().lower() in _TRUE | _FALSE:
        return v.strip().lower() in _TRUE
    raise row.error(col, f"{v!r} is not true or false (true/false, yes/no, 1/0)")


def _seed(row: _Row, col: str, v: Any) -> int:
    if v is None or (isinstance(v, str) and not v.strip()):
        return 0
    if isinstance(v, bool):
        raise row.error(col, f"{v!r} is not a whole number")
    try:
        n = int(v.strip()) if isinstance(v, str) else v
    except ValueError:
        n = None
    if not isinstance(n, int) or n < 0:
        raise row.error(col, f"{v!r} is not a whole number >= 0")
    return n


def _positive(row: _Row, col: str, v: Any) -> float | None:
    if v is None or (isinstance(v, str) and not v.strip()):
        return None
    try:
        x = float(v) if not isinstance(v, bool) else math.nan
    except (TypeError, ValueError):
        x = math.nan
    if not (math.isfinite(x) and x > 0):
        raise row.error(col, f"{v!r} is not a size in mm > 0")
    return x


def _formats(row: _Row, col: str, v: Any, default: tuple[str, ...]) -> tuple[str, ...]:
    from dualscale.export.material import ALL_FORMATS

    if v is None:
        return default
    if isinstance(v, str):
        names = [t for t in v.replace(";", ",").replace(" ", ",").split(",") if t]
    elif isinstance(v, list) and all(isinstance(t, str) for t in v):
        names = [t.strip() for t in v if t.strip()]
    else:
        raise row.error(col, f"expected formats separated by commas, got {v!r}")
    if not names:
        return default
    if names == ["all"]:
        return tuple(ALL_FORMATS)
    bad = [n for n in names if n not in ALL_FORMATS]
    if bad:
        raise row.error(col, f"{', '.join(bad)}: choose from {', '.join(ALL_FORMATS)} or 'all'")
    return tuple(dict.fromkeys(names))


def _sample(row: _Row, values: dict[str, Any], base: Path, quality: str, export: tuple[str, ...]) -> Sample:
    """Check one row's values (``{column: value}``, only known columns) into a :class:`Sample`."""
    from dualscale.export.material import check_name
    from dualscale.formats.photo import parse_transfer
    from dualscale.pipeline import input_dataset

    name = _text(row, "name", values.get("name"))
    if name is None:
        raise row.error("name", "every sample needs a name (its folder in OUTDIR)")
    try:
        check_name(name)
    except InputError as e:
        raise row.error("name", str(e)) from None
    if name.lower() in RESERVED:
        raise row.error("name", f"{name!r} is one of the batch's own files ({', '.join(RESERVED)})")
    inp = _path(row, "input", values.get("input"), base)
    if inp is None:
        raise row.error("input", "every sample needs an input (a dataset folder, or a folder holding micro/)")
    try:
        input_dataset(inp)
    except (FileNotFoundError, InputError) as e:
        raise row.error("input", str(e)) from None
    cal = _path(row, "calibration", values.get("calibration"), base)
    if cal is not None and not cal.is_file():
        raise row.error("calibration", f"calibration file not found: {cal}")
    guidance = _path(row, "guidance", values.get("guidance"), base)
    if guidance is not None and not guidance.exists():
        raise row.error("guidance", f"guidance image or dataset not found: {guidance}")
    transfer = _text(row, "transfer", values.get("transfer"))
    if transfer is not None:
        try:
            parse_transfer(transfer)
        except ValueError as e:
            raise row.error("transfer", str(e)) from None
        if guidance is None:
            raise row.error("transfer", f"{transfer!r} is the transfer function of a display-encoded guidance image, "
                                        "and the row has no guidance: leave the cell empty, or fill the guidance")
    elif guidance is not None and guidance.is_file() and guidance.suffix.lower() != ".exr":
        raise row.error("transfer", f"the guidance {guidance.name} is display-encoded: give its transfer function "
                                    "(srgb, linear or gamma:G; dualscale never guesses it)")
    q = _text(row, "quality", values.get("quality")) or quality
    if q not in QUALITIES:
        raise row.error("quality", f"{q!r}: choose one of {', '.join(QUALITIES)}")
    return Sample(name=name, input=inp, calibration=cal, guidance=guidance, transfer=transfer,
                  guidance_texel_mm=_positive(row, "guidance_texel_mm", values.get("guidance_texel_mm")),
                  quality=q, export=_formats(row, "export", values.get("export"), export),
                  tile=_bool(row, "tile", values.get("tile")), seed=_seed(row, "seed", values.get("seed")),
                  where=f"{row.path.name} row {row.index}")


def _csv_rows(path: Path) -> list[tuple[_Row, dict[str, Any]]]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = None
        for cells in reader:
            if any(c.strip() for c in cells) and not cells[0].lstrip().startswith("#"):
                header = [c.strip() for c in cells]
                break
        if header is None:
            raise InputError(f"{path}: empty: expected a header row ({', '.join(FIELDS)}) and one row per sample")
        head = _Row(path, 0, reader.line_num)
        for col in header:
            if col not in FIELDS:
                raise head.error(col, f"unknown column: the columns are {', '.join(FIELDS)}")
        dup = sorted({c for c in header if header.count(c) > 1})
        if dup:
            raise head.error(dup[0], "the column appears twice")
        for col in ("name", "input"):
            if col not in header:
                raise head.error(col, "missing column (every sample needs a name and an input)")
        rows = []
        for cells in reader:
            if not any(c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
                continue
            row = _Row(path, len(rows) + 1, reader.line_num)
            if len(cells) > len(header):
                raise row.error(None, f"{len(cells)} cells for {len(header)} columns (quote a value holding a comma)")
            rows.append((row, {c: v for c, v in zip(header, cells)}))
    except csv.Error as e:
        raise InputError(f"{path}: line {reader.line_num}: not valid CSV ({e})") from None
    return rows


def _yaml_rows(path: Path) -> list[tuple[_Row, dict[str, Any]]]:
    import yaml

    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8-sig"))
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not readable YAML ({' '.join(str(e).split())})") from None
    if isinstance(doc, dict) and set(doc) == {"samples"}:
        doc = doc["samples"]
    if not isinstance(doc, list):
        raise InputError(f"{path}: expected a list of samples (or 'samples:' holding one), got "
                         f"{type(doc).__name__ if doc is not None else 'nothing'}")
    rows = []
    for i, entry in enumerate(doc, 1):
        row = _Row(path, i)
        if not isinstance(entry, dict):
            raise row.error(None, f"expected a mapping of {', '.join(FIELDS)}, got {type(entry).__name__}")
        for key in entry:
            if key not in FIELDS:
                raise row.error(str(key), f"unknown column: the columns are {', '.join(FIELDS)}")
        rows.append((row, entry))
    return rows


def read_list(path: str | Path, quality: str = "standard", export: tuple[str, ...] | None = None) -> list[Sample]:
    """The samples of the list file ``path`` (module docstring), checked; ``quality`` and
    ``export`` are the defaults of rows without them (``export`` None: every format).  Raises
    :class:`~dualscale.errors.InputError` (one line: the file, row and column) for anything
    that cannot be run, before anything is written."""
    from dualscale.export.material import ALL_FORMATS

    path = Path(path)
    if not path.is_file():
        raise InputError(f"sample list not found: {path}")
    if quality not in QUALITIES:
        raise InputError(f"--quality {quality!r}: choose one of {', '.join(QUALITIES)}")
    export = tuple(ALL_FORMATS) if export is None else tuple(export)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        rows = _csv_rows(path)
    elif suffix in (".yaml", ".yml"):
        rows = _yaml_rows(path)
    else:
        raise InputError(f"{path}: a sample list is a .csv or a .yaml/.yml file")
    base = path.absolute().parent
    samples: list[Sample] = []
    seen: dict[str, int] = {}
    for row, values in rows:
        s = _sample(row, values, base, quality, export)
        if s.name.lower() in seen:
            raise row.error("name", f"{s.name!r} is the name of row {seen[s.name.lower()]} too: names must be "
                                    "unique (ignoring case: they are folders)")
        seen[s.name.lower()] = row.index
        samples.append(s)
    if not samples:
        raise InputError(f"{path}: no samples")
    return samples


