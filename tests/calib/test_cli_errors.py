import json
import shutil

import numpy as np
import pytest

from dualscale.cli import main
from dualscale.formats.exr import read_exr, write_exr


def _copy(session_dir, tmp_path):
    dst = tmp_path / "caps"
    shutil.copytree(session_dir[0], dst)
    return dst, json.loads((dst / "captures.json").read_text())


def _group(m, **kw):
    return next(g for g in m["groups"] if all(g.get(k) == v for k, v in kw.items()))


def _fails(capsys, args, out, pattern):
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "error:" in err and pattern in err, err
    assert not out.exists()
    assert not list(out.parent.glob(f".{out.name}*"))


def test_missing_bracket(session_dir, tmp_path, capsys):
    caps, m = _copy(session_dir, tmp_path)
    (caps / _group(m, target="white_sheet", camera="micro")["files"][0]).unlink()
    _fails(capsys, ["calibrate", str(caps), "-o", str(tmp_path / "c.json")], tmp_path / "c.json", "missing")


def test_all_saturated(session_dir, tmp_path, capsys):
    caps, m = _copy(session_dir, tmp_path)
    g = _group(m, target="white_sheet", camera="polar0")
    for f in g["files"]:
        write_exr(caps / f, np.ones_like(read_exr(caps / f)))
    _fails(capsys, ["calibrate", str(caps), "-o", str(tmp_path / "c.json")], tmp_path / "c.json", "saturated")


def test_chart_not_found(session_dir, tmp_path, capsys):
    caps, m = _copy(session_dir, tmp_path)
    g = _group(m, target="chart", camera="mid", light={"kind": "diffuse", "id": None})
    for f in g["files"]:
        img = read_exr(caps / f)
        write_exr(caps / f, np.full_like(img, float(np.median(img))))
    _fails(capsys, ["calibrate", str(caps), "-o", str(tmp_path / "c.json")], tmp_path / "c.json", "ColorChecker")


def test_mismatched_sizes(session_dir, tmp_path, capsys):
    caps, m = _copy(session_dir, tmp_path)
    f = _group(m, target="white_sheet", camera="mid")["files"][0]
    write_exr(caps / f, np.zeros((10, 12, 3)))
    _fails(capsys, ["calibrate", str(caps), "-o", str(tmp_path / "c.json")], tmp_path / "c.json", "camera")


def test_calibration_from_another_rig(session_dir, calibration, tmp_path, capsys):
    from dualscale.formats.calibration import write_calibration

    other = tmp_path / "other.json"
    write_calibration(other, {**calibration, "rig": {"id": "another-rig", "layout": calibration["rig"]["layout"]}})
    out = tmp_path / "rep"
    _fails(capsys, ["evaluate-device", str(session_dir[0]), "--calibration", str(other), "-o", str(out)], out,
           "another-rig")
    before = other.read_text()
    assert main(["calibrate", str(session_dir[0]), "-o", str(other)]) == 2
    assert "another-rig" in capsys.readouterr().err
    assert other.read_text() == before  # not replaced


def test_calibrate_and_report_end_to_end(session_dir, tmp_path, capsys):
    cal = tmp_path / "cal.json"
    assert main(["calibrate", str(session_dir[0]), "-o", str(cal)]) == 0
    data = json.loads(cal.read_text())
    assert data["format"] == "dualscale-calibration" and data["version"] == 1
    assert data["rig"]["id"] == "virtual-dome-0" and data["provenance"]["manifest_sha256"]
    out = tmp_path / "rep"
    assert main(["evaluate-device", str(session_dir[0]), "--calibration", str(cal), "-o", str(out)]) == 0
    assert (out / "report.html").is_file() and (out / "colour_hemisphere.svg").is_file()
    res = json.loads((out / "results.json").read_text())
    assert abs(res["summary"]["polarization_error_deg"]["analyzer_misalignment"] - 3.0) < 0.5


@pytest.mark.slow
def test_full_session_cli(tmp_path):
    caps = tmp_path / "full"
    assert main(["synth-targets", "-o", str(caps), "--analyzer-offset", "2.5"]) == 0
    assert main(["calibrate", str(caps), "-o", str(tmp_path / "c.json")]) == 0
    assert main(["evaluate-device", str(caps), "--calibration", str(tmp_path / "c.json"), "-o", str(tmp_path / "r")]) == 0
