"""``dualscale capture``: a plan on the rig, frames matched to device events, HDR, resume.

The capture of one :class:`~dualscale.capture.plan.Plan` into ``DATASET`` (issue 14 §3;
supplementary Sec. 3, the rig's sequence of lights, analyser angles and exposures):

1. **Dark frames** at the metering exposure (lights off, software trigger).
2. **Metering** (:func:`dualscale.calib.hdr.meter`'s rule, run as rig sequences): every shot is
   exposed once; a shot with clipped pixels is metered again 8x shorter, one whose peak is
   under 5 % of full scale 8x longer (up to ``max_exposure_s``); the usable shot gives its
   brackets with :func:`dualscale.calib.hdr.plan_brackets` (every pixel one sample in
   [5 %, 80 %] of the white level), as powers of ``2^ev_step`` so the firmware's bracket rule
   ``EXPOSURE_US << (k * EV_STEP)`` (PROTOCOL.md §3) takes them in one step.
3. **Dark frames** at the shortest and longest exposure of the plan.
4. **The capture**: the shots as device-master sequences (PROTOCOL.md §3.1) in gate mode (each
   bracket's exposure is its trigger pulse), ``FRAME_GAP_US`` = the cameras' dead time, batches
   of at most ``batch_steps`` steps.  Every frame is **matched to its event** in the device FIFO
   (``TRIGGER``, ARG = bracket, STEP = step, TS_US): by the device clock when the camera reports
   it (``metadata["device_t_us"]``), else by order when the counts agree.  A frame with no event,
   an event with no frame, a frame whose seen light or analyser differs from its step
   (``metadata["lights"]``, ``["polarizer_cdeg"]`` when the camera reports them), or a step cut
   short by an abort is **taken again** (journal ``retake`` with the reason), never kept; after
   ``retakes`` failed attempts the capture stops with :class:`~dualscale.errors.CameraError`
   (``--resume`` continues).  The run keeps the rig's host watchdog on
   (:meth:`dualscale.rig.client.RigClient.run`), so the lights go off if this host dies.
5. **Write as you go**: each accepted shot's frames land as EXR (temporary file + rename) under
   ``frames/<role>/``, then one journal line (:mod:`.journal`).  ``resume=True`` skips every unit
   the journal holds; a capture killed at any moment loses at most the batch in flight and never
   duplicates a frame.
6. **Merge**: each shot's brackets become one image (:func:`dualscale.calib.hdr.merge_debevec`,
   linear, dark-subtracted with the dark model fitted to the dark frames, samples at or above
   the camera's declared white level less the merge margin excluded:
   :class:`dualscale.calib.hdr.WhiteLevel`), written as ``dn_normalized`` at the shot's shortest
   exposure (dark signal included, so ``dualscale calibrate``/``digitize --calibration`` read it
   like any raw capture; pixels clipped in every bracket are set to the white level, at or above
   the image's ``saturation``), plus the dark frames, into the photometric dataset
   (``DATASET/manifest.json``, :class:`dualscale.formats.dataset.DatasetWriter`).

``DATASET/capture.json`` records the rig identity and firmware version, each camera's spec,
serial, sensor and settings, the calibration id, the date and the plan.

A step keeps its light on for its settle and brackets: the bracket plan keeps that within the
rig's ``LED_MAX_ON_MS`` (read from the device; less a full servo turn), and a batch the firmware
refuses for a light's duty budget (``LED_DUTY`` at step k) runs as steps before k, then the rest
in a sequence of their own (:meth:`CaptureSession._run_batch`).

**Calibration targets** (the plans of :data:`dualscale.capture.plan.TARGET_PLANS`): ``out`` is
a capture set (``captures.json``, :mod:`dualscale.formats.captures`) that several plans fill.
A plan's journal, frames and record live in ``out/parts/<plan>/``; it runs setup by setup
(``operator(setup)`` first: the operator, or the virtual one, puts the target in place; then
metering, from the last metered exposure of the same light, and capture), with each shot
triggering only its own cameras.  Instead of step 6 the brackets themselves are the output, as
``dualscale calibrate`` does its own HDR merge and white-level handling: the part (the record's
``captureset``: rig, camera records with sensitivities and declared white level, one group per
shot and camera -- target, light, patch, analyser (the micro camera's; relative P0/P90, absolute
on the polarisation sweep), exposures, frame files --, dark frames at the metering exposure and
at each camera's shortest and longest exposure, the holder's ``markers`` and ``chart`` corners
and layout) is recorded, then :func:`write_capture_set` rewrites ``captures.json`` and
``images/`` from every finished part through :class:`~dualscale.formats.captures.CaptureWriter`.
The dot grid's camera is recorded as ``micro_dots`` (``dualscale synth-targets``' name).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import numpy as np

from dualscale.calib.chart import ChartLayout
from dualscale.calib.hdr import WhiteLevel, merge_debevec, plan_brackets
from dualscale.calib.radiometric import dark_at, fit_dark
from dualscale.errors import CameraError, CameraTimeout, FormatError, InputError, RigError
from dualscale.formats.atomic import jsonable as _jsonable, write_json
from dualscale.formats.dataset import DatasetWriter
from dualscale.formats.exr import read_exr, write_exr
from dualscale.geometry.cameras import Camera as GeometryCamera, micro_camera, mid_camera, polar_camera
from dualscale.geometry.dome import DomeGeometry
from dualscale.protocol import regmap as rm
from dualscale.rig.client import ACTIVE, DEFAULT_WATCHDOG_MS, RigClient, SequenceRejected
from dualscale.rig.events import Event
from dualscale.rig.sequence import Step, schedule, servo_travel_us, split_words

from .camera import Camera, Frame, TriggerInfo, TriggerMode, frame_metadata
from .captureset import FORMAT, PARTS, _check_parts, _holder_record, read_capture_record, read_parts, write_capture_set  # noqa: F401
from .journal import JOURNAL, Journal
from .plan import Plan, Setup, Shot

VERSION = 1
METER_LOW, METER_HIGH = 0.05, 0.8  # metering and bracket targets, fractions of the white level
METER_STEP = 8.0                   # metering: 8x shorter or longer (calib.hdr.meter's rule)
MATCH_TOLERANCE_US = 50            # a frame's device time within this of its TRIGGER event


@dataclass
class CaptureOptions:
    """How to capture (module doc).  Times in seconds unless named ``_us``."""

    intensity: int = rm.INTENSITY_MAX
    settle_us: int = 2000
    servo_margin_us: int = 20000
    meter_exposure_s: float = 0.01
    max_exposure_s: float = 4.0
    ev_step: int = 2
    max_brackets: int = rm.MAX_BRACKETS
    batch_steps: int = 64
    retakes: int = 3
    meter_rounds: int = 8
    trigger: str = "device"
    rig_id: str | None = None
    calibration_id: str | None = None
    timeout_margin_s: float = 30.0
    collect_quiet_s: float = 3.0
    watchdog_ms: int = DEFAULT_WATCHDOG_MS

    def __post_init__(self) -> None:
        if self.trigger not in ("device", "camera"):
            raise InputError(f"--trigger {self.trigger!r}: device or camera")
        if self.trigger == "camera":
            raise InputError("--trigger camera (camera-master, PROTOCOL.md §3.2) is not supported by "
                             "`dualscale capture` yet: HDR brackets need device-master gate triggers; use --trigger device")
        if not 1 <= self.ev_step <= rm.MAX_EV_STEP:
            raise InputError(f"ev_step {self.ev_step} outside 1..{rm.MAX_EV_STEP}")
        if not 0 < self.intensity <= rm.INTENSITY_MAX:
            raise InputError(f"intensity {self.intensity} outside 1..{rm.INTENSITY_MAX}")
        if not 0 < self.meter_exposure_s <= self.max_exposure_s <= rm.MAX_PHASE_US / 1e6:
            raise InputError(f"need 0 < meter_exposure_s <= max_exposure_s <= {rm.MAX_PHASE_US / 1e6:g} s")


@dataclass
class ShotPlan:
    """A shot's brackets: the firmware's ``exposure_us``, ``brackets`` and ``ev_step``."""

    exposure_us: int
    brackets: int
    ev_step: int

    def exposures_s(self) -> list[float]:
        return [(self.exposure_us << (k * self.ev_step)) / 1e6 for k in range(self.brackets)]


@dataclass
class CaptureSummary:
    """What a capture did: counts and times (the CLI prints it; docs/CAPTURE.md measures it)."""

    shots: int = 0
    frames: int = 0
    retakes: int = 0
    retake_reasons: dict[str, int] = field(default_factory=dict)
    resumed_shots: int = 0
    sequences: int = 0
    sequence_device_s: float = 0.0   # Σ scheduled device time of every sequence (metering included)
    capture_device_s: float = 0.0    # Σ scheduled device time of the capture sequences (retakes included)
    floor_s: float = 0.0             # Σ settle + exposure + gap (+ servo) of the plan's steps
    capture_wall_s: float = 0.0      # wall time of the capture sequences (upload to last frame)
    meter_wall_s: float = 0.0
    total_wall_s: float = 0.0
    link_reconnects: int = 0
    events_dropped: int = 0
    clipped_pixels: int = 0
    dataset: str = ""

    def lines(self) -> list[str]:
        out = [f"captured {self.shots} shot{'s' if self.shots != 1 else ''} ({self.frames} frames; "
               f"{self.resumed_shots} from an earlier run) "
               f"in {self.total_wall_s:.1f} s (metering {self.meter_wall_s:.1f} s, capture {self.capture_wall_s:.1f} s); "
               f"the capture sequences ran {self.capture_device_s:.1f} s on the device clock, for a physical floor "
               f"of {self.floor_s:.1f} s (a simulator faster than real time runs its clock ahead of the wall)"]
        if self.retakes:
            out.append(f"taken again: {self.retakes} ({', '.join(f'{k}: {v}' for k, v in self.retake_reasons.items())})")
        if self.events_dropped or self.link_reconnects:
            out.append(f"link: {self.link_reconnects} reconnects, {self.events_dropped} events dropped by the FIFO")
        if self.clipped_pixels:
            out.append(f"{self.clipped_pixels} pixel(s) clipped in every bracket (marked clipped in the dataset)")
        out.append(f"dataset: {self.dataset}")
        return out


def _sha(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def geometry_for(role: str, camera: Camera) -> GeometryCamera:
    """The rig camera ``role`` (``regmap.CAMERA_NAMES``) at this camera's sensor size: the backend's
    own ``geometry()`` when it has one (the simulated cameras), else rig.toml's camera with the
    sensor's pixel count (micro: ``pixel_um`` read as the object-side pitch)."""
    own = getattr(camera, "geometry", None)
    if callable(own):
        g = own()
        if g.name != role:
            raise InputError(f"camera {camera.spec!r} is the rig's {g.name!r} camera, not {role!r}")
        return g
    s = camera.sensor()
    if role == "micro":
        return micro_camera(s.width, s.pixel_um, height=s.height)
    if role == "mid":
        return mid_camera(s.width)
    if role.startswith("polar"):
        return polar_camera(int(role[-1]), s.width)
    raise InputError(f"unknown camera role {role!r}: one of {', '.join(rm.CAMERA_NAMES)}")


def colour_space(camera: Camera) -> str:
    """The dataset colour space of a camera's raw frames: ``camera_raw:<sensitivities>`` from its
    settings (``colour_space``, or the ``sensitivity`` a backend knows, e.g. the simulated
    cameras'), else ``camera_raw:<serial>`` (the calibration's CCM is then per camera)."""
    st = camera.settings()
    if st.get("colour_space"):
        return str(st["colour_space"])
    if st.get("sensitivity"):
        return f"camera_raw:{st['sensitivity']}"
    return f"camera_raw:{camera.serial}"


def _trigger_mask(roles: tuple[str, ...]) -> int:
    return sum(1 << rm.TRIGGER_NAMES.index(r) for r in roles)


def _analyzer_deg(shot: Shot, camera: GeometryCamera) -> tuple[float | None, bool]:
    if shot.analyzer_cdeg is None or not camera.has_analyzer:
        return None, False
    return shot.analyzer_cdeg / 100.0, True


class CaptureSession:
    """One capture (module doc).  ``rig``: an opened :class:`~dualscale.rig.client.RigClient`;
    ``cameras``: ``role -> Camera`` for every role the plan triggers (opened, not prepared);
    ``out``: the dataset folder; ``progress(done, total, what)`` is called after each shot."""

    def __init__(self, rig: RigClient, cameras: dict[str, Camera], plan: Plan, out: str | Path,
                 opts: CaptureOptions | None = None, resume: bool = False,
                 progress: Callable[[int, int, str], None] | None = None,
                 operator: Callable[[Setup], None] | None = None, holder: dict[str, Any] | None = None) -> None:
        missing = [r for r in plan.roles if r not in cameras]
        if missing:
            raise InputError(f"plan {plan.name!r} needs the {', '.join(missing)} camera(s): add --camera "
                             f"{missing[0]}=SPEC (or a sim:{missing[0]} spec)")
        self.rig, self.plan, self.out = rig, plan, Path(out)
        self.work = self.out / PARTS / plan.name if plan.targets else self.out
        self.cameras = {r: cameras[r] for r in plan.roles}
        self.opts = opts or CaptureOptions()
        self.progress = progress
        self.operator = operator
        self.holder = _holder_record(holder or {})
        self.geometry = {r: geometry_for(r, c) for r, c in self.cameras.items()}
        self.white = {r: WhiteLevel.uniform(c.sensor().white_level) for r, c in self.cameras.items()}
        self.summary = CaptureSummary()
        self._retake_count: dict[str, int] = {}
        if plan.targets:
            self._check_targets()
        self._open_journal(resume)

    # ------------------------------------------------------------------ bookkeeping
    def _identity(self) -> dict[str, Any]:
        ident = self.rig.identity
        return {"plan": self.plan.to_json(), "cameras": {r: {"spec": stable_spec(c.spec), "serial": c.serial}
                                                         for r, c in self.cameras.items()},
                "options": {k: v for k, v in asdict(self.opts).items() if k not in ("timeout_margin_s",)},
                "firmware": list(ident.firmware) if ident else None}

    def _open_journal(self, resume: bool) -> None:
        path = self.work / JOURNAL
        exists = path.exists()
        if exists and not resume:
            raise InputError(f"{self.work} holds a capture ({JOURNAL}): continue it with --resume, or choose "
                             "another folder")
        self.journal = Journal(path)
        ident = self._identity()
        starts = self.journal.of("start")
        if starts:
            if starts[0]["identity_sha"] != _sha(ident):
                raise InputError(f"{self.work}: --resume with another plan, cameras, options or firmware than the "
                                 f"capture there ({starts[0]['identity']['plan']['name']}); use another folder")
        else:
            self.journal.append("start", identity=ident, identity_sha=_sha(ident),
                                date=datetime.now(timezone.utc).isoformat(timespec="seconds"))

    def _frame_path(self, role: str, name: str) -> Path:
        return self.work / "frames" / role / f"{name}.exr"

    def _write_frame(self, role: str, name: str, frame: Frame) -> str:
        path = self._frame_path(role, name)
        img = frame.image if frame.image.ndim == 3 else np.repeat(frame.image[..., None], 3, -1)
        write_exr(path, img, attributes={"dualscale:units": "dn_normalized",
                                         "dualscale:exposure_s": repr(frame.exposure_s)})
        return str(path.relative_to(self.work))

    def _has_files(self, files: list[str]) -> bool:
        return all((self.work / f).is_file() for f in files)

    def _retake(self, key: str, reason: str) -> None:
        self.summary.retakes += 1
        self.summary.retake_reasons[reason] = self.summary.retake_reasons.get(reason, 0) + 1
        n = self._retake_count[key] = self._retake_count.get(key, 0) + 1
        self.journal.append("retake", key=key, reason=reason, attempt=n)
        if n > self.opts.retakes:
            raise CameraError(f"shot {key}: taken {n} times without a frame that matches its event ({reason}); "
                              f"the capture so far is kept: fix the cause and rerun with --resume")

    # ------------------------------------------------------------------ camera I/O
    def _software_frame(self, role: str, exposure_s: float, key: str) -> Frame:
        """One software-triggered frame (the rig idle), taken again while it does not arrive."""
        cam = self.cameras[role]
        while True:
            cam.prepare(TriggerInfo(TriggerMode.INTERNAL, frames=1, exposure_s=exposure_s,
                                    timeout_s=exposure_s + self.opts.collect_quiet_s))
            cam.arm()
            cam.trigger()
            frames = self._collect(cam, first_s=exposure_s)
            if frames:
                return frames[0]
            self._retake(key, "frame missing")

    def _collect(self, cam: Camera, first_s: float = 0.0) -> list[Frame]:
        """The frames of the acquisition that just ended: wait while they keep arriving (a camera
        still reading out or rendering), give up ``collect_quiet_s`` after the last one came;
        ``first_s`` [s]: the exposure still running (a software trigger's), waited for first."""
        seen = -1
        try:
            while True:
                try:
                    return cam.collect(timeout_s=self.opts.collect_quiet_s + (first_s if seen < 0 else 0.0))
                except CameraTimeout as e:
                    if len(e.frames) <= seen:
                        return list(e.frames)
                    seen = len(e.frames)
        finally:
            cam.disarm()

    def _dark(self, role: str, exposure_s: float) -> np.ndarray:
        """The dark frame of ``role`` at ``exposure_s`` (journal ``dark``), taken if missing."""
        us = int(round(exposure_s * 1e6))
        for e in self.journal.of("dark"):
            if e["role"] == role and e["exposure_us"] == us and self._has_files([e["file"]]):
                return read_exr(self.work / e["file"])
        if self.rig.lights_on():
            self.rig.all_off()
        frame = self._software_frame(role, us / 1e6, f"dark_{us}us")
        f = self._write_frame(role, f"dark_{us}us", frame)
        self.journal.append("dark", role=role, exposure_us=us, file=f, meta=_jsonable(frame.metadata))
        return read_exr(self.work / f)

    def _steps(self, shots: list[Shot], plans: dict[str, ShotPlan], angle: int | None = None) -> list[Step]:
        """The device steps of ``shots``, the servo starting from ``angle`` [cdeg] (default: where it is now)."""
        angle = self.rig.read_input(rm.IR.POLARIZER_NOW, 1)[0] if angle is None else angle
        return device_steps(shots, plans, self.plan, self.opts, angle)

    def _ready(self) -> None:
        """Leave the rig idle: a fault (the watchdog of a killed or stalled run) is cleared, a
        sequence still running from an interrupted run is aborted."""
        st = self.rig.status()
        if st.state in ACTIVE:
            self.rig.abort()
            st = self.rig.status()
        if st.state == rm.State.FAULT:
            self.rig.clear_error()

    def _gap_us(self) -> int:
        dead = max(float(c.settings().get("readout_s", 0.0) or 0.0) for c in self.cameras.values())
        return max(rm.TRIGGER_MIN_LOW_US, int(math.ceil(dead * 1e6)))

    def _run_batch(self, shots: list[Shot], plans: dict[str, ShotPlan]) -> tuple[list[Shot], list[Shot], tuple]:
        """Run ``shots`` as one sequence, or as many of them as the firmware's duty rule lets one
        sequence hold: ``(shots run, shots left for the next sequence, _run_sequence's result)``.
        The firmware refuses a sequence whose light would exceed its duty budget at step k
        (``LED_DUTY``, PROTOCOL.md §5; long exposures of one light close together, e.g. the
        chart's patches under one LED at P0 then P90): the steps before k run now, the rest in a
        sequence of their own (the budget starts empty at each START).  A step that alone keeps
        its light on too long (``LED_ON_TIME``) is a ``RigError`` naming the shot and the limit."""
        rest: list[Shot] = []
        while True:
            try:
                return shots, rest, self._run_sequence(shots, plans)
            except SequenceRejected as e:
                if e.error == rm.Error.LED_DUTY and 0 < e.step < len(shots):
                    shots, rest = shots[:e.step], shots[e.step:] + rest
                    continue
                if e.error == rm.Error.LED_ON_TIME and e.step < len(shots):
                    shot = shots[e.step]
                    raise RigError(f"shot {shot.key}: {e}: its light would be on {sum(plans[shot.key].exposures_s()):.3g} s "
                                   f"in one step; the rig allows {self.rig.read_holding(rm.HR.LED_MAX_ON_MS, 1)[0]} ms "
                                   "(LED_MAX_ON_MS): lower --max-exposure or raise the limit") from e
                raise

    def _run_sequence(self, shots: list[Shot], plans: dict[str, ShotPlan]) -> tuple[list[Step], list[Event], dict[str, list[Frame]], str | None]:
        """Run ``shots`` as one device-master sequence; ``(steps, events, frames by role, error)``."""
        self._ready()
        steps = self._steps(shots, plans)
        gap = self._gap_us()
        self.rig.write_registers(rm.HR.FRAME_GAP_US, split_words(gap, 2))
        sched = schedule(steps, gap)
        duration_s = sched[-1].end / 1e6
        armed = []
        for role, cam in self.cameras.items():
            mine = [st for sh, st in zip(shots, steps) if role in self.plan.roles_of(sh)]
            if not mine:
                continue
            n_frames = sum(st.brackets for st in mine)
            longest = max(e for st in mine for e in st.bracket_exposures()) / 1e6
            cam.prepare(TriggerInfo(TriggerMode.GATE, frames=n_frames, exposure_s=longest, deadtime_s=gap / 1e6,
                                    timeout_s=duration_s + self.opts.timeout_margin_s))
            cam.arm()
            armed.append(role)
        error = None
        events: list[Event] = []
        try:
            res = self.rig.run(steps, rm.TriggerMode.DEVICE_MASTER, timeout_s=duration_s * 4 + 60.0,
                               watchdog_ms=self.opts.watchdog_ms)
            events = res.events
            self.summary.link_reconnects += res.reconnects
            self.summary.events_dropped += res.dropped
            if res.state != rm.State.DONE:
                error = f"sequence ended in state {res.state.name} ({res.error.name})"
        except SequenceRejected:
            for role in armed:  # refused at START: no trigger came, no frame will
                self.cameras[role].disarm()
            raise
        except RigError as e:
            error = str(e)
            if not isinstance(e, CameraError):
                events = []
        frames = {role: self._collect(self.cameras[role]) if role in armed else [] for role in self.cameras}
        self.summary.sequences += 1
        self.summary.sequence_device_s += duration_s
        return steps, events, frames, error

    # ------------------------------------------------------------------ matching
    def _match(self, steps: list[Step], events: list[Event], frames: list[Frame],
               only: list[int] | None = None) -> tuple[dict[int, list[Frame]], dict[int, str]]:
        """``(step -> frames in bracket order, step -> reason it must be taken again)`` for one
        camera's ``frames``; ``only``: the steps that trigger this camera (default all)."""
        take = set(range(len(steps)) if only is None else only)
        trig = [e for e in events if e.kind == rm.Event.TRIGGER and e.step != rm.STEP_NONE and e.step in take]
        by_step: dict[int, list[Event | None]] = {k: [None] * s.brackets for k, s in enumerate(steps) if k in take}
        for e in trig:
            if e.step < len(steps) and e.arg < steps[e.step].brackets:
                by_step[e.step][e.arg] = e
        bad: dict[int, str] = {}
        got: dict[int, list[Frame | None]] = {k: [None] * s.brackets for k, s in enumerate(steps) if k in take}
        timed = bool(frames) and all("device_t_us" in f.metadata for f in frames)
        if timed:
            index = {e.ts_us: e for e in trig}
            for f in frames:
                t = int(f.metadata["device_t_us"])
                e = index.get(t) or next((x for x in trig if abs(x.ts_us - t) <= MATCH_TOLERANCE_US), None)
                if e is None or e.step not in got or e.arg >= steps[e.step].brackets:
                    continue  # a frame with no event: its step (if any) lacks a frame below
                if got[e.step][e.arg] is not None:
                    bad[e.step] = "two frames for one trigger"
                got[e.step][e.arg] = f
        elif len(frames) == len(trig) and all(x is not None for v in by_step.values() for x in v):
            order = sorted(trig, key=lambda e: (e.ts_us, e.seq))
            for f, e in zip(sorted(frames, key=lambda f: f.index), order):
                got[e.step][e.arg] = f
        else:
            reason = f"{len(frames)} frames for {len(trig)} trigger events, and the camera gives no device time"
            return {}, {k: reason for k in sorted(take)}
        out: dict[int, list[Frame]] = {}
        for k, s in enumerate(steps):
            if k in bad or k not in take:
                continue
            if any(e is None for e in by_step[k]):
                bad[k] = "trigger event missing"
                continue
            if any(f is None for f in got[k]):
                bad[k] = "frame missing"
                continue
            why = _light_mismatch(s, got[k])  # type: ignore[arg-type]
            if why:
                bad[k] = why
                continue
            out[k] = got[k]  # type: ignore[assignment]
        return out, bad

    # ------------------------------------------------------------------ stages
    def _metered(self) -> dict[str, ShotPlan]:
        """The bracket plans the journal holds (``meter`` entries)."""
        return metered_plans(self.journal)

    def _meter_hints(self) -> dict[tuple, float]:
        """Where to start metering a shot [s]: the exposure at which the last shot of the same light,
        analyser and cameras was metered (a target plan's shots repeat them from patch to patch)."""
        shots = {s.key: s for s in self.plan.shots}
        out: dict[tuple, float] = {}
        for e in self.journal.of("meter"):
            s = shots.get(e["key"])
            if s is not None and e.get("metered_at_us"):
                out[_light_sig(s, self.plan)] = e["metered_at_us"] / 1e6
        return out

    def _meter(self, shots: list[Shot] | None = None) -> dict[str, ShotPlan]:
        """Bracket plans of ``shots`` (default: the plan's) and of every shot metered before
        (journal ``meter``), metering what is missing."""
        plans = self._metered()
        pending = {s.key: s for s in (self.plan.shots if shots is None else shots) if s.key not in plans}
        if not pending:
            return plans
        t0 = time.monotonic()
        darks = {r: self._dark(r, self.opts.meter_exposure_s) for r in self.plan.roles}
        bias = {r: float(np.median(d)) for r, d in darks.items()}
        hints = self._meter_hints()
        t_of = {k: hints.get(_light_sig(s, self.plan), self.opts.meter_exposure_s) for k, s in pending.items()}
        for _round in range(self.opts.meter_rounds):
            if not pending:
                break
            shots = list(pending.values())
            meter_plans = {s.key: ShotPlan(max(1, int(round(t_of[s.key] * 1e6))), 1, 0) for s in shots}
            queue = list(shots)
            while queue:
                batch, queue = queue[:self.opts.batch_steps], queue[self.opts.batch_steps:]
                batch, rest, (steps, events, frames, err) = self._run_batch(batch, meter_plans)
                queue = rest + queue
                matched, bad_all = self._match_all(batch, steps, events, frames)
                for k, s in enumerate(batch):
                    if k in bad_all or any(k not in matched[r] for r in self.plan.roles_of(s)):
                        why = bad_all.get(k, "frame missing")
                        self._retake(s.key, "metering: " + (f"{why} ({err})" if err else why))
                        continue
                    decision = self._decide(s, t_of[s.key], {r: matched[r][k][0] for r in self.plan.roles_of(s)}, bias)
                    if isinstance(decision, float):
                        t_of[s.key] = decision
                        continue
                    plans[s.key] = decision
                    self.journal.append("meter", key=s.key, exposure_us=decision.exposure_us,
                                        brackets=decision.brackets, ev_step=decision.ev_step,
                                        metered_at_us=meter_plans[s.key].exposure_us)
                    pending.pop(s.key)
        if pending:
            raise CameraError(f"could not meter {len(pending)} shot(s) in {self.opts.meter_rounds} rounds "
                              f"(e.g. {next(iter(pending))}); rerun with --resume")
        self.summary.meter_wall_s += time.monotonic() - t0
        return plans

    def _decide(self, shot: Shot, t: float, frames: dict[str, Frame], bias: dict[str, float]) -> ShotPlan | float:
        """A bracket plan from the metering frames, or the next metering exposure [s]."""
        lo_t, hi_t = math.inf, 0.0
        for role, f in frames.items():
            white = float(np.min(self.white[role].threshold))
            img = f.image.astype(np.float64)
            if float(img.max()) >= white:
                if t / METER_STEP * 1e6 < 1:
                    raise CameraError(f"shot {shot.key}: clipped even at {t:g} s: lower the light intensity")
                return t / METER_STEP
            sig = np.clip(img - bias[role], 0, None)
            peak = float(sig.max())
            if peak < METER_LOW * white and t * METER_STEP <= self._longest_s():
                return t * METER_STEP
            step = float(2 ** self.opts.ev_step)
            high = METER_HIGH * self.white[role].level[0]
            try:
                times = plan_brackets(sig, t, low=METER_LOW, high=high, step=step, saturation=white,
                                      max_brackets=64, dark=(bias[role], 0.0))
            except ValueError as e:
                raise CameraError(f"shot {shot.key}: cannot plan brackets from the metering frame: {e}") from e
            lo_t, hi_t = min(lo_t, times[0]), max(hi_t, times[-1])
        hi_t = min(hi_t, self._longest_s())
        lo_t = min(lo_t, hi_t)
        t0_us = max(1, int(lo_t * 1e6))
        step = 2 ** self.opts.ev_step
        n, on_us = 1, t0_us + self._gap_us()
        budget = self._on_budget_us()
        while n < self.opts.max_brackets and (t0_us * step ** n) / 1e6 <= hi_t * 1.0001 \
                and on_us + t0_us * step ** n + self._gap_us() <= budget:
            on_us += t0_us * step ** n + self._gap_us()
            n += 1
        return ShotPlan(t0_us, n, self.opts.ev_step if n > 1 else 0)

    def _on_budget_us(self) -> int:
        """How long one step may keep its light on for its brackets [µs]: the rig's
        ``LED_MAX_ON_MS`` (the firmware refuses a longer step: ``LED_ON_TIME``) less the longest
        settle a step can have (a full servo turn)."""
        if getattr(self, "_budget_us", None) is None:
            cap_us = self.rig.read_holding(rm.HR.LED_MAX_ON_MS, 1)[0] * 1000
            settle = max(self.opts.settle_us, servo_travel_us(rm.POL_MIN_CDEG, rm.POL_MAX_CDEG)
                         + self.opts.servo_margin_us)
            self._budget_us = cap_us - settle
        return self._budget_us

    def _longest_s(self) -> float:
        """The longest exposure a bracket may have [s]: ``max_exposure_s``, and one bracket (with
        the frame gap) within :meth:`_on_budget_us`."""
        return min(self.opts.max_exposure_s, (self._on_budget_us() - self._gap_us()) / 1e6)

    def _match_all(self, batch: list[Shot], steps: list[Step], events: list[Event],
                   frames: dict[str, list[Frame]]) -> tuple[dict[str, dict[int, list[Frame]]], dict[int, str]]:
        """:meth:`_match` for every camera over the steps that trigger it: ``(role -> step ->
        frames, step -> reason it must be taken again)``."""
        matched: dict[str, dict[int, list[Frame]]] = {}
        bad_all: dict[int, str] = {}
        for role in self.plan.roles:
            only = [k for k, s in enumerate(batch) if role in self.plan.roles_of(s)]
            if not only:
                matched[role] = {}
                continue
            m, bad = self._match(steps, events, frames[role], only)
            matched[role] = m
            bad_all.update(bad)
        return matched, bad_all

    def _done(self) -> set[str]:
        """The shots the journal holds with all their frames on disk."""
        return {e["key"] for e in self.journal.of("shot") if self._has_files([f for v in e["files"].values() for f in v])}

    def _capture(self, plans: dict[str, ShotPlan], shots: list[Shot] | None = None) -> None:
        """Take ``shots`` (default: the plan's) that the journal does not hold yet."""
        shots = list(self.plan.shots if shots is None else shots)
        done = self._done()
        self.summary.resumed_shots += sum(s.key in done for s in shots)
        pending = [s for s in shots if s.key not in done]
        total = len(self.plan.shots)
        self.summary.floor_s += floor_s(self._steps(shots, plans), self._gap_us())
        t0 = time.monotonic()
        while pending:
            batch, pending = pending[:self.opts.batch_steps], pending[self.opts.batch_steps:]
            batch, rest, (steps, events, frames, err) = self._run_batch(batch, plans)
            pending = rest + pending
            self.summary.capture_device_s += schedule(steps, self._gap_us())[-1].end / 1e6
            matched, bad_all = self._match_all(batch, steps, events, frames)
            again = []
            for k, s in enumerate(batch):
                roles = self.plan.roles_of(s)
                if k in bad_all or any(k not in matched[r] for r in roles):
                    why = bad_all.get(k, "frame missing")
                    self._retake(s.key, f"{why} ({err})" if err else why)
                    again.append(s)
                    continue
                files: dict[str, list[str]] = {}
                for role in roles:
                    files[role] = [self._write_frame(role, f"{s.key}_b{b}", f) for b, f in enumerate(matched[role][k])]
                ev = [e for e in events if e.step == k and e.kind in (rm.Event.STEP_START, rm.Event.TRIGGER)]
                self.journal.append("shot", key=s.key, files=files,
                                    exposures_s=[f.exposure_s for f in matched[roles[0]][k]],
                                    events=[{"kind": e.kind.name, "arg": e.arg, "seq": e.seq, "ts_us": e.ts_us} for e in ev],
                                    meta={r: _jsonable(matched[r][k][0].metadata) for r in roles})
                done.add(s.key)
                if self.progress:
                    self.progress(len(done), total, s.key)
            pending = again + pending
        self.summary.capture_wall_s += time.monotonic() - t0

    def _merge(self, plans: dict[str, ShotPlan], taken: list[Shot] | None = None, out: Path | None = None) -> Path:
        """Write the photometric dataset from the journal's frames (module doc, step 6): of
        ``taken`` (default: the plan's shots), in the plan's order, into ``out`` (default: the
        capture's folder)."""
        keys = None if taken is None else {s.key for s in taken}
        shots = {e["key"]: e for e in self.journal.of("shot")}
        exposures = sorted({t for p in plans.values() for t in p.exposures_s()})
        dome = DomeGeometry.from_regmap()
        darks: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        dark_files: dict[str, list[tuple[float, np.ndarray]]] = {}
        for role in self.plan.roles:
            pairs = [(t, self._dark(role, t)) for t in sorted({exposures[0], exposures[-1]})]
            dark_files[role] = pairs
            if len(pairs) == 1:
                pairs = pairs + [(self.opts.meter_exposure_s, self._dark(role, self.opts.meter_exposure_s))]
            darks[role] = fit_dark([p[1] for p in pairs], [p[0] for p in pairs])
        spaces = {r: colour_space(self.cameras[r]) for r in self.plan.roles}
        if len(set(spaces.values())) != 1:
            raise InputError(f"the plan's cameras record different colour spaces {spaces}: capture them separately")
        ident = self.rig.identity
        rig = {"id": self.opts.rig_id or (ident.text if ident else "unknown"), "layout": dome.signature()}
        extra = {"capture": {"plan": self.plan.name, "journal": JOURNAL, "record": "capture.json"}}
        clipped = 0
        out = self.out if out is None else Path(out)
        with DatasetWriter(out, units="dn_normalized", colour_space=next(iter(spaces.values())), rig=rig,
                           dome={"source": dome.source, "polarizer": dome.polarizer, "radius_mm": dome.radius_mm},
                           extra=extra) as w:
            for s in self.plan.shots:
                if keys is not None and s.key not in keys:
                    continue
                e = shots[s.key]
                times = plans[s.key].exposures_s()
                for role in self.plan.roles:
                    geo = self.geometry[role]
                    imgs = [read_exr(self.work / f) for f in e["files"][role]]
                    bias, rate = darks[role]
                    wl = self.white[role]
                    hdr = merge_debevec(imgs, times, dark=[dark_at(bias, rate, t) for t in times], white_level=wl,
                                        domain="linear", max_saturated_fraction=1.0, name=s.key)
                    t_ref = times[0]
                    img = hdr.radiance * t_ref + dark_at(bias, rate, t_ref)
                    sat = float(np.min(wl.threshold))
                    img = np.where(hdr.saturated, float(max(wl.level)), img)
                    clipped += int(hdr.saturated.any(-1).sum())
                    an, rel = _analyzer_deg(s, geo)
                    direction = [float(x) for x in dome.led_dirs[s.index]] if s.kind == "led" else None
                    w.add(img.astype(np.float32), geo, s.kind, s.index, direction, self.opts.intensity / rm.INTENSITY_MAX,
                          an, rel, t_ref, saturation=sat)
            for role in self.plan.roles:
                for t, d in dark_files[role]:
                    w.add(d, self.geometry[role], "off", None, None, 1.0, None, False, t)
        self.summary.clipped_pixels = clipped
        return out / "manifest.json"

    def _record(self, part: dict[str, Any] | None = None, adaptive: dict[str, Any] | None = None) -> None:
        ident = self.rig.identity
        rec = {"format": FORMAT, "version": VERSION,
               "date": self.journal.of("start")[0]["date"],
               "rig": {"id": self.opts.rig_id, "identification": ident.text if ident else None,
                       "firmware": ".".join(map(str, ident.firmware)) if ident else None,
                       "protocol": ".".join(map(str, ident.protocol)) if ident else None,
                       "port": self.rig.port},
               "cameras": {r: {**frame_metadata(c), "role": r} for r, c in self.cameras.items()},
               "calibration": self.opts.calibration_id, "plan": self.plan.to_json(),
               "options": asdict(self.opts), "summary": asdict(self.summary)}
        if self.summary.dataset:  # relative: the folder may move (digitize renames its work folder)
            rec["summary"]["dataset"] = os.path.relpath(self.summary.dataset, self.work)
        if part is not None:
            rec["captureset"] = part
        if adaptive is not None:
            rec["adaptive"] = adaptive
        write_json(self.work / "capture.json", _jsonable(rec))

    # ------------------------------------------------------------------ calibration targets
    def rig_record(self) -> dict[str, str]:
        """The rig's record in a dataset or calibration (``id``: ``--rig-id`` or the firmware's
        identification, ``layout``: the dome's signature)."""
        ident = self.rig.identity
        return {"id": self.opts.rig_id or (ident.text if ident else "unknown"),
                "layout": DomeGeometry.from_regmap().signature()}

    def _camera_records(self) -> dict[str, dict[str, Any]]:
        """Each role's capture-set camera record (module doc, "Calibration targets")."""
        out = {}
        for role, cam in self.cameras.items():
            geo = asdict(self.geometry[role])
            geo.pop("name")
            out[self.plan.camera_name(role)] = {"role": role, "geometry": geo,
                                                "sensitivities": colour_space(cam).removeprefix("camera_raw:"),
                                                "white_level": float(cam.sensor().white_level)}
        return _jsonable(out)

    def _check_targets(self) -> None:
        """Before anything is taken: the holder's geometry that ``calibrate`` needs from this plan
        (the mid camera's white markers; the chart's corners in the polar cameras), and cameras and
        rig that agree with the parts already in the capture set."""
        chart_whole = {r for s in self.plan.shots if s.target == "chart" for r in self.plan.roles_of(s)}
        if self.plan.name in ("white-sheet", "chart") and "mid" in self.plan.roles and "mid" not in self.holder["markers"]:
            raise InputError(f"plan {self.plan.name!r}: the mid camera's white-marker boxes are not given: --holder FILE "
                             "with {\"markers\": {\"mid\": [[row0, row1, col0, col1], ...]}} (pixels inside each white "
                             "marker of the holder; the simulated cameras give theirs)")
        for r in sorted(chart_whole):
            if r != "mid" and r not in self.holder["chart_corners"]:
                raise InputError(f"plan 'chart': the {r} camera's chart corners are not given: --holder FILE with "
                                 f"{{\"chart_corners\": {{\"{r}\": [[x, y], ...4]}}}} (the centred chart's swatch-area "
                                 "corners TL, TR, BR, BL in pixels; the simulated cameras give theirs)")
        own = {"rig": self.rig_record(), "cameras": self._camera_records()}
        others = [p for p in read_parts(self.out) if p["plan"] != self.plan.name]
        _check_parts(others + [{"plan": self.plan.name, **own}], self.out)

    def _part(self, plans: dict[str, ShotPlan]) -> dict[str, Any]:
        """This plan's part of the capture set (module doc), its dark frames taken if missing."""
        shots = {e["key"]: e for e in self.journal.of("shot")}
        for role in self.plan.roles:
            ts = sorted({t for s in self.plan.shots if role in self.plan.roles_of(s) for t in plans[s.key].exposures_s()})
            for t in sorted({ts[0], ts[-1]}):
                self._dark(role, t)
        prefix = Path(PARTS) / self.plan.name
        groups = []
        for s in self.plan.shots:
            e = shots[s.key]
            for role in self.plan.roles_of(s):
                an = s.analyzer_cdeg if role == "micro" and s.target != "dot_grid" else None
                groups.append({"target": s.target, "camera": self.plan.camera_name(role), "light_kind": s.kind,
                               "light_id": s.index,
                               "patch": s.patch, "analyzer_deg": None if an is None else an / 100.0,
                               "analyzer_relative": an is not None and s.target != "polarization",
                               "exposures_s": [float(t) for t in e["exposures_s"]],
                               "files": [str(prefix / f) for f in e["files"][role]]})
        darks: dict[str, list[list[Any]]] = {}
        for e in self.journal.of("dark"):
            if e["role"] in self.cameras:
                darks.setdefault(self.plan.camera_name(e["role"]), []).append([e["exposure_us"] / 1e6,
                                                                              str(prefix / e["file"])])
        part: dict[str, Any] = {"rig": self.rig_record(), "cameras": self._camera_records(), "groups": groups,
                                "darks": darks}
        roles = set(self.plan.roles)
        if self.plan.name in ("white-sheet", "chart"):
            part["markers"] = {c: v for c, v in self.holder["markers"].items() if c in roles}
        if self.plan.name == "chart":
            lay = ChartLayout()
            part["chart"] = {"layout": {"rows": lay.rows, "cols": lay.cols, "pitch_mm": lay.pitch_mm,
                                        "patch_mm": lay.patch_mm},
                             "corners": {c: v for c, v in self.holder["chart_corners"].items() if c in roles}}
        return part

    def run(self) -> CaptureSummary:
        """Meter, capture, merge (module doc); returns the summary.  Safe to call again on the same
        folder with ``resume=True`` after any interruption.  A calibration-target plan runs setup by
        setup (:meth:`dualscale.capture.plan.Plan.setups`): ``operator(setup)`` is called before a
        setup with shots still to take, then those are metered and taken; at the end the plan's part
        is recorded and the capture set rewritten (:func:`write_capture_set`)."""
        t0 = time.monotonic()
        self._ready()
        setups = self.plan.setups()
        if self.plan.targets and self.operator is None:
            raise InputError(f"plan {self.plan.name!r} needs an operator at the holder: {setups[0][0].prompt()}")
        plans = self._metered()
        for setup, shots in setups:
            if setup is not None and not {s.key for s in shots} <= self._done():
                self.operator(setup)  # type: ignore[misc]
            plans = self._meter(shots)
            self._capture(plans, shots)
        shots_done = {e["key"] for e in self.journal.of("shot")}
        self.summary.shots = len(shots_done)
        self.summary.frames = sum(len(v) for e in self.journal.of("shot") for v in e["files"].values())
        if self.plan.targets:
            part = self._part(plans)
            self.summary.dataset = str(self.out / "captures.json")
            self.summary.total_wall_s = time.monotonic() - t0
            self._record(part)
            path = write_capture_set(self.out)
            if not self.journal.of("written"):
                self.journal.append("written", captures=str(path.relative_to(self.out)))
            return self.summary
        self.summary.total_wall_s = time.monotonic() - t0
        return self.finish(plans)

    # ------------------------------------------------------------------ a plan taken in parts
    def take(self, shots: list[Shot]) -> dict[str, ShotPlan]:
        """Meter and capture those of ``shots`` (a subset of the plan's, in the order given) that
        the journal does not hold yet (an adaptive capture's round, :mod:`dualscale.adaptive`);
        returns the bracket plans of every shot metered so far.  Resumable like :meth:`run`."""
        t0 = time.monotonic()
        self._ready()  # the host's work between two rounds may have let the watchdog fault the rig
        plans = self._meter(shots)
        self._capture(plans, shots)
        self.summary.total_wall_s += time.monotonic() - t0
        return plans

    def merge(self, taken: list[Shot], out: str | Path) -> Path:
        """The photometric dataset of the ``taken`` shots (in the journal) written into ``out``
        (e.g. an adaptive round's), not the capture's own folder; returns its manifest."""
        return self._merge(self._metered(), taken, Path(out))

    def floor_s(self, shots: list[Shot], start_cdeg: int = rm.POL_P0_CDEG) -> float:
        """The physical floor [s] of ``shots`` taken in that order with their metered brackets,
        the servo starting at ``start_cdeg``: settle, servo moves, exposures and readout gaps
        (the schedule of the device-master sequence, PROTOCOL.md §3.1); metering not included."""
        return floor_s(self._steps(list(shots), self._metered(), angle=start_cdeg), self._gap_us())

    def finish(self, plans: dict[str, ShotPlan] | None = None, taken: list[Shot] | None = None,
               adaptive: dict[str, Any] | None = None) -> CaptureSummary:
        """Merge the photometric dataset of ``taken`` (default: the plan's shots; all must be in the
        journal) and write ``capture.json`` (with the ``adaptive`` record when given)."""
        plans = self._metered() if plans is None else plans
        entries = self.journal.of("shot")
        keys = None if taken is None else {s.key for s in taken}
        self.summary.shots = len({e["key"] for e in entries if keys is None or e["key"] in keys})
        self.summary.frames = sum(len(v) for e in entries if keys is None or e["key"] in keys for v in e["files"].values())
        path = self._merge(plans, taken)
        self.summary.dataset = str(path)
        self._record(adaptive=adaptive)
        if not self.journal.of("merged"):
            self.journal.append("merged", manifest="manifest.json")
        return self.summary


def device_steps(shots: list[Shot], plans: dict[str, ShotPlan], plan: Plan, opts: CaptureOptions,
                 angle: int) -> list[Step]:
    """The device-master steps of ``shots`` with their bracket ``plans`` (PROTOCOL.md §3.1), the
    servo starting at ``angle`` [cdeg]: a step that turns the analyser settles for the servo's
    travel plus ``opts.servo_margin_us``, the others for ``opts.settle_us``."""
    steps = []
    for s in shots:
        mask = _trigger_mask(plan.roles_of(s))
        p = plans[s.key]
        settle, pol = opts.settle_us, None
        if s.analyzer_cdeg is not None and s.analyzer_cdeg != angle:
            settle = max(settle, servo_travel_us(angle, s.analyzer_cdeg) + opts.servo_margin_us)
            pol, angle = s.analyzer_cdeg, s.analyzer_cdeg
        steps.append(Step(s.source, s.index or 0, opts.intensity, pol, settle, p.exposure_us, 0,
                          p.brackets, p.ev_step, mask))
    return steps


def floor_s(steps: list[Step], gap_us: int) -> float:
    """The physical floor [s] of ``steps``: settle, exposures and readout gaps as scheduled."""
    return sum(t.end - t.start for t in schedule(steps, gap_us)) / 1e6 if steps else 0.0


def metered_plans(journal: Journal) -> dict[str, ShotPlan]:
    """The bracket plans a capture's journal holds (``meter`` entries), by shot key."""
    return {e["key"]: ShotPlan(e["exposure_us"], e["brackets"], e["ev_step"]) for e in journal.of("meter")}


def _light_sig(shot: Shot, plan: Plan) -> tuple:
    """What makes two shots meter alike: light, analyser and cameras (not the target's place)."""
    return (shot.kind, shot.index, shot.analyzer_cdeg, plan.roles_of(shot))


def _light_mismatch(step: Step, frames: list[Frame]) -> str | None:
    """Why the frames' seen light state (when the camera reports it) is not the step's, or None."""
    want = [int(step.source), step.index]
    for f in frames:
        lights = f.metadata.get("lights")
        if lights is not None:
            on = [[int(k), int(i)] for k, i, v in lights if int(v) > 0]
            if on != [want]:
                return f"light state differs (saw {on}, step {want})"
        pol = f.metadata.get("polarizer_cdeg")
        if pol is not None and step.polarizer_cdeg is not None and int(pol) != step.polarizer_cdeg:
            return f"analyser differs (saw {pol} cdeg, step {step.polarizer_cdeg})"
    return None


def stable_spec(spec: str) -> str:
    """``spec`` without its ``hw=`` option (the side-channel socket of a simulated rig, a
    temporary path that differs from run to run): what identifies the camera across resumes."""
    from .camera import split_options

    scheme, _, rest = spec.partition(":")
    target, opts = split_options(rest)
    opts.pop("hw", None)
    return f"{scheme}:{target}" + ("?" + "&".join(f"{k}={v}" for k, v in sorted(opts.items())) if opts else "")

