"""`dualscale synth-targets`, `dualscale calibrate` and `dualscale evaluate-device`."""

from __future__ import annotations

import argparse
from pathlib import Path

from dualscale.formats.atomic import write_json

from .common import add_output, add_work_options, apply_threads, output_folder, want_progress


def cmd_synth_targets(a: argparse.Namespace) -> int:
    from dualscale.sim.targets import Defects, SynthConfig, write_session

    apply_threads(a)
    cfg = SynthConfig(led_step=a.led_step, micro_px=a.micro_px, other_px=a.other_px, rig_id=a.rig_id)
    d = Defects(led_gain_sigma=a.led_gain_sigma, collimation_max=a.collimation, analyzer_offset_deg=a.analyzer_offset,
                blur_sigma_um=(a.blur_um[0], a.blur_um[1]), vignetting=a.vignetting, seed=a.seed)
    parts = tuple(a.parts.split(","))
    with output_folder(a, "synth-targets", [f"rig:{a.rig_id}", f"seed:{a.seed}"]):
        write_session(a.output, cfg, d, parts, progress=want_progress(a))
    print(Path(a.output) / "captures.json")
    return 0


def cmd_calibrate(a: argparse.Namespace) -> int:
    from dualscale.formats.calibration import read_calibration, write_calibration
    from dualscale.formats.captures import read_captures
    from dualscale.calib.pipeline import calibrate

    apply_threads(a)
    cs = read_captures(a.captures)
    out = Path(a.output)
    if out.exists() and not (a.force or a.overwrite):  # never silently replace another rig's calibration
        read_calibration(out, rig_id=cs.rig["id"])
    with output_folder(a, "calibrate", record=False, folder=out.absolute().parent):
        data = calibrate(cs, progress=want_progress(a))
        write_calibration(out, data)
    for cam, kinds in data["ccm"].items():
        for kind, f in kinds.items():
            d = f["mean_delta_e2000"]
            print(f"{cam:7s} {kind:8s} dE00 fit/held-out: before {d['before']['fit']:.2f}/{d['before']['held_out']:.2f}"
                  f"  LS {d['least_squares']['fit']:.2f}/{d['least_squares']['held_out']:.2f}"
                  f"  CIEDE2000 {d['ciede2000']['fit']:.2f}/{d['ciede2000']['held_out']:.2f}")
    print(out)
    return 0


def _evaluate(s) -> tuple[dict, dict]:
    """Every measurement of the device evaluation on a calibrated session: results, summary."""
    import numpy as np

    from dualscale.calib import evaluate as ev

    cs = s.cs
    res: dict = {"colour": ev.colour_accuracy(s)}
    summary: dict = {}
    for cam, d in res["colour"].items():
        summary[f"{cam}_mean_dE00"] = {k: float(np.mean([np.mean(v[k]) for v in d.values()])) for k in ("before", "after")}
    dots = cs.select(target="dot_grid")
    if dots:
        xy, vals = ev.sharpness_map(s.merged(dots[0]).radiance)
        res["sharpness"] = {"centres": xy.tolist(), "values": vals.tolist()}
        summary["sharpness_mean"] = float(np.nanmean(vals)) if len(vals) else None
    pol = ev.polarization(s)
    if pol:
        res["polarization"] = {"leds": [{"led": p.led, "angles_deg": p.angles_deg.tolist(), "intensity": p.intensity.tolist(),
                                         "max_deg": p.max_deg, "min_deg": p.min_deg, "theory_max_deg": p.theory_max_deg,
                                         "error_deg": p.error_deg, "contrast": p.contrast} for p in pol]}
        e = np.array([p.error_deg for p in pol])
        summary["polarization_error_deg"] = {"mean_abs": float(np.abs(e).mean()), "max_abs": float(np.abs(e).max()),
                                             "analyzer_misalignment": float(-e.mean())}
    res["collimation"] = ev.collimation(s)
    if res["collimation"]:
        summary["collimation_std_max"] = max(res["collimation"].values())
    return res, summary


def cmd_evaluate(a: argparse.Namespace) -> int:
    from dualscale.calib import evaluate as ev
    from dualscale.formats.calibration import read_calibration
    from dualscale.formats.captures import read_captures
    from dualscale.calib.pipeline import session_with
    from dualscale.report.device import write_report

    from dualscale.progress import tracker

    apply_threads(a)
    cs = read_captures(a.captures)
    calib = read_calibration(a.calibration, rig_id=cs.rig["id"], layout=cs.rig.get("layout"))
    with output_folder(a, "evaluate-device", [a.captures, a.calibration]) as out:
        with tracker(want_progress(a), ev.merges_needed(cs), "evaluate-device", "group") as bar:
            res, summary = _evaluate(session_with(cs, calib, progress=bar))
        res["summary"] = summary
        write_json(out / "results.json", res)
        print(write_report(out, res, calib))
    return 0


def register(sub) -> None:
    """Add the calibration subcommands to the `dualscale` parser."""
    s = sub.add_parser("synth-targets", help="write synthetic calibration captures of the virtual dome")
    add_output(s, "capture-set directory to write (captures.json + EXRs)")
    s.add_argument("--led-step", type=int, default=8, help="use every N-th LED (default: 8)")
    s.add_argument("--micro-px", type=int, default=16, help="micro camera image side in pixels (default: 16)")
    s.add_argument("--other-px", type=int, default=48, help="mid and polar camera image side in pixels (default: 48)")
    s.add_argument("--rig-id", default="virtual-dome-0", help="rig id recorded in the captures (default: virtual-dome-0)")
    s.add_argument("--parts", default="white_sheet,chart,dot_grid,polarization",
                   help="comma-separated parts of the session to write (default: white_sheet,chart,dot_grid,polarization)")
    s.add_argument("--led-gain-sigma", type=float, default=0.05, help="relative spread of the LEDs' gains (default: 0.05)")
    s.add_argument("--collimation", type=float, default=0.08, help="max per-LED irradiance ramp over the micro field (default: 0.08)")
    s.add_argument("--analyzer-offset", type=float, default=0.0, help="injected analyser misalignment [deg] (default: 0)")
    s.add_argument("--blur-um", type=float, nargs=2, default=(2.0, 8.0), help="PSF sigma at centre and corner [um] (default: 2 8)")
    s.add_argument("--vignetting", type=float, default=0.25, help="corner fall-off of the cameras' vignetting (default: 0.25)")
    s.add_argument("--seed", type=int, default=0, help="seed of the injected defects and noise (default: 0)")
    add_work_options(s)
    s.set_defaults(fn=cmd_synth_targets)

    c = sub.add_parser("calibrate", help="compute the calibration file from a capture set")
    c.add_argument("captures", help="directory with captures.json")
    add_output(c, "calibration file (JSON, written atomically)")
    c.add_argument("--force", action="store_true", help="replace an existing file even from another rig")
    add_work_options(c)
    c.set_defaults(fn=cmd_calibrate)

    e = sub.add_parser("evaluate-device", help="colour, sharpness, polarisation and collimation report")
    e.add_argument("captures", help="directory with captures.json")
    e.add_argument("--calibration", required=True, help="calibration file (calibration.json) to evaluate the device with")
    add_output(e, "report directory (report.html, PNG/SVG, results.json)")
    add_work_options(e)
    e.set_defaults(fn=cmd_evaluate)
