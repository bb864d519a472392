"""The capture stage of ``dualscale digitize --rig``: what it captures, what it keys on, and the
check of the calibration before the first shot.  :mod:`dualscale.pipeline` runs it as the stage
before ``calibrate`` (``RUN/capture/{micro,mid}/``, record ``stages/capture.json``:
:data:`dualscale.formats.run.CAPTURE_STAGE`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable

from dualscale.errors import CalibrationError
from dualscale.formats.run import file_sha256


@dataclass
class RigCapture:
    """``digitize --rig``: the opened rig (:class:`dualscale.rig.client.RigClient`), its cameras
    by role (:class:`dualscale.capture.camera.Camera`, opened), the micro plan's LED selection and
    the capture options (:class:`dualscale.capture.session.CaptureOptions`)."""

    rig: Any
    cameras: dict[str, Any]
    lights: str = "ALL"
    options: Any = None
    #: ``--adaptive``: the micro plan's :class:`dualscale.adaptive.loop.AdaptiveOptions` (``None``: the fixed plan)
    adaptive: Any = None


def capture_spec(rc: RigCapture, progress: Callable[[int, int, str], None] | None = None,
                 runners: dict[str, Callable[[Any], Any]] | None = None
                 ) -> tuple[dict[str, Any], dict[str, Any], Callable[[Path], dict[str, Any]]]:
    """``(inputs, params, fn)`` of the capture stage: the micro plan (and the mid plan when a mid
    camera is given) captured into ``WORK/{micro,mid}/`` by ``fn(WORK)``
    (:class:`dualscale.capture.session.CaptureSession`, resumed from its journal there; a plan
    named in ``runners`` is run by ``runners[name](session)`` instead of ``session.run()``: the
    adaptive capture, which lives above this layer).  Its inputs are the rig's identification
    and the cameras' specs and serials, its parameters the plans and options (and the adaptive
    options); ``fn`` returns each plan's capture summary."""
    from dualscale.capture.plan import make_plan
    from dualscale.capture.session import CaptureOptions, CaptureSession, stable_spec

    plans = [make_plan("micro", rc.lights)] + ([make_plan("mid")] if "mid" in rc.cameras else [])
    opts = rc.options or CaptureOptions()
    ident = rc.rig.identity
    inputs = {"rig": None if ident is None else ident.text,
              "cameras": {r: [stable_spec(c.spec), c.serial] for r, c in sorted(rc.cameras.items())}}
    params = {"lights": rc.lights, "plans": [p.name for p in plans],
              "options": {k: v for k, v in asdict(opts).items() if k != "timeout_margin_s"}}
    if rc.adaptive is not None:
        params["adaptive"] = asdict(rc.adaptive)

    def fn(work: Path) -> dict[str, Any]:
        out = {}
        for plan in plans:
            cams = {r: rc.cameras[r] for r in plan.roles}
            session = CaptureSession(rc.rig, cams, plan, work / plan.name, opts, resume=True, progress=progress)
            run = (runners or {}).get(plan.name)
            summary = session.run() if run is None else run(session)
            out[plan.name] = {k: v for k, v in asdict(summary).items() if k != "dataset"}
        return out

    return inputs, params, fn


def check_rig_calibration(rc: RigCapture, calibration: Path) -> None:
    """Before capturing: the calibration must be of this rig (its id and dome layout) and cover
    every LED of the micro plan, or the capture would be refused by calibrate afterwards.  Records
    the calibration's id (file name and content hash) as the capture's ``calibration_id`` unless
    one was given.  Raises :class:`~dualscale.errors.CalibrationError` naming the LEDs it lacks,
    and :func:`dualscale.formats.calibration.read_calibration`'s errors for another rig's file."""
    from dualscale.capture.plan import make_plan
    from dualscale.capture.session import CaptureOptions
    from dualscale.formats.calibration import read_calibration
    from dualscale.geometry.dome import DomeGeometry

    opts = rc.options or CaptureOptions()
    ident = rc.rig.identity
    rig_id = opts.rig_id or (ident.text if ident is not None else None)
    cal = read_calibration(calibration, rig_id=rig_id, layout=DomeGeometry.from_regmap().signature())
    leds = {s.index for s in make_plan("micro", rc.lights).shots if s.kind == "led"}
    have = calibrated_leds(cal)
    if have is not None and not leds <= have:
        missing = sorted(leds - have)
        raise CalibrationError(f"{calibration}: no white-sheet capture for LED(s) {missing[:8]}"
                               f"{' ...' if len(missing) > 8 else ''} of --lights {rc.lights}: capture those lights "
                               "with the calibration, or choose --lights the calibration covers")
    if opts.calibration_id is None:
        rc.options = replace(opts, calibration_id=f"{calibration.name}#sha256:{file_sha256(calibration)[:12]}")


def calibrated_leds(cal: dict[str, Any]) -> set[int] | None:
    """The LED ids the calibration's micro camera has an ``r_c`` for, or None if it does not say."""
    rc = (cal.get("r_c") or {}).get("micro")
    if not isinstance(rc, dict):
        return None
    out = set()
    for key in rc:
        if str(key).startswith("led") and str(key)[3:].isdigit():
            out.add(int(str(key)[3:]))
    return out or None
