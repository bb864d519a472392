"""The adaptive capture's options and their command-line forms (issue 27; docs/CAPTURE.md,
"Adaptive capture"): light to import (the command line's parser builds from them), the loop
itself is :mod:`.loop`."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from dualscale.errors import InputError

CRITERIA = ("D", "A")
"""The optimal-design criteria (:mod:`.design`)."""

#: map -> the default target median sigma (map units, as fit.json's uncertainty summary)
DEFAULT_TARGETS: dict[str, float] = {}


@dataclass
class AdaptiveOptions:
    """How the adaptive capture decides (module doc).  ``targets``: map -> median sigma to stop
    at; ``budget_shots`` / ``budget_s``: the most shots / seconds of device time (floor);
    ``batch``: LEDs per round (``None``: :func:`auto_batch`)."""

    initial: int = 12
    batch: int | None = None
    criterion: str = "D"
    targets: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_TARGETS))
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
        if self.budget_shots is not None and self.budget_shots < 1:
            raise InputError(f"--budget {self.budget_shots}: a positive shot count (e.g. 80) or device time (e.g. 300s)")
        if self.budget_shots is not None and self.budget_shots < 2 * self.initial + 2:
            raise InputError(f"--budget {self.budget_shots} shots: the first round alone takes {2 * self.initial + 2} "
                             f"({self.initial} LEDs at P0 and P90, and the back light)")
        if self.budget_s is not None and not self.budget_s > 0:
            raise InputError(f"--budget {self.budget_s}s: a positive device time")


def parse_targets(spec: str | None) -> dict[str, float]:
    """``--target MAP=SIGMA,...`` (e.g. ``normal=0.5,roughness=0.01``; sigma in the map's units:
    the normal in degrees) over :data:`DEFAULT_TARGETS`; ``InputError`` naming the bad entry."""
    from dualscale.formats.maps import SIGMA_UNITS

    out = dict(DEFAULT_TARGETS)
    if not spec:
        return out
    for part in str(spec).split(","):
        name, sep, val = part.strip().partition("=")
        if not sep or name not in SIGMA_UNITS:
            raise InputError(f"--target {part!r}: MAP=SIGMA with MAP one of {', '.join(sorted(SIGMA_UNITS))}")
        if name in out and name not in DEFAULT_TARGETS:
            raise InputError(f"--target {spec!r}: {name} is named twice; give each map once")
        try:
            out[name] = float(val)
        except ValueError:
            raise InputError(f"--target {part!r}: {val!r} is not a number") from None
    return out


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
    if key == "targets":
        return ",".join(f"{k}={x:g}" for k, x in v.items()) or "none"
    if key == "budget_s":
        return f"{v:g}s"
    return f"{v:g}" if isinstance(v, float) else str(v)


def describe_options(opts: dict[str, Any]) -> str:
    """The stored options as the command line gives them (those set), e.g. ``--budget (shots) 40``."""
    defaults = _jsonable(asdict(AdaptiveOptions()))
    parts = [f"{flag} {_show(k, opts.get(k))}" for k, flag in OPTION_FLAGS.items()
             if opts.get(k) != defaults.get(k) or k == "criterion"]
    return ", ".join(parts)


def option_differences(there: dict[str, Any], given: dict[str, Any]) -> list[str]:
    """One line per option that differs: ``--budget (shots): 40 there, none given``."""
    out = []
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


def _jsonable(obj: Any) -> Any:
    return json.loads(json.dumps(obj, default=str))
