"""Numbers for people: units, significant digits, goals beside values, durations.

Every value a report shows goes through here, so a page never shows a Python repr, a JSON
dump or a 16-digit float. All functions return plain ``str`` (the templates escape them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, Mapping

DIGITS = 3
DASH = "—"

# units written without a space before them (SI writes "45°", "12 %" is also common; we keep
# the compact form for angles and percent)
_TIGHT_UNITS = {"°", "%", "′", "″"}


def number(x: Any, digits: int = DIGITS) -> str:
    """``x`` with ``digits`` significant digits, no exponent in [1e-3, 1e6), no trailing zeros.

    Integers (and integral floats above 1000) keep every digit, with thin-space thousands
    separators. ``None``/NaN give an em dash; infinities a signed ∞.
    """
    if x is None:
        return DASH
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return _group(f"{x:d}")
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if math.isnan(v):
        return DASH
    if math.isinf(v):
        return "∞" if v > 0 else "−∞"
    if v == 0:
        return "0"
    mag = math.floor(math.log10(abs(v)))
    if abs(v) >= 1e6 or abs(v) < 1e-3:
        m = f"{v:.{digits - 1}e}"
        mant, exp = m.split("e")
        mant = _strip(mant)
        return f"{mant.replace('-', '−')} × 10{_superscript(int(exp))}"
    decimals = max(0, digits - 1 - mag)
    r = round(v, decimals)
    s = f"{r:.{decimals}f}"
    if decimals:
        s = _strip(s)
    if abs(r) >= 1000:
        s = _group(s)
    return s.replace("-", "−")


def _strip(s: str) -> str:
    return s.rstrip("0").rstrip(".") if "." in s else s


def _group(s: str) -> str:
    neg = s.startswith("-")
    s = s.lstrip("-")
    head, _, tail = s.partition(".")
    groups = []
    while len(head) > 3:
        groups.insert(0, head[-3:])
        head = head[:-3]
    groups.insert(0, head)
    out = "\u2009".join(groups) + (f".{tail}" if tail else "")
    return ("−" if neg else "") + out


def _superscript(n: int) -> str:
    table = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")
    return str(n).translate(table)


def quantity(x: Any, unit: str = "", digits: int = DIGITS) -> str:
    """``number(x)`` followed by its unit: ``0.43°``, ``2.5 mm``, ``12 %``."""
    s = number(x, digits)
    if not unit or s == DASH:
        return s
    return f"{s}{unit}" if unit in _TIGHT_UNITS else f"{s} {unit}"


def percent(share: Any, digits: int = DIGITS) -> str:
    """A share in [0, 1] as a percentage: ``0.0123 -> 1.23%``."""
    if share is None:
        return DASH
    return quantity(100.0 * float(share), "%", digits)


def length_mm(x: Any, digits: int = DIGITS) -> str:
    """A length given in mm, written in µm below 0.1 mm and in mm above."""
    if x is None:
        return DASH
    v = float(x)
    if abs(v) < 0.1:
        return quantity(v * 1000.0, "µm", digits)
    return quantity(v, "mm", digits)


def size_mm(wh: Iterable[Any] | None, digits: int = DIGITS) -> str:
    """A field size ``[w, h]`` in mm: ``10 × 7.5 mm``."""
    if not wh:
        return DASH
    w, h = list(wh)[:2]
    return f"{number(w, digits)} × {number(h, digits)} mm"


def duration(seconds: Any) -> str:
    """Human duration: ``0.42 s``, ``12.3 s``, ``2 min 13 s``, ``1 h 02 min``."""
    if seconds is None:
        return DASH
    s = float(seconds)
    if math.isnan(s):
        return DASH
    if s < 60:
        return quantity(s, "s")
    total = int(round(s))
    if total < 3600:
        m, sec = divmod(total, 60)
        return f"{m} min {sec} s" if sec else f"{m} min"
    h, rest = divmod(total, 3600)
    return f"{h} h {rest // 60:02d} min"


_OPS = {"<": (lambda v, t: v < t), "<=": (lambda v, t: v <= t), "≤": (lambda v, t: v <= t),
        ">": (lambda v, t: v > t), ">=": (lambda v, t: v >= t), "≥": (lambda v, t: v >= t)}
_OP_TEXT = {"<=": "≤", ">=": "≥"}


@dataclass(frozen=True)
class Checked:
    """A value with its goal: ``text`` = ``0.43°``, ``goal`` = ``goal < 0.5°``, ``ok`` = True/False/None."""

    text: str
    goal: str
    ok: bool | None

    @property
    def mark(self) -> str:
        return {True: "✓", False: "✗", None: ""}[self.ok]

    def __str__(self) -> str:
        tail = f" ({self.goal}) {self.mark}".rstrip() if self.goal else ""
        return self.text + tail


def check(value: Any, op: str, threshold: float, unit: str = "", digits: int = DIGITS,
          scale: float = 1.0) -> Checked:
    """``check(0.43, "<", 0.5, "°")`` -> ``0.43° (goal < 0.5°) ✓``.

    ``scale`` multiplies both value and threshold for display (e.g. 100 for shares shown in %).
    """
    if op not in _OPS:
        raise ValueError(f"unknown comparison {op!r}")
    goal = f"goal {_OP_TEXT.get(op, op)} {quantity(threshold * scale, unit, digits)}"
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return Checked(DASH, goal, None)
    v = float(value)
    return Checked(quantity(v * scale, unit, digits), goal, bool(_OPS[op](v, threshold)))


def timestamp(iso: Any) -> str:
    """An ISO-8601 time as ``2026-12-01 14:03:27 UTC`` (seconds, no fraction); other text as is."""
    from datetime import datetime

    if not iso:
        return DASH
    try:
        t = datetime.fromisoformat(str(iso).replace("Z", "+00:00"))
    except ValueError:
        return str(iso)
    return t.strftime("%Y-%m-%d %H:%M:%S") + (t.strftime(" %Z") if t.tzinfo else "")


def label(key: str) -> str:
    """A JSON key as a heading: ``val_rmse_isotropic`` -> ``val rmse isotropic``."""
    return str(key).replace("_", " ").strip()


def short_hash(h: Any, n: int = 12) -> str:
    s = str(h)
    return s[:n] + "…" if len(s) > n else s


def value(x: Any, digits: int = DIGITS, max_items: int = 8) -> str:
    """Any JSON value as one readable line (no braces, no repr).

    Numbers get ``digits`` significant digits; booleans yes/no; ``None`` a dash; short lists
    of scalars are joined by commas, long ones summarised; mappings become ``key: value; ...``.
    """
    if x is None or isinstance(x, (bool, int, float)):
        return number(x, digits)
    if isinstance(x, str):
        return x
    if isinstance(x, Mapping):
        if not x:
            return DASH
        items = list(x.items())
        parts = [f"{label(k)}: {value(v, digits, max_items)}" for k, v in items[:max_items]]
        if len(items) > max_items:
            parts.append(f"… {len(items) - max_items} more")
        return "; ".join(parts)
    if isinstance(x, (list, tuple)):
        if not x:
            return DASH
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in x) and len(x) > max_items:
            vals = [float(v) for v in x]
            return f"{len(x)} values, {number(min(vals), digits)} to {number(max(vals), digits)}"
        parts = [value(v, digits, max_items) for v in x[:max_items]]
        if len(x) > max_items:
            parts.append(f"… {len(x) - max_items} more")
        return ", ".join(parts)
    return str(x)


def rows(d: Mapping[str, Any] | None, prefix: str = "", depth: int = 2) -> list[tuple[str, str]]:
    """Flatten a (nested) mapping into ``(label, value)`` rows for a two-column table;
    nested mappings up to ``depth`` levels get ``parent › child`` labels."""
    out: list[tuple[str, str]] = []
    for k, v in (d or {}).items():
        name = f"{prefix}{label(k)}"
        if isinstance(v, Mapping) and v and depth > 0:
            out.extend(rows(v, f"{name} › ", depth - 1))
        else:
            out.append((name, value(v)))
    return out


__all__ = ["number", "quantity", "percent", "length_mm", "size_mm", "duration", "check", "Checked",
           "timestamp", "label", "short_hash", "value", "rows", "DASH"]
