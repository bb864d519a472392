"""The propagation trade (issue 29 §4): accuracy against training time on the twill benchmark,
and where a ``digitize`` run's training preset sits on it.

The data are the package file ``dualscale/report/data/propagate_trade.json`` (:data:`TRADE_FILE`).
Its one writer is ``bench/bench_propagate_trade.py`` (which also draws the figure of
docs/PROPAGATION.md from it); its one reader is :func:`load_trade`.  Layout (``version`` 1)::

    {"format": "dualscale-propagate-trade", "version": 1, "benchmark": str, "metrics": str,
     "maps": [map, ...],
     "runs": [{"name": str, "date": str, "machine": str, "load": str, "source": str,
               "points": [{"label": str, "kind": "preset" | "baseline", "seconds": float,
                           "load": float, "maps": {map: [l1, ssim], ...},
                           # presets only:
                           "preset": str, "warm_start": bool, "iterations": int, "batch": int}]}]}

``seconds`` is the training time (a baseline's: fit and run), wall clock, on the run's machine
and load; L1 is in the map's own units (normals: unit-vector components; tangent: axial turns),
SSIM is unitless.  These are the benchmark's accuracies, measured against a ground truth a
``digitize`` run does not have: the report labels them so, never as the run's accuracy.

:func:`trade_rows` gives the report's rows for one run; a preset with no measured point says
so.  Errors: :class:`~dualscale.errors.FormatError` for a file that is not this layout.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ..errors import FormatError
from . import format as fmt

TRADE_FILE = Path(__file__).resolve().parent / "data" / "propagate_trade.json"
FORMAT, VERSION = "dualscale-propagate-trade", 1

#: the maps whose accuracy the report's row shows (the issue's headline maps; every map is in the file)
SHOWN_MAPS = ("albedo", "normal")


def validate(doc: Any, where: str = "propagation trade data") -> dict[str, Any]:
    """Check ``doc`` against the layout of the module docstring and return it.  Raises
    :class:`~dualscale.errors.FormatError` naming ``where`` and the first bad field; two preset
    points of one (preset, warm start) are refused (the report could not say which it means)."""
    def bad(what: str) -> FormatError:
        return FormatError(f"{where}: {what}")

    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise bad(f"not a {FORMAT} document")
    if doc.get("version") != VERSION:
        raise bad(f"version {doc.get('version')!r} is not {VERSION}; rewrite it with bench/bench_propagate_trade.py")
    maps = doc.get("maps")
    if not isinstance(maps, list) or not maps or not all(isinstance(m, str) for m in maps):
        raise bad("'maps' must be a non-empty list of map names")
    if not isinstance(doc.get("runs"), list) or not doc["runs"]:
        raise bad("'runs' must be a non-empty list")
    seen: set[tuple[str, bool]] = set()
    for i, run in enumerate(doc["runs"]):
        for k in ("name", "date", "machine", "load"):
            if not isinstance(run.get(k), str) or not run[k]:
                raise bad(f"runs[{i}].{k} must be a non-empty string")
        if not isinstance(run.get("points"), list) or not run["points"]:
            raise bad(f"runs[{i}].points must be a non-empty list")
        for j, p in enumerate(run["points"]):
            at = f"runs[{i}].points[{j}]"
            if p.get("kind") not in ("preset", "baseline") or not isinstance(p.get("label"), str):
                raise bad(f"{at} needs a label and a kind of 'preset' or 'baseline'")
            s = p.get("seconds")
            if isinstance(s, bool) or not isinstance(s, (int, float)) or not s > 0:
                raise bad(f"{at}.seconds must be a positive number, not {s!r}")
            pm = p.get("maps")
            if not isinstance(pm, dict) or set(pm) != set(maps):
                raise bad(f"{at}.maps must give every map of 'maps' ({', '.join(maps)})")
            for m, v in pm.items():
                if (not isinstance(v, list) or len(v) != 2
                        or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
                    raise bad(f"{at}.maps.{m} must be [L1, SSIM]")
            if p["kind"] == "preset":
                if not isinstance(p.get("preset"), str) or not isinstance(p.get("warm_start"), bool):
                    raise bad(f"{at}: a preset point needs 'preset' (a name) and 'warm_start' (true/false)")
                for k in ("iterations", "batch"):
                    if isinstance(p.get(k), bool) or not isinstance(p.get(k), int) or p[k] < 1:
                        raise bad(f"{at}.{k} must be a positive integer")
                key = (p["preset"], p["warm_start"])
                if key in seen:
                    raise bad(f"{at}: a second point for preset {key[0]!r} (warm start {key[1]})")
                seen.add(key)
    return doc


def load_trade(path: str | Path | None = None) -> dict[str, Any]:
    """The trade data (default: the packaged :data:`TRADE_FILE`), checked by :func:`validate`.
    Raises :class:`~dualscale.errors.FormatError` for a file that is missing, not JSON or not
    the layout."""
    path = Path(path) if path is not None else TRADE_FILE
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as e:
        raise FormatError(f"{path}: the propagation trade data are missing (bench/bench_propagate_trade.py "
                          "writes them)") from e
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise FormatError(f"{path}: not readable as JSON ({e})") from e
    return validate(doc, str(path))


def measured_point(doc: dict[str, Any], preset: str, warm_start: bool = False
                   ) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """``(run, point)`` of the benchmark's point for ``preset`` (cold unless ``warm_start``),
    or ``None`` when that preset was not measured."""
    for run in doc["runs"]:
        for p in run["points"]:
            if p["kind"] == "preset" and p["preset"] == preset and p["warm_start"] == warm_start:
                return run, p
    return None


def _accuracy_text(doc: dict[str, Any], point: dict[str, Any]) -> str:
    return "; ".join(f"{fmt.label(m)} L1 {point['maps'][m][0]:.3f}, SSIM {point['maps'][m][1]:.2f}"
                     for m in SHOWN_MAPS if m in point["maps"])


def trade_rows(summary: dict[str, Any], doc: dict[str, Any] | None = None) -> list[tuple[str, str]]:
    """The report's rows for a propagate stage ``summary`` (its ``preset``, ``iterations``,
    ``train_seconds``): the run's own preset, training time and iterations, then the
    benchmark's measured point for that preset, warm-started or not as the run was (its
    ``warm_start``: the warm-start model's file name, or ``None``), labelled "measured on the twill benchmark, <date>, <machine>", or a sentence
    saying the preset has no measured point.  ``doc``: the trade data (default
    :func:`load_trade`)."""
    doc = load_trade() if doc is None else doc
    preset = summary.get("preset")
    its = summary.get("iterations")
    rows = [("training preset", fmt.value(preset)),
            ("training of this run", f"{fmt.duration(summary.get('train_seconds'))}, "
                                     f"{fmt.value(its)} iterations")]
    warm = bool(summary.get("warm_start"))
    rows.append(("warm start", fmt.value(summary["warm_start"]) if warm else "none (random weights)"))
    found = measured_point(doc, preset, warm) if isinstance(preset, str) else None
    if found is None:
        rows.append(("on the trade curve", f"the preset {fmt.value(preset)} "
                                           f"({'warm-started' if warm else 'from random weights'}) has no measured "
                                           "point on the twill "
                                           f"benchmark (measured: {', '.join(_measured_names(doc))})"))
        return rows
    run, p = found
    text = (f"{p['label']}: {fmt.duration(p['seconds'])} for {p['iterations']} iterations × batch {p['batch']} "
            f"(load {p['load']:g}); {_accuracy_text(doc, p)}")
    if isinstance(its, int) and its != p["iterations"]:
        text += f" (this run trained {its} iterations, not the benchmark's {p['iterations']})"
    rows.append((f"on the trade curve (measured on the twill benchmark, {run['date']}, {run['machine']}; "
                 "not this run's accuracy)", text))
    return rows


def _measured_names(doc: dict[str, Any]) -> list[str]:
    names: list[str] = []
    for run in doc["runs"]:
        names += [p["preset"] for p in run["points"] if p["kind"] == "preset" and p["preset"] not in names]
    return names


__all__ = ["TRADE_FILE", "validate", "load_trade", "measured_point", "trade_rows"]
