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

The calibration-target plans (:data:`TARGET_PLANS`) capture the parts of a calibration session
(``captures.json``, :mod:`dualscale.formats.captures`; the groups ``dualscale synth-targets``
writes, :func:`dualscale.sim.targets.write_session`) with the cameras given (``cameras``), each
shot carrying its capture-set ``target`` and the roles it triggers:

* ``white-sheet`` -- the white diffuser sheet under every selected LED, the diffuse group and back
  light 0: all cameras at P0, the micro camera again at P90 (its analyser; the other cameras have
  their one image from the P0 shot).  Order: the lights at P0, then at P90 (one servo move);
* ``chart`` -- the ColorChecker under every selected LED and the diffuse group (no back light):
  first centred, imaged whole by the mid and polar cameras (no analyser); then moved 24 times so
  that patch k fills the micro camera's field, each patch at P0 and P90 (target ``patch``);
* ``dot-grid`` -- the dot grid under the diffuse group, micro camera (recorded as camera
  ``micro_dots``, as ``write_session`` does: the full-resolution micro camera);
* ``polarization`` -- the glossy dark target under every selected LED, micro camera, the analyser
  swept over ``0, 10, ..., 170`` degrees (:data:`POL_STEP_CDEG`; absolute servo angles), up and
  down on alternate LEDs (one short servo move between shots).

Each change of what lies on the holder is a :class:`Setup`, with the line the operator is given
(:meth:`Setup.prompt`); the capture stops there until it is done (:mod:`.session`).
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

POL_STEP_CDEG = 1000
"""The polarisation sweep's analyser step [centidegrees] (``SynthConfig.pol_step_deg``)."""

TARGETS = ("white_sheet", "chart", "patch", "dot_grid", "polarization")
"""Capture-set targets a shot can have (:data:`dualscale.formats.captures.TARGETS` less ``dark``)."""


@dataclass(frozen=True)
class Setup:
    """What lies on the sample holder: a calibration ``target`` (``white_sheet``, ``chart``,
    ``dot_grid``, ``polarization``) and, for the chart, the ``patch`` (0..23) moved under the
    micro camera (``None``: the chart centred)."""

    target: str
    patch: int | None = None

    def prompt(self) -> str:
        """The operator's instruction for this setup (one line)."""
        if self.target == "white_sheet":
            return ("put the white diffuser sheet on the sample holder, flat, covering the micro camera's field "
                    "(the holder's white markers visible to the mid camera)")
        if self.target == "chart" and self.patch is None:
            return ("put the ColorChecker on the holder, centred, dark skin at the top left: the mid and polar "
                    "cameras see all of it")
        if self.target == "chart":
            from dualscale.calib.colourref import patch_names

            return (f"move the ColorChecker so that patch {self.patch} ({patch_names()[self.patch]}) fills the "
                    f"micro camera's field")
        if self.target == "dot_grid":
            return "put the dot-grid target (125 um pitch) under the micro camera, in focus"
        if self.target == "polarization":
            return "put the glossy dark polarisation target on the holder under the micro camera"
        raise InputError(f"unknown target {self.target!r}")


@dataclass(frozen=True)
class Shot:
    """One light state: ``kind`` ``led`` | ``backlight`` | ``diffuse``, its ``index`` (``None``
    for the diffuse group), and the analyser angle ``analyzer_cdeg`` [centidegrees relative to
    the LED polariser; the polarisation sweep's are absolute servo angles; ``None`` = leave the
    analyser where it is, for cameras without one].  Calibration-target plans add the camera
    ``roles`` the shot triggers (``None``: the plan's), its capture-set ``target``
    (:data:`TARGETS`) and ColorChecker ``patch``."""

    kind: str
    index: int | None
    analyzer_cdeg: int | None
    roles: tuple[str, ...] | None = None
    target: str | None = None
    patch: int | None = None

    @property
    def key(self) -> str:
        """A stable name, e.g. ``led017_p09000``, ``diffuse_nopol``; a target shot's starts with
        its target (``patch07_led032_p00000``, ``white_sheet_diffuse_p00000``)."""
        src = self.kind if self.index is None else f"{self.kind}{self.index:03d}"
        pol = "nopol" if self.analyzer_cdeg is None else f"p{self.analyzer_cdeg:05d}"
        if self.target is None:
            return f"{src}_{pol}"
        what = self.target if self.patch is None else f"{self.target}{self.patch:02d}"
        return f"{what}_{src}_{pol}"

    @property
    def source(self) -> rm.Source:
        return {"led": rm.Source.LED, "backlight": rm.Source.BACKLIGHT, "diffuse": rm.Source.DIFFUSE}[self.kind]

    @property
    def setup(self) -> Setup | None:
        """What must lie on the holder for this shot (``None`` for a sample's shots)."""
        if self.target is None:
            return None
        return Setup("chart" if self.target == "patch" else self.target, self.patch)

    def to_json(self) -> dict:
        d: dict = {"kind": self.kind, "index": self.index, "analyzer_cdeg": self.analyzer_cdeg}
        if self.target is not None:  # a sample's shots keep their record (a resumed capture's identity)
            d.update(roles=None if self.roles is None else list(self.roles), target=self.target, patch=self.patch)
        return d

    @classmethod
    def from_json(cls, d: dict) -> "Shot":
        return cls(str(d["kind"]), None if d.get("index") is None else int(d["index"]),
                   None if d.get("analyzer_cdeg") is None else int(d["analyzer_cdeg"]),
                   None if d.get("roles") is None else tuple(str(r) for r in d["roles"]),
                   None if d.get("target") is None else str(d["target"]),
                   None if d.get("patch") is None else int(d["patch"]))


@dataclass(frozen=True)
class Plan:
    """``name``, the ``shots`` in capture order, and the camera ``roles`` they trigger (a shot
    with its own ``roles`` triggers those).  ``names``: the camera name a role has in a capture
    set when it is not the role (the dot grid's ``micro_dots``)."""

    name: str
    shots: tuple[Shot, ...]
    roles: tuple[str, ...]
    names: tuple[tuple[str, str], ...] = ()

    @property
    def targets(self) -> bool:
        """Whether this is a calibration-target plan (its output is a capture set)."""
        return any(s.target is not None for s in self.shots)

    def roles_of(self, shot: Shot) -> tuple[str, ...]:
        return self.roles if shot.roles is None else shot.roles

    def camera_name(self, role: str) -> str:
        return dict(self.names).get(role, role)

    def setups(self) -> list[tuple[Setup | None, list[Shot]]]:
        """The shots in runs of one setup, in capture order."""
        out: list[tuple[Setup | None, list[Shot]]] = []
        for s in self.shots:
            if out and out[-1][0] == s.setup:
                out[-1][1].append(s)
            else:
                out.append((s.setup, [s]))
        return out

    def to_json(self) -> dict:
        d = {"name": self.name, "roles": list(self.roles), "shots": [s.to_json() for s in self.shots]}
        if self.names:
            d["names"] = dict(self.names)
        return d


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


def _target_lights(lights: str, backlight: bool) -> list[tuple[str, int | None]]:
    """``write_session``'s lights (:func:`dualscale.sim.targets.lights`): the selected LEDs, the
    diffuse group and (``backlight``) back light 0."""
    return [("led", i) for i in select_leds(lights)] + [("diffuse", None)] + ([("backlight", 0)] if backlight else [])


def _cameras(name: str, cameras: tuple[str, ...] | None, need: tuple[str, ...] = ()) -> tuple[str, ...]:
    cams = tuple(rm.CAMERA_NAMES) if cameras is None else tuple(cameras)
    bad = [c for c in cams if c not in rm.CAMERA_NAMES]
    if bad:
        raise InputError(f"plan {name!r}: unknown camera(s) {bad}: the rig's are {', '.join(rm.CAMERA_NAMES)}")
    missing = [c for c in need if c not in cams]
    if missing or not cams:
        raise InputError(f"plan {name!r} needs the {', '.join(missing or rm.CAMERA_NAMES)} camera "
                         f"(--camera {(missing or ['micro'])[0]}=SPEC)")
    return tuple(c for c in rm.CAMERA_NAMES if c in cams)  # the rig's order


def white_sheet_plan(lights: str = "ALL", cameras: tuple[str, ...] | None = None) -> Plan:
    """The white sheet (module doc): every light at P0 with all ``cameras``, then the micro camera's
    P90 shots."""
    cams = _cameras("white-sheet", cameras)
    p0, p90 = ANALYZERS_CDEG
    srcs = _target_lights(lights, backlight=True)
    if "micro" not in cams:
        shots = [Shot(k, i, None, cams, "white_sheet") for k, i in srcs]
    else:
        shots = [Shot(k, i, p0, cams, "white_sheet") for k, i in srcs] + \
                [Shot(k, i, p90, ("micro",), "white_sheet") for k, i in srcs]
    return Plan("white-sheet", tuple(shots), cams)


def chart_plan(lights: str = "ALL", cameras: tuple[str, ...] | None = None) -> Plan:
    """The ColorChecker (module doc): centred for the mid and polar cameras, then each patch under
    the micro camera at P0 and P90 (alternating which comes first: one servo move per patch)."""
    from dualscale.calib.colourref import N_PATCHES

    cams = _cameras("chart", cameras)
    srcs = _target_lights(lights, backlight=False)
    whole = tuple(c for c in cams if c != "micro")
    shots = [Shot(k, i, None, whole, "chart") for k, i in srcs] if whole else []
    if "micro" in cams:
        for p in range(N_PATCHES):
            for a in (ANALYZERS_CDEG if p % 2 == 0 else ANALYZERS_CDEG[::-1]):
                shots += [Shot(k, i, a, ("micro",), "patch", p) for k, i in srcs]
    return Plan("chart", tuple(shots), cams)


def dot_grid_plan(lights: str = "ALL", cameras: tuple[str, ...] | None = None) -> Plan:
    """The dot grid (module doc): the diffuse group, micro camera as ``micro_dots``; ``lights`` is
    not used."""
    _cameras("dot-grid", cameras, need=("micro",))
    return Plan("dot-grid", (Shot("diffuse", None, None, ("micro",), "dot_grid"),), ("micro",),
                names=(("micro", "micro_dots"),))


def polarization_plan(lights: str = "ALL", cameras: tuple[str, ...] | None = None) -> Plan:
    """The polarisation sweep (module doc): per selected LED, the analyser at 0..170 degrees."""
    _cameras("polarization", cameras, need=("micro",))
    angles = list(range(0, 18000, POL_STEP_CDEG))
    shots = [Shot("led", i, a, ("micro",), "polarization")
             for n, i in enumerate(select_leds(lights)) for a in (angles if n % 2 == 0 else angles[::-1])]
    return Plan("polarization", tuple(shots), ("micro",))


PLANS = {"micro": micro_plan, "mid": mid_plan, "white-sheet": white_sheet_plan, "chart": chart_plan,
         "dot-grid": dot_grid_plan, "polarization": polarization_plan}
"""``name -> plan builder(lights)`` (the target plans also take ``cameras``)."""

TARGET_PLANS = ("white-sheet", "chart", "dot-grid", "polarization")
"""The calibration-target plans, in the order their parts appear in a capture set."""


def make_plan(name: str, lights: str = "ALL", cameras: tuple[str, ...] | None = None) -> Plan:
    """Plan ``name`` (:data:`PLANS`) over the LEDs ``lights`` (:func:`select_leds`); a target plan
    with the rig ``cameras`` given (roles; default all the rig's), the others ignore it."""
    if name not in PLANS:
        raise InputError(f"unknown plan {name!r}: one of {', '.join(PLANS)}")
    if name in TARGET_PLANS:
        return PLANS[name](lights, cameras)
    return PLANS[name](lights)
