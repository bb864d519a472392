"""`dualscale capture` of the calibration targets through the simulated rig (issue 14 §3): each
target plan writes a capture set that `read_captures`, `calibrate` and `evaluate-device` take,
and holds what `dualscale synth-targets` (:func:`dualscale.sim.targets.write_session`) writes for
the same virtual rig, within sensor noise."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from dualscale.formats.captures import read_captures
from dualscale.rig.launcher import sim_binary

pytestmark = pytest.mark.skipif(not sim_binary().exists(), reason="POSIX simulator not built (make -C firmware posix)")

RIG = "virtual-dome-0"
WL = 0.95  # a sensor clipping below full scale, declared by the simulated cameras
MICRO = f"sim:micro?target=white_sheet&size=16&readout_ms=1&white_level={WL}"
MID = f"sim:mid?target=white_sheet&size=48&readout_ms=1&white_level={WL}"
JITTER = 1.0606774710153424  # write_session's DSLR exposure jitter of the mid diffuse captures (Defects seed 0)


def _capture(plan: str, out: Path, *cameras: str, lights: str = "ROW0", speed: str = "10", extra=()) -> int:
    from dualscale.cli import main

    cams = [x for c in cameras for x in ("--camera", c)]
    return main(["capture", plan, "-o", str(out), "--port", "sim", *cams, "--lights", lights, "--rig-id", RIG,
                 "--sim-speed", speed, "--max-exposure", "60", "--no-progress", *extra])


def _synth(out: Path, parts: tuple[str, ...], cameras: tuple[str, ...], **defects):
    """write_session for the virtual rig the captures ran on: LED 0 only (ROW0 = led_step >= 127)."""
    from dualscale.sim.targets import Defects, SynthConfig, write_session

    cfg = SynthConfig(led_step=200, cameras=cameras, rig_id=RIG, white_level=WL, dot_px=128)
    write_session(out, cfg, Defects(**defects), parts=parts)
    return read_captures(out)


def _rates(cs) -> dict:
    """Each non-dark group's HDR merge [DN/s] (the calibration's own merge, dark model and white level)."""
    from dualscale.calib.pipeline import Session

    s = Session(cs)
    return {g.id: s.merged(g).radiance for g in cs.groups if g.target != "dark"}


def _same_within_noise(a: dict, b: dict, scale: dict | None = None, mean_tol: float = 0.01, pix_tol: float = 0.03):
    """Per group: channel means agree within ``mean_tol`` and the median per-pixel difference is
    under ``pix_tol`` of the group's mean (the captures' and synth-targets' noise are independent
    draws of the same sensor model; 12 bits, shot and read noise)."""
    assert set(a) == set(b)
    for gid in a:
        x, y = a[gid], b[gid] * (scale or {}).get(gid, 1.0)
        m = y.reshape(-1, 3).mean(0)
        assert np.all(np.abs(x.reshape(-1, 3).mean(0) / m - 1) < mean_tol), (gid, x.reshape(-1, 3).mean(0) / m)
        assert float(np.median(np.abs(x - y))) < pix_tol * float(m.mean()), gid


@pytest.fixture(scope="module")
def white_sheet(tmp_path_factory):
    root = tmp_path_factory.mktemp("ws")
    assert _capture("white-sheet", root / "cal", MICRO, MID) == 0
    return root


def test_white_sheet_capture_equals_synth_targets_within_noise(white_sheet):
    """write_session's white-sheet groups (micro at P0 and P90, mid without analyser, under LED 0,
    the diffuse group and back light 0), camera records (declared white level 0.95), markers and
    dark groups, with the same signal (the mid camera's diffuse captures aside: synth-targets
    scales them by a DSLR's exposure jitter, which a gate-triggered camera has not)."""
    cap = read_captures(white_sheet / "cal")
    ref = _synth(white_sheet / "ref", ("white_sheet",), ("micro", "mid"))
    assert cap.rig == ref.rig
    assert {g.id for g in cap.groups} == {g.id for g in ref.groups}
    assert cap.manifest["cameras"] == ref.manifest["cameras"]
    assert cap.white_level("micro") == [WL] * 3
    assert cap.manifest["markers"] == ref.manifest["markers"]
    assert sorted(cap.select(target="dark", camera="micro")[0].exposures_s)[0] == 0.01  # the metering darks
    _same_within_noise(_rates(cap), _rates(ref), {"mid_white_sheet_diffuse_nopol": 1 / JITTER})
    rec = json.loads((white_sheet / "cal" / "parts" / "white-sheet" / "capture.json").read_text())
    assert rec["summary"]["retakes"] == 0 and rec["plan"]["name"] == "white-sheet"


def test_parts_share_a_capture_set_and_must_agree(white_sheet, capsys):
    """A rerun of a finished part resumes and takes nothing; another plan into the same set with
    another micro camera is refused before anything is taken (one camera record per name)."""
    cal = white_sheet / "cal"
    before = (cal / "captures.json").read_text()
    assert _capture("white-sheet", cal, MICRO, MID) == 2  # a finished part needs --resume
    assert _capture("white-sheet", cal, MICRO, MID, extra=("--resume",)) == 0
    assert "6 shots (18 frames; 6 from an earlier run)" in capsys.readouterr().out
    after = json.loads((cal / "captures.json").read_text())
    assert [g["id"] for g in after["groups"]] == [g["id"] for g in json.loads(before)["groups"]]
    other = MICRO.replace("size=16", "size=12").replace("white_sheet", "polarization")
    assert _capture("polarization", cal, other) == 2
    assert "camera 'micro' of the polarization part differs" in capsys.readouterr().err
    assert not (cal / "parts" / "polarization" / "journal.jsonl").exists()


def test_chart_capture_equals_synth_targets_within_noise(tmp_path):
    """The chart plan: centred, mid and polar0 image the whole chart under LED 0 and the diffuse
    group (polar0's corners from its view of the holder: synth-targets' hand-given corners); then
    the chart is moved 24 times and the micro camera takes each patch at P0 and P90.  The groups
    and the signal are synth-targets'.  Long exposures of one LED close together exceed its duty
    budget in one sequence: those batches are split where the firmware refuses them, never taken
    again.  (Simulator at speed 0: 103 shots, 394 s of exposures.)"""
    polar = "sim:polar0?target=chart&size=48&readout_ms=1&white_level=0.95"
    cams = [c.replace("white_sheet", "chart") for c in (MICRO, MID)] + [polar]
    assert _capture("chart", tmp_path / "cal", *cams, speed="0") == 0
    cap = read_captures(tmp_path / "cal")
    ref = _synth(tmp_path / "ref", ("chart",), ("micro", "mid", "polar0"))
    assert {g.id for g in cap.groups} == {g.id for g in ref.groups}
    assert len(cap.select(target="patch")) == 24 * 2 * 2
    assert {g.id for g in cap.groups if g.target == "chart"} == {
        "mid_chart_led000_nopol", "mid_chart_diffuse_nopol", "polar0_chart_led000_nopol", "polar0_chart_diffuse_nopol"}
    assert cap.manifest["chart"]["layout"] == ref.manifest["chart"]["layout"]
    np.testing.assert_allclose(cap.manifest["chart"]["corners"]["polar0"], ref.manifest["chart"]["corners"]["polar0"])
    assert cap.manifest["markers"] == ref.manifest["markers"]
    rec = json.loads((tmp_path / "cal" / "parts" / "chart" / "capture.json").read_text())
    assert rec["summary"]["retakes"] == 0
    _same_within_noise(_rates(cap), _rates(ref), {"mid_chart_diffuse_nopol": 1 / JITTER}, pix_tol=0.05)


def test_dot_grid_is_the_full_resolution_micro_camera(tmp_path):
    from dualscale.calib.evaluate import sharpness_map

    cam = "sim:micro?target=dot_grid&size=128&texel_um=1.8&readout_ms=1&white_level=0.95"
    assert _capture("dot-grid", tmp_path / "cal", cam) == 0
    cap = read_captures(tmp_path / "cal")
    ref = _synth(tmp_path / "ref", ("dot_grid",), ("micro",))
    assert {g.id for g in cap.groups} == {"micro_dots_dark_off_nopol", "micro_dots_dot_grid_diffuse_nopol"}
    own = dict(cap.manifest["cameras"]["micro_dots"])
    assert own.pop("white_level") == [WL] * 3  # declared by the camera (synth-targets leaves it to be measured)
    assert own == ref.manifest["cameras"]["micro_dots"]
    a = _rates(cap)
    _same_within_noise(a, {k: v for k, v in _rates(ref).items() if k in a}, pix_tol=0.04)
    xy, sharp = sharpness_map(a["micro_dots_dot_grid_diffuse_nopol"])
    assert len(xy) >= 1 and np.all((sharp > 0.1) & (sharp < 1.0))


def test_polarization_sweep_measures_the_analyser_offset(tmp_path):
    """The analyser swept 0..170 degrees (absolute) under LED 0 on the glossy dark target: the
    sweep's intensities are synth-targets', and the device evaluation's Malus fit recovers the
    injected 4 degree misalignment.  Long exposures of one LED in a row exceed its duty budget in
    one sequence: the batches are split where the firmware refuses them, never taken again.
    (Simulator at speed 0: device time jumps from exposure to exposure.)"""
    from dualscale.calib import colourref as cr
    from dualscale.calib.evaluate import polarization
    from dualscale.calib.pipeline import Session

    cam = "sim:micro?target=polarization&size=16&readout_ms=1&white_level=0.95&analyzer_offset=4"
    assert _capture("polarization", tmp_path / "cal", cam, speed="0") == 0
    cap = read_captures(tmp_path / "cal")
    pol = cap.select(target="polarization")
    assert sorted(g.analyzer_deg for g in pol) == [float(a) for a in range(0, 180, 10)]
    assert not any(g.analyzer_relative for g in pol)
    rec = json.loads((tmp_path / "cal" / "parts" / "polarization" / "capture.json").read_text())
    assert rec["summary"]["retakes"] == 0
    (res,) = polarization(Session(cap))
    assert abs(-res.error_deg - 4.0) < 0.5, res.error_deg
    ref = _synth(tmp_path / "ref", ("polarization",), ("micro",), analyzer_offset_deg=4.0)
    s = Session(ref)
    want = {g.analyzer_deg: float(cr.luminance(s.merged(g).radiance).mean()) for g in ref.select(target="polarization")}
    s = Session(cap)
    got = {g.analyzer_deg: float(cr.luminance(s.merged(g).radiance).mean()) for g in pol}
    for a in want:
        assert abs(got[a] / want[a] - 1) < 0.02, (a, got[a] / want[a])


def test_a_real_rig_needs_the_holder_geometry_and_the_operator(tmp_path, capsys):
    """With a camera that is not simulated, the mid camera's white markers must be given
    (--holder), and every setup is an instruction the operator confirms on stdin."""
    import cv2

    from dualscale.capture.camera import open_camera
    from dualscale.capture.plan import Setup
    from dualscale.cli.capture import make_operator
    from dualscale.errors import InputError

    png = tmp_path / "mid.png"
    cv2.imwrite(str(png), np.full((48, 48, 3), 128, np.uint8))
    assert _capture("white-sheet", tmp_path / "cal", MICRO, f"mid=uvc:{png}") == 2
    err = capsys.readouterr().err
    assert "white-marker boxes are not given: --holder FILE" in err
    cam = open_camera(f"uvc:{png}")
    try:
        out = io.StringIO()
        make_operator({"mid": cam}, False, out, io.StringIO("\n"))(Setup("chart", 18))
        assert "move the ColorChecker so that patch 18 (white 9.5 (.05 D)) fills" in out.getvalue()
        with pytest.raises(InputError, match="not confirmed"):
            make_operator({"mid": cam}, False, out, io.StringIO(""))(Setup("white_sheet"))
        make_operator({"mid": cam}, True, out, io.StringIO(""))(Setup("dot_grid"))  # --target-ready: no wait
    finally:
        cam.close()


@pytest.mark.slow
def test_calibration_from_the_rig_agrees_with_synth_targets(tmp_path):
    """`dualscale calibrate` on a captured white-sheet + chart set against the same on
    `synth-targets`' set of the same virtual rig (LED 0, micro 16 px, mid 48 px, sensors clipping at
    0.95): r_c, r_ws, the measured patch colours, the CCMs' fit and the white level agree within
    what the sensor noise of two independent draws allows; then the dot grid and the polarisation
    sweep join the set and `evaluate-device` runs on it."""
    from dualscale.calib.ccm import delta_e_patches
    from dualscale.calib.pipeline import calibrate, light_kind, measure_patches, session_with
    from dualscale.cli import main
    from dualscale.formats.calibration import read_calibration

    cal = tmp_path / "cal"
    assert _capture("white-sheet", cal, MICRO, MID) == 0
    chart = [c.replace("white_sheet", "chart") for c in (MICRO, MID)]
    assert _capture("chart", cal, *chart, speed="0") == 0  # 98 shots, 394 s of exposures at LED 0
    assert main(["calibrate", str(cal), "-o", str(tmp_path / "rig.calib.json"), "--no-progress"]) == 0
    a = read_calibration(tmp_path / "rig.calib.json", rig_id=RIG)
    ref = _synth(tmp_path / "ref", ("white_sheet", "chart"), ("micro", "mid"))
    b = calibrate(ref)
    assert a["white_level"] == b["white_level"]
    for cam in ("micro", "mid"):
        for light, v in b["r_c"][cam].items():
            want = np.asarray(v) / (JITTER if (cam, light) == ("mid", "diffuse") else 1.0)
            assert np.all(np.abs(np.asarray(a["r_c"][cam][light]) / want - 1) < 0.01), (cam, light)
    assert np.all(np.abs(np.asarray(a["r_ws"]) / np.asarray(b["r_ws"]) - 1) < 0.02)  # 2 x 4 marker pixels
    pa = measure_patches(session_with(read_captures(cal), a))
    pb = measure_patches(session_with(ref, b))
    for cam in ("micro", "mid"):
        for light in pb[cam]:
            assert np.all(np.abs(pa[cam][light]["rgb"] / pb[cam][light]["rgb"] - 1) < 0.03), (cam, light)
            k = light_kind(light)
            fit_a = delta_e_patches(np.asarray(a["ccm"][cam][k]["matrix"]), pa[cam][light]["rgb"]).mean()
            fit_b = delta_e_patches(np.asarray(b["ccm"][cam][k]["matrix"]), pb[cam][light]["rgb"]).mean()
            assert abs(fit_a - fit_b) < 0.75, (cam, light, fit_a, fit_b)
    np.testing.assert_allclose(a["ccm"]["micro"]["led"]["matrix"], b["ccm"]["micro"]["led"]["matrix"], atol=0.05)

    assert _capture("dot-grid", cal, "sim:micro?target=dot_grid&size=128&texel_um=1.8&readout_ms=1&white_level=0.95") == 0
    pol = MICRO.replace("white_sheet", "polarization") + "&analyzer_offset=3"
    assert _capture("polarization", cal, pol, speed="0") == 0
    cs = read_captures(cal)
    assert {g.target for g in cs.groups} == {"dark", "white_sheet", "chart", "patch", "dot_grid", "polarization"}
    assert main(["evaluate-device", str(cal), "--calibration", str(tmp_path / "rig.calib.json"), "-o",
                 str(tmp_path / "report"), "--no-progress"]) == 0
    res = json.loads((tmp_path / "report" / "results.json").read_text())["summary"]
    assert abs(res["polarization_error_deg"]["analyzer_misalignment"] - 3.0) < 0.5
    assert res["micro_mean_dE00"]["after"] < res["micro_mean_dE00"]["before"]
    assert res["sharpness_mean"] is not None and res["collimation_std_max"] > 0
