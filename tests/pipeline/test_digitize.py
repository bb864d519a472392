"""`dualscale digitize` end to end on the virtual rig's dataset: stages, records, resume, refusal."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dualscale.cli import main
from dualscale.pipeline import STAGES

ARGS = ["--quality", "draft", "--threads", "1", "--no-progress"]


def _digitize(sample: Path, run: Path, *extra: str) -> int:
    return main(["digitize", str(sample / "micro"), "-o", str(run), "--guidance", str(sample / "mid"), *ARGS, *extra])


def _records(run: Path) -> dict[str, dict]:
    return {s: json.loads((run / "stages" / f"{s}.json").read_text()) for s in STAGES
            if (run / "stages" / f"{s}.json").is_file()}


@pytest.fixture(scope="module")
def full_run(sample, tmp_path_factory) -> tuple[Path, str]:
    """``(run folder, stdout)`` of one fresh digitize of the sample, every stage, shared by the
    tests that only read it (its fit and flyouts stages are the ones ``--until fit`` /
    ``--until flyouts`` run with the same options)."""
    import contextlib
    import io

    run = tmp_path_factory.mktemp("full") / "run"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert _digitize(sample, run) == 0
    return run, out.getvalue()


def test_digitize_runs_every_stage_and_records_it(full_run):
    run, out = full_run
    recs = _records(run)
    assert list(recs) == list(STAGES)
    for name, r in recs.items():
        assert r["format"] == "dualscale-stage" and r["stage"] == name
        assert r["seconds"] >= 0 and r["finished"] and "dualscale" in r["versions"] and "torch" in r["versions"]
        assert all((run / p).is_file() for p in r["outputs"])
    assert recs["fit"]["params"]["preset"] == "draft"
    fit = recs["fit"]["summary"]
    assert 0 < fit["heldout_relative_l1"] < 0.2 and 0 < fit["heldout_baseline_relative_l1"]
    # the maps are fitted on every light (32 LEDs x P0/P90); the held-out figure is cross-validated
    assert fit["images"] == fit["train_images"] == 64 and fit["leds"] == fit["fitted_leds"] == 32
    assert recs["fit"]["params"]["cv_pixels"] == 2000 and recs["fit"]["params"]["cv_folds"] == "auto"
    assert fit["heldout_method"] == "8-fold cross-validation over 32 lights on 1024 sample pixels"
    fit_json = json.loads((run / "fit" / "maps" / "fit.json").read_text())
    assert fit_json["lights"]["fitted_images"] == fit_json["lights"]["images"] == 64
    ho = json.loads((run / "fit" / "heldout" / "heldout.json").read_text())
    assert sorted(l["led_id"] for l in ho["lights"]) == list(range(0, 127, 4))  # every light has its error
    assert all(0 < l["relative_l1"] < 0.5 and 0 <= l["fold"] < 8 for l in ho["lights"])
    assert sorted(i for f in ho["folds"] for i in f) == list(range(0, 127, 4)) and len(ho["folds"]) == 8
    assert len(ho["renders"]) == 8 and not any(r["held_out"] for r in ho["renders"])
    assert all((run / "fit" / "heldout" / r[k]).is_file() for r in ho["renders"] for k in ("capture", "render"))
    assert (run / "fit" / "maps" / "material.json").is_file() and (run / "fit" / "residual.exr").is_file()
    assert json.loads((run / "fit" / "maps" / "material.json").read_text())["texel_mm"] == pytest.approx(0.009)
    assert (run / "export" / "micro" / "maps" / "albedo.exr").is_file()
    exp = recs["export"]["summary"]["exports"]
    assert set(exp) == {"micro", "mesoscale"}
    for scale, e in exp.items():
        doc = json.loads((run / "export" / scale / "export.json").read_text())
        assert set(doc["formats"]) == {"maps", "exr", "mtlx", "gltf", "glb", "u3m"} and doc["name"] == e["name"]
        assert doc["repeat_mm"][0] > 0 and all((run / "export" / scale / f).is_file()
                                               for files in doc["formats"].values() for f in files)
    assert (run / "report" / "index.html").is_file()
    assert not (run / "work").exists() or not any((run / "work").iterdir())
    assert str(run / "report" / "index.html") in out and str(run / "export") in out
    assert "maps fitted on 64 of 64 images; held-out relative L1" in out and "8-fold cross-validation" in out


def test_rerun_skips_unchanged_stages_and_redoes_changed_ones(sample, tmp_path, capsys):
    run = tmp_path / "run"
    assert _digitize(sample, run, "--until", "fit") == 0
    first = _records(run)
    assert set(first) == {"calibrate", "fit"}
    capsys.readouterr()
    assert _digitize(sample, run, "--until", "fit") == 0
    assert "up to date" in capsys.readouterr().out
    assert _records(run)["fit"]["finished"] == first["fit"]["finished"]
    # a damaged output is noticed and the stage redone
    (run / "fit" / "maps" / "albedo.exr").write_bytes(b"garbage")
    assert _digitize(sample, run, "--until", "fit") == 0
    assert (run / "fit" / "maps" / "albedo.exr").read_bytes()[:4] == b"v/1\x01"  # an EXR again


def test_bad_input_is_refused_and_nothing_is_written(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["digitize", str(tmp_path), "-o", str(run), *ARGS]) == 2
    assert "not a photometric dataset" in capsys.readouterr().err
    assert not run.exists()


def test_kill_9_during_the_fit_then_resume(sample, tmp_path):
    """A run killed with SIGKILL in the middle of the fit leaves no half-written artefact under a
    final name, and the same command then finishes the run."""
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "dualscale.cli", "digitize", str(sample / "micro"), "-o", str(run), "--until", "fit",
           *ARGS]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    t0 = time.time()
    while time.time() - t0 < 120:  # wait until the fit stage is working
        if (run / "stages" / "calibrate.json").is_file() and (run / "work" / "fit").is_dir():
            break
        time.sleep(0.05)
    time.sleep(0.5)
    p.send_signal(signal.SIGKILL)
    p.wait()
    assert not (run / "stages" / "fit.json").exists() and not (run / "fit").exists()
    for f in run.rglob("*"):  # everything under a final name is complete: JSON parses
        if f.is_file() and f.suffix == ".json" and not f.name.startswith(".tmp-"):
            json.loads(f.read_text())
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert (run / "stages" / "fit.json").is_file() and (run / "fit" / "maps" / "material.json").is_file()


def test_inputs_a_later_stage_would_refuse_are_refused_before_anything_is_written(sample, tmp_path, capsys):
    """Camera counts without --calibration, a calibration that is not one, a PNG guidance without
    its transfer function: exit 2, one line, and no run folder."""
    import numpy as np

    from dualscale.formats.exr import write_png_preview

    raw = tmp_path / "raw"
    assert main(["synth", "leather", "-o", str(raw), "--size", "8", "--texel-um", "9", "--dataset", "--lights",
                 "mod32", "--realistic", "--no-previews", "--no-progress"]) == 0
    png = tmp_path / "guide.png"
    write_png_preview(png, np.full((16, 16, 3), 0.5))
    bad_cal = tmp_path / "cal.json"
    bad_cal.write_text("{}")
    cases = [([str(raw / "micro")], "--calibration"),
             ([str(raw / "micro"), "--calibration", str(bad_cal)], "not a dualscale-calibration"),
             ([str(sample / "micro"), "--guidance", str(png)], "--transfer"),
             ([str(sample / "micro"), "--export", "gltf,fbx"], "--export 'gltf,fbx'"),
             ([str(sample / "micro"), "--name", "../x"], "material name '../x'")]
    for args, words in cases:
        run = tmp_path / "run"
        capsys.readouterr()
        assert main(["digitize", *args, "-o", str(run), *ARGS]) == 2
        captured = capsys.readouterr()
        assert words in captured.err and len(captured.err.strip().splitlines()) == 1 and captured.out == ""
        assert not run.exists()


def test_outputs_get_the_usual_file_mode(sample, tmp_path):
    """Atomic writes go through mkstemp (mode 0600): the artefacts still get 0666 & ~umask."""
    old = os.umask(0o022)
    try:
        run = tmp_path / "run"
        assert _digitize(sample, run, "--until", "calibrate") == 0
    finally:
        os.umask(old)
    for f in (run / "run.json", run / "stages" / "calibrate.json", run / "calibrate" / "dataset" / "manifest.json"):
        assert f.stat().st_mode & 0o777 == 0o644, f
    assert (run / "calibrate").stat().st_mode & 0o777 == 0o755


def test_digitize_fits_in_tiles_on_workers_with_the_same_maps(sample, full_run, tmp_path, capsys):
    """``--workers 2``: the fit stage runs in tiles on a local Dask cluster (issue 16); its maps
    are the in-process stage's (``full_run``'s) bit for bit, so its record is the same and a
    rerun without ``--workers`` skips it."""
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    from dualscale.formats.maps import load_maps

    one, two = full_run[0], tmp_path / "two"
    assert _digitize(sample, two, "--until", "fit", "--workers", "2") == 0
    fit = json.loads((two / "fit" / "maps" / "fit.json").read_text())
    assert fit["tiled"]["engine"].startswith("local (2 workers") and fit["tiled"]["tiles"] >= 1
    a, _ = load_maps(one / "fit" / "maps")
    b, _ = load_maps(two / "fit" / "maps")
    import torch

    for (k, v), (_, w) in zip(a.items(), b.items(), strict=True):
        assert torch.equal(v, w), k
    assert _records(one)["fit"]["params"] == _records(two)["fit"]["params"]
    capsys.readouterr()
    assert _digitize(sample, two, "--until", "fit") == 0
    out = capsys.readouterr().out
    assert "fit        up to date" in out and "calibrate  up to date" in out, out


def test_the_fit_stage_out_of_core_gives_the_same_maps_and_evidence(sample, full_run, tmp_path, monkeypatch):
    """``--memory`` below the micro dataset's fit (issue 25): the fit stage reads the dataset
    band by band and writes the maps by rows, and its residual map and re-renders are read band
    by band too, as is the fly-out stage's confidence map; the maps equal the in-memory stage's
    bit for bit, the evidence to float32 rounding, and the stage's record (its params) is the
    same.  (The in-memory stages are ``full_run``'s.)"""
    import numpy as np
    import torch

    from dualscale.fit.observations import fit_layout
    from dualscale.fit.stream import BYTES_PER_SAMPLE, RESERVE
    from dualscale.formats.exr import read_exr
    from dualscale.formats.maps import load_maps

    from dualscale.fit import stream

    _, _, (h, w), images = fit_layout(sample / "micro")
    monkeypatch.setattr(stream, "MIN_PART_PIXELS", 1)  # a small sample: parts below the product's least
    memory = RESERVE + (h * w // 4) * images * BYTES_PER_SAMPLE
    one, two = full_run[0], tmp_path / "two"
    assert _digitize(sample, two, "--until", "flyouts", "--memory", str(memory)) == 0
    fit = json.loads((two / "fit" / "maps" / "fit.json").read_text())
    assert fit["out_of_core"]["parts"] >= 4
    # the fly-out stage read its confidence map band by band: the same map, the same fibres
    assert np.array_equal(read_exr(one / "flyouts" / "confidence.exr"), read_exr(two / "flyouts" / "confidence.exr"))
    assert _records(one)["flyouts"]["summary"] == _records(two)["flyouts"]["summary"]
    a, _ = load_maps(one / "fit" / "maps")
    b, _ = load_maps(two / "fit" / "maps")
    for (k, v), (_, u) in zip(a.items(), b.items(), strict=True):
        assert torch.equal(v, u), k
    ra, rb = (read_exr(r / "fit" / "residual.exr") for r in (one, two))
    assert np.array_equal(np.isnan(ra), np.isnan(rb)) and np.allclose(ra, rb, rtol=1e-5, atol=1e-7, equal_nan=True)
    ha, hb = (json.loads((r / "fit" / "heldout" / "heldout.json").read_text()) for r in (one, two))
    assert ha["lights"] == hb["lights"] and [r["led_id"] for r in ha["renders"]] == [r["led_id"] for r in hb["renders"]]
    for x, y in zip(ha["renders"], hb["renders"], strict=True):
        assert x["relative_l1"] == pytest.approx(y["relative_l1"], rel=1e-5)
        for k in ("capture", "render"):
            assert np.allclose(read_exr(one / "fit" / "heldout" / x[k]), read_exr(two / "fit" / "heldout" / y[k]),
                               rtol=1e-5, atol=1e-7)
    assert _records(one)["fit"]["params"] == _records(two)["fit"]["params"]


def test_digitize_a_dozen_photographs_fits_every_light_and_leaves_one_out(tmp_path, capsys):
    """Imported photographs under 12 lights: the final maps are fitted on all 12, the held-out
    error is leave-one-light-out over all 12 on the mask's pixels, and the capture/render pairs
    are re-renders of training lights, black outside the mask (never fitted)."""
    import numpy as np

    from dualscale.formats.exr import read_exr
    from tests.photos.photoset import lights_one_side, render_sphere

    s = render_sphere(tmp_path / "ball", lights_one_side())
    ds = tmp_path / "ds"
    assert main(["import", str(s.folder), "--lights", str(s.lp), "-o", str(ds), "--transfer", "srgb",
                 "--no-progress"]) == 0
    run = tmp_path / "run"
    assert main(["digitize", str(ds), "-o", str(run), "--until", "fit", *ARGS]) == 0
    fit = _records(run)["fit"]["summary"]
    assert fit["images"] == fit["train_images"] == 12 and fit["leds"] == fit["fitted_leds"] == 12
    pixels = int(s.mask.sum())  # fewer than the 2000 of the sample: all of them
    assert fit["heldout_method"] == f"leave-one-light-out cross-validation over 12 lights on {pixels} sample pixels"
    assert 0 < fit["heldout_relative_l1"] < 0.1
    ho = json.loads((run / "fit" / "heldout" / "heldout.json").read_text())
    assert [l["led_id"] for l in ho["lights"]] == list(range(12)) and ho["folds"] == [[i] for i in range(12)]
    assert [l["fold"] for l in ho["lights"]] == list(range(12))
    assert len(ho["renders"]) == 8 and not any(r["held_out"] for r in ho["renders"])
    ren = read_exr(run / "fit" / "heldout" / ho["renders"][0]["render"])
    assert (ren[~s.mask] == 0).all() and (ren[s.mask].max(-1) > 0).mean() > 0.5
    assert "maps fitted on 12 of 12 images" in capsys.readouterr().out


def test_the_memory_budget_reaches_the_propagate_stage(monkeypatch):
    """digitize --memory bounds the propagate stage too: its in-memory threshold is the budget's
    share (the stage peaks at about 5.5x what it holds), never above the stage's own."""
    from dualscale.pipeline import PROPAGATE_PEAK_FACTOR, _propagate_in_memory
    from dualscale.propagate.data import IN_MEMORY_BYTES

    monkeypatch.delenv("DUALSCALE_PROPAGATE_IN_MEMORY_MB", raising=False)
    assert _propagate_in_memory(None) is None
    assert _propagate_in_memory(2 * 1024 ** 3) == pytest.approx(2 * 1024 ** 3 / PROPAGATE_PEAK_FACTOR)
    assert _propagate_in_memory(64 * 1024 ** 3) == IN_MEMORY_BYTES
    monkeypatch.setenv("DUALSCALE_PROPAGATE_IN_MEMORY_MB", "0")
    assert _propagate_in_memory(2 * 1024 ** 3) == 0


def test_a_memory_budget_below_the_fits_least_is_refused_before_the_run_folder(sample, tmp_path, capsys):
    run = tmp_path / "run"
    assert _digitize(sample, run, "--memory", "10M", "--until", "fit") == 2
    assert "--memory 10 MiB is below what a fit of 64 images needs" in capsys.readouterr().err
    assert not run.exists()


def test_digitize_scores_the_fit_against_a_ground_truth(sample, tmp_path, capsys):
    """``--gt MAPS``: the fit stage is scored against the ground truth (``fit.json``'s
    ``ground_truth``, from which the report's uncertainty section shows the maps' errors beside
    their sigma and sigma's coverage, ``tests/report/test_uncertainty.py``); a folder that is no
    maps folder is refused before the run folder is made; the fit's line of sigma is printed."""
    bad = tmp_path / "not-maps"
    bad.mkdir()
    assert _digitize(sample, tmp_path / "refused", "--gt", str(bad)) == 2
    assert not (tmp_path / "refused").exists()
    run = tmp_path / "run"
    capsys.readouterr()
    assert _digitize(sample, run, "--until", "fit", "--gt", str(sample / "maps")) == 0
    assert "fit: uncertainty (" in capsys.readouterr().out  # the maps' sigma, as `dualscale fit` says it
    fit = json.loads((run / "fit" / "maps" / "fit.json").read_text())
    assert Path(fit["ground_truth"]["dir"]) == (sample / "maps").resolve()
    assert fit["ground_truth"]["errors"]["albedo_rmse"] < 0.05 and fit["uncertainty"]["maps"]
    assert _records(run)["fit"]["inputs"]["gt"]
