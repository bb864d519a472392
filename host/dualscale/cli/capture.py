"""``dualscale capture PLAN -o DATASET --port PORT --camera SPEC...``: a capture on the rig
(:mod:`dualscale.capture.session`; docs/CAPTURE.md).

``--port sim`` starts the POSIX firmware simulator with its hardware side channel for the
duration of the command, and every ``sim:`` camera spec without ``hw=`` is connected to it: the
whole virtual rig, through the real firmware core.

The calibration-target plans (``white-sheet``, ``chart``, ``dot-grid``, ``polarization``) write
their part into the capture set ``-o CAL`` (``CAL/captures.json``, what ``dualscale calibrate``
and ``evaluate-device`` read); several plans go into one folder.  Each change of target is an
operator's job: the command prints the instruction and waits for Enter on stdin
(``--target-ready``: it does not wait); with simulated cameras the virtual operator does it
(:meth:`dualscale.sim.camera.SimCamera.place`).  The holder's geometry that ``calibrate`` needs
(the mid camera's white-marker boxes, the polar cameras' chart corners) comes from ``--holder
FILE`` or, for simulated cameras, from the cameras themselves.
"""

from __future__ import annotations

import argparse
import contextlib
import tempfile
import json
import sys
from pathlib import Path
from typing import Any, Callable, Iterator, TextIO

from dualscale.errors import DualscaleError, InputError

from .common import add_output, add_work_options, apply_threads, output_folder, want_progress

SIM_PORT = "sim"


def _with_option(spec: str, key: str, value: str) -> str:
    scheme, _, rest = spec.partition(":")
    if f"{key}=" in rest:
        return spec
    return f"{spec}{'&' if '?' in rest else '?'}{key}={value}"


def parse_camera_args(values: list[str]) -> list[tuple[str | None, str]]:
    """``--camera [ROLE=]SPEC`` values as ``(role or None, spec)``."""
    from dualscale.protocol import regmap as rm

    out = []
    for v in values:
        role, sep, spec = v.partition("=")
        if sep and role in rm.CAMERA_NAMES and ":" in spec:
            out.append((role, spec))
        else:
            out.append((None, v))
    return out


@contextlib.contextmanager
def rig_and_cameras(port: str, cameras: list[str], roles: tuple[str, ...], parity: str = "E",
                    stopbits: int | None = None, sim_speed: float = 1.0) -> Iterator[tuple[object, dict]]:
    """Open the rig (``port``, or ``sim``: start the simulator) and the cameras; yields ``(rig
    client, role -> camera)``; closes everything at the end."""
    import dualscale.sim.camera  # noqa: F401  registers the "sim" camera backend (the virtual rig's cameras)
    from dualscale.capture.camera import open_camera
    from dualscale.rig.client import RigClient
    from dualscale.rig.launcher import SimulatedRig

    with contextlib.ExitStack() as stack:
        hw = None
        if port == SIM_PORT:
            tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="dualscale-rig-")))
            hw = tmp / "hw.sock"
            sim = stack.enter_context(SimulatedRig("posix", speed=sim_speed, hw_socket=hw, parity=parity,
                                                   stop_bits=stopbits))
            port = sim.port
        opened: dict[str, object] = {}
        for role, spec in parse_camera_args(cameras):
            typed = spec
            if spec.startswith("sim:"):
                if hw is None and "hw=" not in spec:
                    raise InputError(f"--camera {spec}: a sim camera needs the simulated rig, port 'sim' "
                                     f"(capture --port sim, digitize --rig sim), not {port}; or hw=SOCKET")
                if hw is not None:
                    spec = _with_option(spec, "hw", str(hw))
            try:
                cam = open_camera(spec)
            except DualscaleError as e:  # name the spec the user gave, not the socket added here
                raise type(e)(str(e).replace(spec, typed)) from e
            stack.callback(cam.close)
            if role is None:
                g = getattr(cam, "geometry", None)
                if callable(g):
                    role = g().name
                elif len(roles) == 1:
                    role = roles[0]
                else:
                    raise InputError(f"--camera {spec}: say which rig camera it is, e.g. --camera micro={spec}")
            if role in opened:
                raise InputError(f"two cameras for the {role} role")
            opened[role] = cam
        rig = RigClient(port, parity=parity, stopbits=stopbits)
        rig.open()
        stack.callback(rig.close)
        yield rig, opened


def capture_options(a: argparse.Namespace, port: str):
    """The session's options from the command line; on the simulated rig the host watchdog is
    scaled to the simulator's speed (:func:`dualscale.rig.demo.demo_watchdog_ms`: its device clock
    runs that much faster than the host's)."""
    from dualscale.capture.session import CaptureOptions
    from dualscale.rig.client import DEFAULT_WATCHDOG_MS
    from dualscale.rig.demo import demo_watchdog_ms

    if not a.sim_speed >= 0:
        raise InputError(f"--sim-speed {a.sim_speed:g}: 0 (as fast as possible) or a positive factor (1 = real time)")
    if not 0.01 <= a.max_exposure <= 60.0:
        raise InputError(f"--max-exposure {a.max_exposure:g} s: between the metering exposure 0.01 s and 60 s")
    wd = demo_watchdog_ms(a.sim_speed) if port == SIM_PORT else DEFAULT_WATCHDOG_MS
    return CaptureOptions(intensity=a.intensity, max_exposure_s=a.max_exposure, batch_steps=a.batch, retakes=a.retakes,
                          trigger=a.trigger, rig_id=a.rig_id, calibration_id=a.calibration_id, watchdog_ms=wd)


def read_holder(path: str | None) -> dict[str, Any]:
    """``--holder FILE``: ``{"markers": {camera: [[row0, row1, col0, col1], ...]}, "chart_corners":
    {camera: [[x, y] x 4]}}`` (``{}`` without a file); ``InputError`` naming the file."""
    if path is None:
        return {}
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"--holder {path}: not a readable JSON file ({e})") from e
    if not isinstance(doc, dict):
        raise InputError(f"--holder {path}: a JSON object with markers and/or chart_corners")
    return doc


def holder_of(cams: dict[str, Any], given: dict[str, Any]) -> dict[str, Any]:
    """The holder's geometry: what the cameras report (the simulated ones, ``holder()``), then
    ``given`` (``--holder``) over it."""
    out: dict[str, dict] = {"markers": {}, "chart_corners": {}}
    for cam in cams.values():
        own = getattr(cam, "holder", None)
        if callable(own):
            for k, v in own().items():
                out.setdefault(k, {}).update(v)
    for k, v in given.items():
        if not isinstance(v, dict):
            raise InputError(f"--holder: {k} must map camera names to their values")
        out.setdefault(k, {}).update(v)
    return out


def make_operator(cams: dict[str, Any], target_ready: bool, out: TextIO | None = None,
                  answers: TextIO | None = None) -> Callable[[Any], None]:
    """The operator of the target plans' setups (:class:`dualscale.capture.plan.Setup`), for the
    cameras ``cams`` (role -> camera): a simulated camera (one with ``place()``) gets the target
    from the virtual operator (the chart's patch moves under the micro camera only); when any
    camera is not simulated, the instruction goes to ``out`` (stderr) and a line is read from
    ``answers`` (stdin: Enter) unless ``target_ready``.  ``InputError`` when stdin ends before the
    operator confirmed."""
    real = [r for r, c in cams.items() if not callable(getattr(c, "place", None))]

    def operator(setup) -> None:
        o = out or sys.stderr
        for role, c in cams.items():
            if callable(getattr(c, "place", None)):  # the others are not triggered while the chart is moved
                c.place(setup.target, setup.patch if role == "micro" else None)
        if not real:
            print(f"virtual operator: {setup.prompt()}", file=o, flush=True)
            return
        print(f"operator: {setup.prompt()}" + ("" if target_ready else "; then press Enter"), file=o, flush=True)
        if not target_ready and not (answers or sys.stdin).readline():
            raise InputError(f"the target was not confirmed (stdin ended) for: {setup.prompt()}; rerun with --resume "
                             "and answer the prompt, or give --target-ready when the targets are placed without one")

    return operator


def cmd_capture(a: argparse.Namespace) -> int:
    from dualscale.capture.plan import TARGET_PLANS, make_plan
    from dualscale.capture.session import CaptureSession
    from dualscale.progress import tracker

    apply_threads(a)
    a.resume_hint = "continue it with the same command and --resume"
    targets = a.plan in TARGET_PLANS
    plan = make_plan(a.plan, a.lights)  # checks the plan and --lights before anything starts
    given = read_holder(a.holder)
    opts = capture_options(a, a.port)
    adaptive = adaptive_options(a, plan)  # checked before the rig starts
    ident = ["calibration targets"] if targets else [f"plan:{a.plan}", f"lights:{a.lights}", *a.camera]
    if a.resume and not targets:
        from dualscale.adaptive.options import check_resume

        check_resume(a.output, adaptive)  # an adaptive capture resumed as one, with its options
    with output_folder(a, "capture", ident) as out:
        if a.overwrite and not a.resume:
            restart(out, a.plan)
        with rig_and_cameras(a.port, a.camera, () if targets else plan.roles, a.parity, a.stopbits,
                             a.sim_speed) as (rig, cams):
            operator = holder = None
            if targets:
                plan = make_plan(a.plan, a.lights, tuple(cams))
                used = {r: cams[r] for r in plan.roles if r in cams}
                operator, holder = make_operator(used, a.target_ready), holder_of(used, given)
            with tracker(want_progress(a), len(plan.shots), f"capture {plan.name}", "shot") as bar:
                seen = [0]

                def progress(done: int, total: int, key: str) -> None:
                    bar.update(done - seen[0], what=key)
                    seen[0] = done

                session = CaptureSession(rig, cams, plan, a.output, opts, resume=a.resume, progress=progress,
                                         operator=operator, holder=holder)
                if adaptive is not None:
                    from dualscale.adaptive.loop import AdaptiveCapture

                    summary = AdaptiveCapture(session, a.calibration, adaptive, log=print).run()
                else:
                    summary = session.run()
    for line in summary.lines():
        print(line)
    return 0


def adaptive_options(a: argparse.Namespace, plan):
    """``--adaptive`` and its options as :class:`dualscale.adaptive.loop.AdaptiveOptions`, or
    ``None`` without ``--adaptive``; ``InputError`` for a plan other than micro, a missing
    calibration (every round is calibrated with it) or a bad option, before the rig starts."""
    if not getattr(a, "adaptive", False):
        from dualscale.adaptive.options import AdaptiveOptions

        d = AdaptiveOptions()
        only = (("--target", "target", None), ("--budget", "budget", None), ("--initial-leds", "initial_leds", d.initial),
                ("--batch-leds", "batch_leds", None), ("--criterion", "criterion", d.criterion),
                ("--min-gain", "min_gain", d.min_gain))
        given = [flag for flag, dest, default in only if getattr(a, dest, default) != default]
        if given:
            raise InputError(f"{', '.join(given)}: options of the adaptive capture; add --adaptive (and "
                             f"--calibration), or leave them out for the fixed plan")
        return None
    from dualscale.adaptive.loop import check_calibration
    from dualscale.adaptive.options import AdaptiveOptions, parse_budget, parse_targets

    if plan.name != "micro":
        raise InputError(f"--adaptive captures the micro plan, not {plan.name}")
    if not getattr(a, "calibration", None):
        raise InputError("--adaptive needs the rig's calibration (--calibration FILE): every round is calibrated and "
                         "fitted to choose the next lights")
    if not Path(a.calibration).is_file():
        raise InputError(f"--calibration {a.calibration}: no such file")
    leds = sorted({s.index for s in plan.shots if s.kind == "led"})
    if len(leds) < a.initial_leds:
        raise InputError(f"--initial-leds {a.initial_leds}: --lights {a.lights} gives {len(leds)} candidate LEDs")
    rig = None
    if getattr(a, "rig_id", None):  # else the firmware names the rig: checked once it is open, before the first shot
        from dualscale.geometry.dome import DomeGeometry

        rig = {"id": a.rig_id, "layout": DomeGeometry.from_regmap().signature()}
    check_calibration(Path(a.calibration), leds, rig)
    shots, seconds = parse_budget(a.budget)
    targets, full = parse_targets(a.target)
    return AdaptiveOptions(initial=a.initial_leds, batch=a.batch_leds, criterion=a.criterion,
                           targets=targets, full_target=full, min_gain=a.min_gain, budget_shots=shots,
                           budget_s=seconds, seed=getattr(a, "seed", 0) or 0)


def add_adaptive_options(p: argparse.ArgumentParser) -> None:
    """The options of ``--adaptive`` that ``capture micro`` and ``digitize --rig`` share."""
    from dualscale.adaptive.options import AdaptiveOptions

    d = AdaptiveOptions()
    g = p.add_argument_group("adaptive capture (docs/CAPTURE.md, \"Adaptive capture\")")
    g.add_argument("--adaptive", action="store_true",
                   help="micro plan: choose the lights round by round from the fit's uncertainty, among --lights, and "
                        "stop when the maps are determined (needs --calibration)")
    g.add_argument("--target", default=None, metavar="MAP=SIGMA,...|full+N%|none",
                   help="stop when every named map's median 1-sigma is at or under this (the maps' sigma units: "
                        "normal in degrees), and with full+N%% every other map's predicted sigma is within N %% of "
                        "what the whole candidate plan would give; none: only the gain and budget rules stop it "
                        "(default: full+5%%)")
    g.add_argument("--budget", default=None, metavar="SHOTS|Ts|Tmin",
                   help="the most shots (e.g. 80) or device time (e.g. 300s, 5min) the capture may take "
                        "(default: no limit)")
    g.add_argument("--initial-leds", type=int, default=d.initial, metavar="N",
                   help=f"LEDs of the first round, spread over the dome (default {d.initial})")
    g.add_argument("--batch-leds", type=int, default=None, metavar="N",
                   help="LEDs per round (default: enough that the round's two servo moves are at most 10%% of its "
                        "device time, 4-16)")
    g.add_argument("--criterion", choices=("D", "A"), default=d.criterion,
                   help=f"optimal-design criterion (default {d.criterion})")
    g.add_argument("--min-gain", type=float, default=d.min_gain, metavar="NATS",
                   help=f"stop when no light's D-gain per sample pixel reaches this (default {d.min_gain:g})")


def restart(out: Path, plan: str) -> None:
    """``--overwrite`` without ``--resume``: forget the capture of ``plan`` in ``out`` so that it
    starts over (a sample plan: its journal, frames, dataset and record; a calibration-target
    plan: its part only, the other parts are kept)."""
    import shutil

    from dualscale.capture.journal import JOURNAL
    from dualscale.capture.plan import TARGET_PLANS
    from dualscale.capture.session import PARTS

    if plan in TARGET_PLANS:
        if (out / PARTS / plan).is_dir():
            shutil.rmtree(out / PARTS / plan)
        return
    for name in (JOURNAL, "capture.json", "manifest.json", "mask.exr"):
        (out / name).unlink(missing_ok=True)
    for name in ("frames", "images"):
        if (out / name).is_dir():
            shutil.rmtree(out / name)


def add_capture_options(p: argparse.ArgumentParser) -> None:
    """The rig and camera options ``capture`` and ``digitize --rig`` share."""
    p.add_argument("--camera", action="append", default=[], metavar="[ROLE=]SPEC",
                   help="a camera: sim:micro, genicam:SERIAL, gphoto2:, uvc:0 (ROLE = micro|mid|polar0|polar1 when "
                        "the spec does not say it); repeat for several")
    p.add_argument("--trigger", choices=("device", "camera"), default="device",
                   help="device: the rig times every exposure (gate triggers, HDR brackets); camera: camera-master "
                        "(default device)")
    p.add_argument("--lights", default="ALL", metavar="ALL|MODn|ROWa+b|FILE",
                   help="the LEDs of the micro plan and of the white-sheet, chart and polarization plans "
                        "(default ALL; synth-targets' --led-step N is MODN)")
    p.add_argument("--intensity", type=int, default=65535, help="LED drive level, 1..65535 (default full)")
    p.add_argument("--max-exposure", type=float, default=4.0, metavar="S",
                   help="longest exposure a bracket may have [s] (default 4)")
    p.add_argument("--batch", type=int, default=64, metavar="STEPS", help="steps per device sequence (default 64)")
    p.add_argument("--retakes", type=int, default=3, help="how often a shot is taken again before giving up (default 3)")
    p.add_argument("--rig-id", default=None, help="the rig's id in the dataset (checked against calibrations); "
                                                  "default: the device's identification")
    p.add_argument("--calibration-id", default=None, help="the calibration this capture is for (recorded)")
    p.add_argument("--sim-speed", type=float, default=1.0,
                   help="--port sim: simulator speed (1 = real time, 0 = as fast as possible; default 1)")
    from . import _serial_format_options

    _serial_format_options(p)


def register(sub) -> None:
    """Add ``capture`` to an argparse subparsers object."""
    from .choices import CAPTURE_PLANS as PLANS

    p = sub.add_parser("capture", help="capture a plan on the rig with its cameras (resumable)")
    p.add_argument("plan", choices=list(PLANS), help="micro: the photometric dataset; mid: the guidance image; "
                                                     "white-sheet, chart, dot-grid, polarization: a calibration "
                                                     "target into the capture set -o (calibrate, evaluate-device)")
    add_output(p, "dataset folder (manifest.json, frames/, journal.jsonl, capture.json); for a target plan the "
                  "capture set (captures.json, images/, parts/PLAN/)")
    p.add_argument("--port", required=True, help="the rig's serial port, or 'sim' for the simulated rig")
    p.add_argument("--resume", action="store_true", help="continue an interrupted capture in the same folder")
    p.add_argument("--holder", metavar="FILE", default=None,
                   help="target plans: JSON with the holder as the cameras see it: {\"markers\": {\"mid\": [[row0, "
                        "row1, col0, col1], ...]}, \"chart_corners\": {\"polar0\": [[x, y] x 4]}} (simulated cameras "
                        "give their own)")
    p.add_argument("--target-ready", action="store_true",
                   help="target plans: do not wait for Enter after each instruction to the operator (the targets are "
                        "placed without one)")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="--adaptive: the rig's calibration (dualscale calibrate), to fit each round")
    add_capture_options(p)
    add_adaptive_options(p)
    add_work_options(p)
    p.set_defaults(fn=cmd_capture)
