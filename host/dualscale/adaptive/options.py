"""The adaptive capture's options and their command-line forms (issue 27; docs/CAPTURE.md,
"Adaptive capture"): light to import (the command line's parser builds from them), the loop
itself is :mod:`.loop`."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from dualscale.errors import InputError
from dualscale.formats.atomic import jsonable as _jsonable  # loop.py imports it from here too

CRITERIA = ("D", "A")
"""The optimal-design criteria (:mod:`.design`)."""

#: map -> the default target median sigma (map units, as fit.json's uncertainty summary): none;
#: the default target is relative, :data:`DEFAULT_FULL_TARGET`
DEFAULT_TARGETS: dict[str, float] = {}

#: the default ``--target full+5%``: stop when every map's predicted median sigma is within 5 % of
#: what the whole candidate plan would give (the ``standard`` fit on a full capture of this
#: sample, predicted from the current maps: :func:`dualscale.adaptive.design.predicted_sigmas`)
DEFAULT_FULL_TARGET = 0.05


@dataclass
class AdaptiveOptions:
    """How the adaptive capture decides (module doc).  ``targets``: map -> median sigma to stop
    at; ``full_target``: stop when every map's predicted median sigma is at most ``1 +
    full_target`` times the whole candidate plan's (``None``: no such rule; a map named in
    ``targets`` uses its own target instead); ``budget_shots`` / ``budget_s``: the most shots / seconds of device time (floor);
    ``batch``: LEDs per round (``None``: :func:`auto_batch`)."""

    initial: int = 12
    batch: int | None = None
    criterion: str = "D"
    targets: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_TARGETS))
    full_target: float | None = DEFAULT_FULL_TARGET
    min_gain: float = 0.1
    budget_shots: int | None = None
    budget_s: float | None = None
    sample_pixels: int = 1024
    seed: int = 0
    max_rounds: int = 64

    def __post_init__(self) -> None:
        if self.criterion not in CRITERIA:
            raise InputError(f"--criterion {self.criterion!r}: one of {', '.join(CRITERIA)}")
        if self.initial < 3:
            raise InputError(f"--initial-leds {self.initial}: at least 3 LEDs (the photometric stereo start needs 3)")
        if self.batch is not None and self.batch < 1:
            raise InputError(f"--batch-leds {self.batch}: at least 1")
        if self.sample_pixels < 16:
            raise InputError(f"sample pixels {self.sample_pixels}: at least 16")
        if not self.min_gain >= 0:
            raise InputError(f"--min-gain {self.min_gain}: >= 0 (nats per sample pixel)")
        for k, v in self.targets.items():
            if not (isinstance(v, (int, float)) and v > 0 and math.isfinite(v)):
                raise InputError(f"--target {k}={v}: a positive sigma")
        if self.full_target is not None and not (math.isfinite(self.full_target) and self.full_target >= 0):
            raise InputError(f"--target full+{self.full_target:g}: a percentage >= 0 (e.g. full+5%)")
        if self.budget_shots is not None and self.budget_shots < 1:
            raise InputError(f"--budget {self.budget_shots}: a positive shot count (e.g. 80) or device time (e.g. 300s)")
        if self.budget_shots is not None and self.budget_shots < 2 * self.initial + 2:
            raise InputError(f"--budget {self.budget_shots} shots: the first round alone takes {2 * self.initial + 2} "
                             f"({self.initial} LEDs at P0 and P90, and the back light)")
        if self.budget_s is not None and not self.budget_s > 0:
            raise InputError(f"--budget {self.budget_s}s: a positive device time")


def parse_targets(spec: str | None) -> tuple[dict[str, float], float | None]:
    """``--target`` as ``(targets, full_target)`` (:class:`AdaptiveOptions`); ``InputError``
    naming the bad entry.  Entries, comma-separated: ``MAP=SIGMA`` (e.g. ``normal=0.5``; sigma in
    the map's units: the normal in degrees) and ``full+N%`` (every other map within N % of the
    whole candidate plan's predicted sigma); ``none``: no target (the gain and budget rules
    stop the capture).  Without ``--target``: :data:`DEFAULT_TARGETS` and ``full+5%``
    (:data:`DEFAULT_FULL_TARGET`).  A given ``--target`` replaces the default whole."""
    from dualscale.formats.maps import SIGMA_UNITS

    if spec is None:
        return dict(DEFAULT_TARGETS), DEFAULT_FULL_TARGET
    if not str(spec).strip():
        raise InputError("--target '': give MAP=SIGMA,..., full+N% or none (without --target: full+5%)")
    out: dict[str, float] = {}
    full = None
    parts = [p.strip() for p in str(spec).split(",")]
    if parts == ["none"]:
        return out, None
    for part in parts:
        if part.startswith("full"):
            pct = part[4:].strip()
            if full is not None:
                raise InputError(f"--target {spec!r}: full+N% is given twice")
            if not (pct.startswith("+") and pct.endswith("%")):
                raise InputError(f"--target {part!r}: full+N% (e.g. full+5%: within 5 % of the whole plan's sigma)")
            try:
                full = float(pct[1:-1]) / 100.0
            except ValueError:
                raise InputError(f"--target {part!r}: {pct[1:-1]!r} is not a number") from None
            if not (math.isfinite(full) and full >= 0):
                raise InputError(f"--target {part!r}: a percentage >= 0")
            continue
        name, sep, val = part.partition("=")
        if not sep or name not in SIGMA_UNITS:
            raise InputError(f"--target {part!r}: MAP=SIGMA with MAP one of {', '.join(sorted(SIGMA_UNITS))}, "
                             "or full+N%, or none")
        if name in out:
            raise InputError(f"--target {spec!r}: {name} is named twice; give each map once")
        try:
            out[name] = float(val)
        except ValueError:
            raise InputError(f"--target {part!r}: {val!r} is not a number") from None
    return out, full


#: the options' names on the command line (for a refused --resume)
OPTION_FLAGS = {"initial": "--initial-leds", "batch": "--batch-leds", "criterion": "--criterion",
                "targets": "--target", "min_gain": "--min-gain", "budget_shots": "--budget",
                "budget_s": "--budget"}


def check_resume(work: str | Path, opts: "AdaptiveOptions | None") -> None:
    """``--resume`` into ``work``: refuse (``InputError``, before the rig starts) to continue an
    adaptive capture without ``--adaptive`` (a fixed-plan resume would take every candidate),
    a fixed-plan capture with ``--adaptive``, or an adaptive capture with other options (named,
    with the value there and the one given)."""
    from dualscale.capture.journal import JOURNAL, Journal

    path = Path(work) / JOURNAL
    if not path.is_file():
        return
    journal = Journal(path)
    starts = journal.of("adaptive")
    if starts and opts is None:
        raise InputError(f"{work} holds an adaptive capture: continue it with --adaptive and its options "
                         f"({describe_options(starts[0]['options'])}), or choose another folder")
    if opts is None:
        return
    if not starts and journal.of("shot"):
        raise InputError(f"{work} holds a capture of a fixed plan (no --adaptive): continue it without --adaptive, "
                         f"or choose another folder")
    if starts:
        diff = option_differences(starts[0]["options"], _jsonable(asdict(opts)))
        if diff:
            raise InputError(f"{work}: --resume with other adaptive options than the capture there: {'; '.join(diff)}; "
                             f"use the same options or another folder")


def _show(key: str, v: Any) -> str:
    if v is None:
        return "none"
    if key == "targets":  # v: (targets, full_target), as target_spec takes them
        return target_spec(*v)
    if key == "budget_s":
        return f"{v:g}s"
    return f"{v:g}" if isinstance(v, float) else str(v)


def target_spec(targets: dict[str, float] | None, full_target: float | None) -> str:
    """The ``--target`` that gives ``targets`` and ``full_target``: ``normal=0.5,full+5%``, or ``none``."""
    parts = [f"{k}={x:g}" for k, x in (targets or {}).items()]
    if full_target is not None:
        parts.append(f"full+{100 * full_target:g}%")
    return ",".join(parts) or "none"


def _merged(opts: dict[str, Any]) -> dict[str, Any]:
    """The stored options with ``targets`` and ``full_target`` as one ``--target`` value."""
    out = {k: v for k, v in opts.items() if k != "full_target"}
    out["targets"] = (opts.get("targets") or {}, opts.get("full_target"))
    return out


def describe_options(opts: dict[str, Any]) -> str:
    """The stored options as the command line gives them (those set), e.g. ``--budget (shots) 40``."""
    defaults, opts = _merged(_jsonable(asdict(AdaptiveOptions()))), _merged(opts)
    parts = [f"{flag} {_show(k, opts.get(k))}" for k, flag in OPTION_FLAGS.items()
             if opts.get(k) != defaults.get(k) or k == "criterion"]
    return ", ".join(parts)


def option_differences(there: dict[str, Any], given: dict[str, Any]) -> list[str]:
    """One line per option that differs: ``--budget (shots): 40 there, none given``."""
    out = []
    there, given = _merged(there), _merged(given)
    for k in sorted(set(there) | set(given)):
        if there.get(k) != given.get(k):
            flag = OPTION_FLAGS.get(k, k)
            out.append(f"{flag}: {_show(k, there.get(k))} there, {_show(k, given.get(k))} given")
    return out


def parse_budget(spec: str | None) -> tuple[int | None, float | None]:
    """``--budget N`` (shots) or ``--budget Ts`` / ``Tmin`` (device time): ``(shots, seconds)``."""
    if spec is None:
        return None, None
    s = str(spec).strip().lower()
    try:
        if s.endswith("min"):
            return None, float(s[:-3]) * 60.0
        if s.endswith("s"):
            return None, float(s[:-1])
        return int(s), None
    except ValueError:
        raise InputError(f"--budget {spec!r}: a shot count (e.g. 80) or a device time (e.g. 300s, 5min)") from None
