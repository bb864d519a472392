"""Capture plans: which light states a capture takes, with which cameras (issue 14 §3).

A plan is a list of :class:`Shot` (one light state: a source and an analyser angle) and the
camera roles (``regmap.CAMERA_NAMES``) whose trigger lines fire on each.  Every shot becomes one
image per camera in the dataset, merged from its HDR brackets (:mod:`.session`).

Plans (:data:`PLANS`; ``dualscale capture PLAN``):

* ``micro`` -- the micro photometric dataset (supplementary Sec. 3-4): every selected LED under
  the analyser at P0 and at P90, and back light 0 under both (the rig always takes the back-lit
  image: it is how an opaque sample shows it is opaque), with the micro camera -- the shots
  ``dualscale synth --dataset`` renders.  Order: the LEDs then the back light at P0, the same at
  P90 (one servo move; the back light's two long exposures apart, for its duty limit);
* ``mid`` -- the mid-range guidance image (Sec. 7): the diffuse group, mid camera, no analyser.

LED selection (``--lights``, :func:`select_leds`): ``ALL``; ``MODn`` (every n-th LED id);
``ROWa+b+...`` (whole dome rows, 0 = zenith, the regmap ring layout); or a file with LED ids
(whitespace- or comma-separated integers; ``#`` starts a comment).

The calibration-target plans (white sheet, ColorChecker, dot grid, polarisation sweep) are not
built yet: their captures still come from ``dualscale synth-targets`` (docs/CAPTURE.md).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from dualscale.errors import InputError
from dualscale.geometry.dome import ring_layout
from dualscale.protocol import regmap as rm

ANALYZERS_CDEG = (rm.POL_P0_CDEG, rm.POL_P90_CDEG)
"""The micro plan's analyser angles [centidegrees, relative to each LED's polariser]: P0, P90."""


@dataclass(frozen=True)
class Shot:
    """One light state: ``kind`` ``led`` | ``backlight`` | ``diffuse``, its ``index`` (``None``
    for the diffuse group), and the analyser angle ``analyzer_cdeg`` [centidegrees relative to
    the LED polariser; ``None`` = leave the analyser where it is, for cameras without one]."""

    kind: str
    index: int | None
    analyzer_cdeg: int | None

    @property
    def key(self) -> str:
        """A stable name, e.g. ``led017_p09000``, ``diffuse_nopol``."""
        src = self.kind if self.index is None else f"{self.kind}{self.index:03d}"
        pol = "nopol" if self.analyzer_cdeg is None else f"p{self.analyzer_cdeg:05d}"
        return f"{src}_{pol}"

    @property
    def source(self) -> rm.Source:
        return {"led": rm.Source.LED, "backlight": rm.Source.BACKLIGHT, "diffuse": rm.Source.DIFFUSE}[self.kind]

    def to_json(self) -> dict:
        return {"kind": self.kind, "index": self.index, "analyzer_cdeg": self.analyzer_cdeg}

    @classmethod
    def from_json(cls, d: dict) -> "Shot":
        return cls(str(d["kind"]), None if d.get("index") is None else int(d["index"]),
                   None if d.get("analyzer_cdeg") is None else int(d["analyzer_cdeg"]))


@dataclass(frozen=True)
class Plan:
    """``name``, the ``shots`` in capture order, and the camera ``roles`` they trigger."""

    name: str
    shots: tuple[Shot, ...]
    roles: tuple[str, ...]

    def to_json(self) -> dict:
        return {"name": self.name, "roles": list(self.roles), "shots": [s.to_json() for s in self.shots]}


def select_leds(spec: str) -> list[int]:
    """LED ids for ``--lights`` (module doc); ``InputError`` naming what is wrong."""
    s = str(spec).strip()
    up = s.upper()
    if up == "ALL":
        return list(range(rm.N_LEDS))
    m = re.fullmatch(r"MOD(\d+)", up)
    if m:
        n = int(m.group(1))
        if n < 1:
            raise InputError(f"--lights {spec!r}: MODn needs n >= 1")
        return list(range(0, rm.N_LEDS, n))
    m = re.fullmatch(r"ROW(\d+(?:\+\d+)*)", up)
    if m:
        rows = [int(r) for r in m.group(1).split("+")]
        layout = ring_layout()
        n_rows = len(rm.DOME_COUNTS)
        bad = [r for r in rows if not 0 <= r < n_rows]
        if bad:
            raise InputError(f"--lights {spec!r}: rows {bad} outside 0..{n_rows - 1} (0 = zenith)")
        return [i for i, (row, _, _) in enumerate(layout) if row in rows]
    path = Path(s)
    if not path.is_file():
        raise InputError(f"--lights {spec!r}: use ALL, MODn, ROWa+b or a file of LED ids (no such file)")
    ids: list[int] = []
    for ln, line in enumerate(path.read_text().splitlines(), 1):
        for tok in re.split(r"[\s,]+", line.split("#", 1)[0].strip()):
            if not tok:
                continue
            if not tok.isdigit() or int(tok) >= rm.N_LEDS:
                raise InputError(f"{path}:{ln}: {tok!r} is not an LED id 0..{rm.N_LEDS - 1}")
            ids.append(int(tok))
    if not ids:
        raise InputError(f"{path}: no LED ids")
    if len(set(ids)) != len(ids):
        raise InputError(f"{path}: LED ids repeat: {sorted(i for i in set(ids) if ids.count(i) > 1)}")
    return ids


def micro_plan(lights: str = "ALL") -> Plan:
    """The micro photometric plan (module doc): for P0 then P90, the LEDs then back light 0."""
    leds = select_leds(lights)
    shots = [s for a in ANALYZERS_CDEG for s in [Shot("led", i, a) for i in leds] + [Shot("backlight", 0, a)]]
    return Plan("micro", tuple(shots), ("micro",))


def mid_plan(lights: str = "ALL") -> Plan:
    """The mid-range guidance plan: the diffuse group, mid camera (``lights`` is ignored)."""
    return Plan("mid", (Shot("diffuse", None, None),), ("mid",))


PLANS = {"micro": micro_plan, "mid": mid_plan}
"""``name -> plan builder(lights)``."""


def make_plan(name: str, lights: str = "ALL") -> Plan:
    if name not in PLANS:
        raise InputError(f"unknown plan {name!r}: one of {', '.join(PLANS)} (the calibration-target plans "
                         "are not built yet: use dualscale synth-targets)")
    return PLANS[name](lights)
