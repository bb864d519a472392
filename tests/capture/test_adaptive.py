"""Adaptive capture on the simulated rig (issue 27, "Done when"): every fourth LED as candidates,
the firmware simulator (the real C core) and a simulated micro camera; the decisions journaled,
resumed identically after a kill -9, and the dataset a normal photometric dataset."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from dualscale.rig.launcher import sim_binary

pytestmark = pytest.mark.skipif(not sim_binary().exists(), reason="POSIX simulator not built (make -C firmware posix)")

CAM = "sim:micro?material=twill&size=12&texel_um=9&readout_ms=1"
ARGS = ["--lights", "MOD4", "--rig-id", "virtual-dome-0", "--sim-speed", "0", "--no-progress", "--threads", "1",
        "--adaptive", "--initial-leds", "6", "--batch-leds", "3"]


@pytest.fixture(scope="module")
def cal(tmp_path_factory) -> Path:
    """A calibration of every fourth LED (the candidates)."""
    from tests.units.rawrig import calibration_session

    return calibration_session(tmp_path_factory.mktemp("rig"), led_step=4)


def _capture(out: Path, cal: Path, *extra: str) -> int:
    from dualscale.cli import main

    return main(["capture", "micro", "-o", str(out), "--port", "sim", "--camera", CAM, "--calibration", str(cal),
                 *ARGS, *extra])


def _journal(out: Path) -> list[dict]:
    return [json.loads(ln) for ln in (out / "journal.jsonl").read_text().splitlines() if ln.strip()]


@pytest.fixture(scope="module")
def run(cal, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("adaptive") / "cap"
    assert _capture(out, cal, "--budget", "26") == 0
    return out


def test_an_adaptive_capture_chooses_rounds_and_stops_on_its_budget(run):
    """Round 0 spreads 6 LEDs, later rounds take 3 by the criterion; the decisions are journaled
    before their shots; the capture stops on the shot budget; capture.json records the rounds."""
    rec = json.loads((run / "capture.json").read_text())["adaptive"]
    rounds = rec["rounds"]
    assert rec["stop"] == "budget" and rounds[-1]["leds"] == [] and rounds[-1]["stop"] == "budget"
    taken = [r["leds"] for r in rounds[:-1]]
    assert len(taken[0]) == 6 and all(len(t) <= 3 for t in taken[1:]) and len(taken) >= 3
    flat = [i for t in taken for i in t]
    assert len(flat) == len(set(flat)) and all(i % 4 == 0 for i in flat)  # candidates only, none twice
    assert rec["shots"] == 2 * len(flat) + 2 <= 26
    for r in rounds[1:-1]:  # every candidate scored, the picks among the best by gain per second
        assert set(r["leds"]) == {p[0] for p in r["picks"]}
        assert all(str(i) in r["scores"] for i in r["leds"])
        assert all(set(v) == {"gain", "cost_s"} and v["cost_s"] > 0 for v in r["scores"].values())
        assert len(r["scores"]) == 32 - sum(len(t) for t in taken[:r["round"]])
    # journal order: a round's decision precedes its shots, its fit follows them
    j = _journal(run)
    pos = {(e["kind"], e.get("round")): k for k, e in enumerate(j) if e["kind"] in ("round", "fit")}
    shot_at = {e["key"]: k for k, e in enumerate(j) if e["kind"] == "shot"}
    for r in rounds[:-1]:
        for i in r["leds"]:
            for pol in ("p00000", "p09000"):
                assert pos[("round", r["round"])] < shot_at[f"led{i:03d}_{pol}"] < pos[("fit", r["round"])]
    # sigma falls as lights are added (the first round's fit has 6 LEDs, the last 6 + 3 k)
    s0, s1 = rounds[0]["fit"]["sigma"], rounds[-2]["fit"]["sigma"]
    assert s1["normal"] < s0["normal"] and s1["roughness"] < s0["roughness"]
    assert rec["floor_s"] > 0 and rounds[-2]["fit"]["floor_s"] == pytest.approx(rec["floor_s"])
    # every decision says what the whole candidate plan (32 LEDs) would give and cost
    for r in rounds[1:]:
        full = r["full_plan"]
        assert full["shots"] == 66 and full["cost_s"] > rounds[r["round"] - 1]["fit"]["floor_s"]
        assert set(full["sigma"]) == set(full["sigma_now"]) >= {"normal", "roughness"}
        assert all(full["sigma"][k] < full["sigma_now"][k] for k in ("normal", "roughness"))
    assert rounds[-1]["full_plan"]["cost_s"] > rec["floor_s"]


def test_the_adaptive_dataset_is_a_normal_photometric_dataset(run, cal, tmp_path):
    """Nothing is lost for later: calibrate and fit read it as any other; it holds exactly the
    LEDs taken (both analyser modes) and the back light."""
    from dualscale.calib.apply import to_radiance
    from dualscale.fit.observations import load_observations

    rec = json.loads((run / "capture.json").read_text())["adaptive"]
    leds = sorted(i for r in rec["rounds"] for i in r["leds"])
    to_radiance(run, tmp_path / "rad", cal)
    obs = load_observations(tmp_path / "rad")
    assert sorted(set(obs.led_ids.tolist())) == leds and obs.n == 2 * len(leds) and obs.backlight is not None
    assert obs.has_polarisation


def test_targets_and_gain_stop_an_adaptive_capture(cal, tmp_path, capsys):
    """A target every map meets at once stops after the first round; so does an unreachable
    minimum gain (each with its reason); a target on a map this sample's fit has no sigma of
    (an opaque twill's transmittance) is said to be one that cannot stop it."""
    assert _capture(tmp_path / "t", cal, "--target", "albedo=1,normal=90") == 0
    rec = json.loads((tmp_path / "t" / "capture.json").read_text())["adaptive"]
    assert rec["stop"] == "targets" and len(rec["rounds"]) == 2 and rec["shots"] == 14
    assert "cannot stop" not in capsys.readouterr().out
    assert _capture(tmp_path / "g", cal, "--min-gain", "1e9", "--target", "transmittance=0.01") == 0
    assert "no sigma of transmittance" in capsys.readouterr().out
    rec = json.loads((tmp_path / "g" / "capture.json").read_text())["adaptive"]
    assert rec["stop"] == "gain" and "under 1e+09" in rec["reason"] and len(rec["rounds"]) == 2
    # the relative target: the capture stops at the first decision whose predicted sigma of every
    # map is within 1000 % of the whole plan's predicted sigma, and not before
    assert _capture(tmp_path / "f", cal, "--target", "full+1000%") == 0
    rec = json.loads((tmp_path / "f" / "capture.json").read_text())["adaptive"]
    assert rec["stop"] == "targets" and "within 1000 % of the whole plan's" in rec["reason"]
    assert rec["options"]["full_target"] == 10.0 and len(rec["rounds"]) <= 4
    worst = [max(r["full_plan"]["sigma_now"][k] / r["full_plan"]["sigma"][k] for k in r["full_plan"]["sigma"])
             for r in rec["rounds"][1:]]
    assert all(w > 11.0 for w in worst[:-1]) and 1.0 < worst[-1] <= 11.0
    assert f"{100 * (worst[-1] - 1):.1f} %" in rec["reason"]


def test_the_rounds_samples_join_along_the_images(run, cal, tmp_path):
    """concat_images: the rounds' samples one after the other (images, directions, weights, LED
    ids, masks, signal scales), the back light the first's; the joined sample of the whole
    capture holds exactly the images of its dataset at the same pixels (in round order)."""
    from dualscale.adaptive.loop import concat_images
    from dualscale.calib.apply import to_radiance
    from dualscale.fit.observations import load_observations

    to_radiance(run, tmp_path / "rad", cal)
    obs = load_observations(tmp_path / "rad")
    idx = torch.arange(0, obs.shape[0] * obs.shape[1], 7)
    sample = obs.pixels(idx)
    rec = json.loads((run / "capture.json").read_text())["adaptive"]
    ids = [[i for i in r["leds"]] for r in rec["rounds"] if r["leds"]]
    parts = [sample.select_leds(set(k)) for k in ids]
    parts[1] = type(parts[1])(**{**parts[1].__dict__, "valid": None, "backlight": None})
    joined = concat_images(parts)
    assert joined.images.shape == (sample.n, 1, len(idx), 3) and joined.backlight is parts[0].backlight
    order = [k for i in ids for k, x in enumerate(sample.led_ids.tolist()) if x in set(i)]
    order = list(dict.fromkeys(order))
    torch.testing.assert_close(joined.images, sample.images[order])
    torch.testing.assert_close(joined.dirs, sample.dirs[order])
    assert joined.led_ids.tolist() == sample.led_ids[order].tolist()
    if sample.valid is not None:
        n1 = parts[0].n
        assert joined.valid[n1:n1 + parts[1].n].all()
    torch.testing.assert_close(joined.signal_scale, sample.signal_scale[order])


def test_parse_targets():
    """``--target``: the default is ``full+5%`` and no map; a given one replaces it whole."""
    from dualscale.adaptive.options import parse_targets
    from dualscale.errors import InputError

    assert parse_targets(None) == ({}, 0.05)
    assert parse_targets("full+10%") == ({}, pytest.approx(0.10))
    assert parse_targets("none") == ({}, None)
    assert parse_targets("normal=0.5") == ({"normal": 0.5}, None)
    assert parse_targets("normal=0.5,full+2.5%") == ({"normal": 0.5}, pytest.approx(0.025))
    for bad, why in [("full", r"full\+N%"), ("full+x%", "not a number"), ("full+5%,full+3%", "given twice"),
                     ("full+-5%", ">= 0"), ("gloss=1", "MAP=SIGMA"), ("", "without --target: full")]:
        with pytest.raises(InputError, match=why):
            parse_targets(bad)


def _round1_decided(entries: list[dict]) -> bool:
    return any(e["kind"] == "round" and e.get("round") == 1 for e in entries)


def _round0_shot(entries: list[dict]) -> bool:
    return sum(e["kind"] == "shot" for e in entries) >= 14 and not any(e["kind"] == "fit" for e in entries)


@pytest.mark.parametrize("when", [_round1_decided, _round0_shot], ids=["round 1 decided", "before round 0's fit"])
def test_kill_9_in_the_middle_resumes_with_identical_decisions(run, cal, tmp_path, when):
    """Done when: a kill -9 in the middle of an adaptive capture, then --resume, gives the same
    decisions and the same dataset as the uninterrupted capture (the module's ``run``): once a
    decision is journaled (its shots or its fit in flight), and after round 0's shots before its
    fit, so that its dark frames are taken by the resumed process (the virtual sensor's dark
    noise once depended on where the analyser happened to be: round 0's sigma, components and
    every later decision differed)."""
    from dualscale.formats.dataset import read_dataset

    out = tmp_path / "k"
    cmd = [sys.executable, "-m", "dualscale.cli", "capture", "micro", "-o", str(out), "--port", "sim", "--camera",
           CAM, "--calibration", str(cal), *ARGS, "--budget", "26"]
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if (out / "journal.jsonl").is_file() and when(_journal(out)):
            break
        time.sleep(0.02)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    assert not (out / "capture.json").exists()  # killed before the end
    before = {e["key"] for e in _journal(out) if e["kind"] == "shot"}
    r = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    # the summary counts the shots of the killed run, and its floor is the whole capture's
    assert f"; {len(before)} from an earlier run)" in r.stdout and len(before) >= 14, r.stdout
    floor = float(r.stdout.split("for a physical floor of ")[1].split(" s")[0])
    assert floor == pytest.approx(json.loads((run / "capture.json").read_text())["adaptive"]["floor_s"], abs=1.0)
    want = json.loads((run / "capture.json").read_text())["adaptive"]
    got = json.loads((out / "capture.json").read_text())["adaptive"]
    assert [x["leds"] for x in got["rounds"]] == [x["leds"] for x in want["rounds"]]
    assert [x.get("picks") for x in got["rounds"]] == [x.get("picks") for x in want["rounds"]]
    a, b = read_dataset(run), read_dataset(out)
    assert [x.file for x in a.records] == [x.file for x in b.records]
    for i in range(len(a.records)):
        np.testing.assert_array_equal(a.load(i), b.load(i))
    rounds = [e["round"] for e in _journal(out) if e["kind"] == "round"]
    assert rounds == sorted(set(rounds))  # no decision taken twice


def test_adaptive_refusals_come_before_the_rig(cal, tmp_path, capsys):
    """Bad adaptive input is refused (exit 2) before the simulator starts or the folder is made."""
    from dualscale.cli import main

    base = ["capture", "micro", "--port", "sim", "--camera", CAM, "--rig-id", "virtual-dome-0", "--no-progress"]
    cases = [
        (["--adaptive"], "needs the rig's calibration"),
        (["--adaptive", "--calibration", str(tmp_path / "none.json")], "no such file"),
        (["--adaptive", "--calibration", str(cal), "--lights", "MOD2"], "no white-sheet capture for LED(s) [2, 6"),
        (["--adaptive", "--calibration", str(cal), "--lights", "MOD4", "--target", "gloss=1"], "MAP=SIGMA"),
        (["--adaptive", "--calibration", str(cal), "--lights", "MOD4", "--budget", "lots"], "a shot count"),
        (["--adaptive", "--calibration", str(cal), "--lights", "MOD4", "--budget", "10"], "the first round alone"),
        (["--adaptive", "--calibration", str(cal), "--lights", "MOD4", "--criterion", "E"], "invalid choice"),
        (["--adaptive", "--calibration", str(cal), "--lights", "MOD4", "--budget", "-5"], "a positive shot count"),
        (["--adaptive", "--calibration", str(cal), "--lights", "MOD4", "--target", "normal=1,normal=2"],
         "normal is named twice"),
        (["--adaptive", "--calibration", str(cal), "--lights", "MOD4", "--initial-leds", "2"], "--initial-leds 2"),
        (["--adaptive", "--calibration", str(cal), "--lights", "MOD4", "--initial-leds", "40"],
         "--initial-leds 40: --lights MOD4 gives 32 candidate LEDs"),
        (["--adaptive", "--calibration", str(cal), "--lights", "MOD4", "--rig-id", "other-dome"],
         "calibration is from rig 'virtual-dome-0', the captures are from rig 'other-dome'"),
        (["--lights", "MOD4", "--budget", "40", "--criterion", "A"], "--budget, --criterion: options of the adaptive"),
    ]
    for k, (extra, why) in enumerate(cases):
        out = tmp_path / f"o{k}"
        assert main([*base, "-o", str(out), *extra]) == 2
        assert why in capsys.readouterr().err
        assert not out.exists()
    assert main(["capture", "mid", "-o", str(tmp_path / "m"), "--port", "sim", "--camera", CAM, "--adaptive",
                 "--calibration", str(cal), "--no-progress"]) == 2
    assert "micro plan" in capsys.readouterr().err


def test_another_rigs_calibration_is_refused_before_the_first_shot(cal, tmp_path, capsys):
    """Without --rig-id the firmware names the rig: a calibration of another rig is refused once
    the rig is open, before any shot, naming --rig-id."""
    from dualscale.cli import main

    out = tmp_path / "r"
    rc = main(["capture", "micro", "-o", str(out), "--port", "sim", "--camera", CAM, "--calibration", str(cal),
               *[x for x in ARGS if x not in ("--rig-id", "virtual-dome-0")], "--budget", "26"])
    err = capsys.readouterr().err
    assert rc == 2 and "calibration is from rig 'virtual-dome-0'" in err and "--rig-id" in err, err
    assert not (out / "journal.jsonl").is_file() or not [e for e in _journal(out) if e["kind"] == "shot"]


def test_resume_keeps_the_adaptive_capture_and_its_options(run, cal, tmp_path, capsys):
    """``--resume`` without ``--adaptive`` (which would take every candidate as a fixed plan),
    with other adaptive options (named, there and given), or ``--adaptive`` on a fixed plan's
    capture: refused (exit 2) before the rig, the journal untouched."""
    import shutil

    from dualscale.cli import main

    before = (run / "journal.jsonl").read_bytes()
    fixed = ["capture", "micro", "-o", str(run), "--port", "sim", "--camera", CAM, "--resume",
             *[x for x in ARGS if x not in ("--adaptive", "--initial-leds", "6", "--batch-leds", "3")]]
    assert main(fixed) == 2
    err = capsys.readouterr().err
    assert "holds an adaptive capture: continue it with --adaptive" in err and "--budget 26" in err, err
    assert _capture(run, cal, "--resume", "--budget", "30", "--criterion", "A") == 2
    err = capsys.readouterr().err
    assert "--budget: 26 there, 30 given" in err and "--criterion: D there, A given" in err, err
    assert _capture(run, cal, "--resume", "--budget", "26", "--target", "normal=0.5,full+10%") == 2
    assert "--target: full+5% there, normal=0.5,full+10% given" in capsys.readouterr().err
    assert (run / "journal.jsonl").read_bytes() == before
    plain = tmp_path / "fixed"  # the same capture's journal without its adaptive entries: a fixed plan's
    shutil.copytree(run, plain)
    keep = [ln for ln in before.decode().splitlines(keepends=True)
            if json.loads(ln)["kind"] not in ("adaptive", "round", "fit")]
    (plain / "journal.jsonl").write_text("".join(keep))
    assert _capture(plain, cal, "--resume", "--budget", "26") == 2
    assert "holds a capture of a fixed plan" in capsys.readouterr().err


def test_predicted_sigmas_on_known_matrices():
    """The predicted sigma of a map is the median over the pixels of the posterior ``F^-1``'s
    diagonal in the map's units (ior: ``eta = 1 + 2 v``), undetermined pixels left out; added
    information lowers it."""
    from dualscale.adaptive.design import DesignState, predicted_sigmas
    from dualscale.bsdf import Components

    n = 5
    h = torch.diag_embed(torch.tensor([[1.0, 2.0]] * n, dtype=torch.float64) * torch.arange(1, n + 1)[:, None])
    g = torch.diag_embed(torch.tensor([[4.0, 1.0]] * n, dtype=torch.float64))
    prior = torch.full((n, 2), 0.5, dtype=torch.float64)
    det = torch.ones(n, 2, dtype=torch.bool)
    det[4, 1] = False  # pixel 4's ior undetermined (held)
    st = DesignState(("roughness", "ior"), torch.full((n, 2), 0.3, dtype=torch.float64), h, g, 2.0, prior, det,
                     torch.zeros(n, 2, dtype=torch.float64), True, None, 1.0)
    params = {"roughness": torch.full((1, n, 1), 0.3), "ior": torch.full((1, n, 1), 0.3)}
    f = torch.stack([h[:, j, j] ** 2 / g[:, j, j] / 2.0 + 0.5 for j in range(2)], 1)
    got = predicted_sigmas(st, params, Components())
    assert got["roughness"] == pytest.approx(float(f[:, 0].rsqrt().median()))
    assert got["ior"] == pytest.approx(2.0 * float(f[:4, 1].rsqrt().double().median()))
    more = torch.stack([h, g], 1)  # the same lights again: twice the data information, the prior once
    after = predicted_sigmas(st, params, Components(), more)
    f2 = 2.0 * (f - 0.5) + 0.5
    assert after["roughness"] == pytest.approx(float(f2[:, 0].rsqrt().median()))
    assert after["ior"] == pytest.approx(2.0 * float(f2[:4, 1].rsqrt().median()))
    assert after["roughness"] < got["roughness"] and after["ior"] < got["ior"]
    assert predicted_sigmas(st, params, Components(), torch.zeros_like(more)) == pytest.approx(got)


def test_an_indefinite_information_matrix_is_lifted_not_fatal():
    """Rounding can leave a badly determined pixel's ``H G^-1 H`` indefinite (a sheer sample's
    first rounds once stopped the capture with a Cholesky error): its factor is that of the
    nearest matrix with eigenvalues at least EIG_FLOOR times the largest; good pixels are
    factored as they are."""
    from dualscale.adaptive.design import EIG_FLOOR, _cholesky

    good = torch.tensor([[4.0, 1.0], [1.0, 3.0]], dtype=torch.float64)
    bad = torch.tensor([[1.0, 1.0], [1.0, 1.0 - 1e-14]], dtype=torch.float64)  # eigenvalues 2 and ~ -5e-15
    f = torch.stack([good, bad])
    with pytest.raises(Exception):
        torch.linalg.cholesky(f)
    chol = _cholesky(f)
    torch.testing.assert_close(chol[0], torch.linalg.cholesky(good))
    rebuilt = chol[1] @ chol[1].T
    w = torch.linalg.eigvalsh(rebuilt)
    assert torch.isfinite(chol).all() and w.min() >= EIG_FLOOR * w.max() * 0.99
    torch.testing.assert_close(rebuilt, bad, atol=1e-10, rtol=0)


def test_the_design_criteria_on_known_matrices():
    """The D-gain is the log-determinant ratio of the information after and before, the A-gain
    the relative variance reductions; the greedy batch picks the best first and rescoring after
    a pick lowers a similar candidate's gain (diminishing returns)."""
    from dualscale.adaptive.design import DesignState, _information, choose_batch, gains

    torch.manual_seed(0)
    n, p, c = 5, 3, 4
    j = torch.randn(n, c, 6, p, dtype=torch.float64)
    info = torch.stack([j.transpose(-1, -2) @ j, 2.0 * j.transpose(-1, -2) @ j], 2)  # H_l, G_l
    info[:, 3] = info[:, 2]  # candidate 3 repeats candidate 2
    h0 = torch.eye(p, dtype=torch.float64).expand(n, p, p).clone() * 3
    g0 = torch.eye(p, dtype=torch.float64).expand(n, p, p).clone() * 5
    prior = torch.zeros(n, p, dtype=torch.float64)
    f0 = _information(h0, g0, 1.5, prior)
    for k in range(c):
        f1 = _information(h0 + info[:, k, 0], g0 + info[:, k, 1], 1.5, prior)
        want = torch.logdet(f1) - torch.logdet(f0)
        torch.testing.assert_close(gains(h0, g0, 1.5, prior, info, "D")[:, k], want)
        va = torch.linalg.inv(f1).diagonal(dim1=-2, dim2=-1) / torch.linalg.inv(f0).diagonal(dim1=-2, dim2=-1)
        torch.testing.assert_close(gains(h0, g0, 1.5, prior, info, "A")[:, k], (1 - va).sum(-1))
    st = DesignState(("x",), torch.zeros(n, p, dtype=torch.float64), h0, g0, 1.5, prior,
                     torch.ones(n, p, dtype=torch.bool), torch.zeros(n, 2, dtype=torch.float64), True, None, 1.0)
    picked, got, first = choose_batch(st, info, np.ones(c), 2)
    assert picked[0] == int(np.argmax(first)) and got[0] == pytest.approx(float(first.max()))
    if picked[0] in (2, 3):  # its twin is worth less once it is taken
        twin = 5 - picked[0]
        assert got[1] < first[twin] or picked[1] != twin
    assert all(g > 0 for g in got)
