"""Issue 24 §1 and §2 for ``dualscale digitize``: the output-folder rule (another command's
outputs, another input's run, ``--overwrite``), every input checked before the run folder is made
(``--guidance`` named), and a run that fails its own check exits 1 naming it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dualscale.cli import main

ARGS = ["--quality", "draft", "--threads", "1", "--no-progress"]
SMALL = ["--size", "16", "--texel-um", "9", "--no-previews", "--no-progress", "--threads", "1"]


def _err(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_digitize_refuses_a_folder_holding_synth_outputs(sample, tmp_path, capsys):
    """`synth twill -o X; digitize syn -o X` exited 0 and mixed both commands' outputs."""
    x = tmp_path / "x"
    assert main(["synth", "twill", "-o", str(x), *SMALL]) == 0
    before = sorted(p.name for p in x.iterdir())
    capsys.readouterr()
    assert main(["digitize", str(sample / "micro"), "-o", str(x), *ARGS]) == 2
    err = _err(capsys)
    assert "dualscale synth" in err and "--overwrite" in err, err
    assert sorted(p.name for p in x.iterdir()) == before  # nothing added: no run.json, work/, stages/


def test_digitize_refuses_a_fit_folder(sample, tmp_path, capsys):
    """`fit syn -o F; digitize syn -o F --until calibrate` exited 0."""
    f = tmp_path / "f"
    assert main(["fit", str(sample / "micro"), "-o", str(f), "--preset", "draft", "--threads", "1",
                 "--no-progress", "--no-previews", "--cv-pixels", "0"]) == 0
    before = sorted(p.name for p in f.iterdir())
    capsys.readouterr()
    assert main(["digitize", str(sample / "micro"), "-o", str(f), "--until", "calibrate", *ARGS]) == 2
    assert "dualscale fit" in _err(capsys)
    assert sorted(p.name for p in f.iterdir()) == before


def test_digitize_refuses_the_run_of_another_input_and_overwrite_empties_it(sample, tmp_path, capsys):
    """`digitize other -o RUN_OF_SYN --until calibrate` rewrote run.json and kept the first run's
    stages; now it is refused, and with --overwrite the folder is emptied first."""
    other = tmp_path / "other"
    assert main(["synth", "leather", "-o", str(other), *SMALL, "--dataset", "--lights", "mod16"]) == 0
    run = tmp_path / "run"
    assert main(["digitize", str(sample / "micro"), "-o", str(run), "--until", "calibrate", *ARGS]) == 0
    (run / "notes.txt").write_text("mine")
    doc = (run / "run.json").read_text()
    capsys.readouterr()
    assert main(["digitize", str(other / "micro"), "-o", str(run), "--until", "calibrate", *ARGS]) == 2
    err = _err(capsys)
    assert "another run of digitize" in err and "--overwrite" in err, err
    assert (run / "run.json").read_text() == doc
    # the same input again: its own folder, resumed
    assert main(["digitize", str(sample / "micro"), "-o", str(run), "--until", "calibrate", *ARGS]) == 0
    assert "calibrate  up to date" in capsys.readouterr().out
    assert main(["digitize", str(other / "micro"), "-o", str(run), "--until", "calibrate", "--overwrite",
                 *ARGS]) == 0
    assert json.loads((run / "run.json").read_text())["input"] == str(other / "micro")
    assert not (run / "notes.txt").exists()


def test_a_run_folder_from_before_records_is_still_its_own(sample, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["digitize", str(sample / "micro"), "-o", str(run), "--until", "calibrate", *ARGS]) == 0
    (run / ".dualscale-output.json").unlink()
    assert main(["digitize", str(sample / "micro"), "-o", str(run), "--until", "calibrate", *ARGS]) == 0
    assert (run / ".dualscale-output.json").is_file()


def test_overwrite_removes_unrelated_files(tmp_path):
    """`synth ... -o F --overwrite` kept unrelated files; --overwrite empties the folder first."""
    f = tmp_path / "f"
    f.mkdir()
    (f / "unrelated.txt").write_text("x")
    (f / "sub").mkdir()
    assert main(["synth", "twill", "-o", str(f), *SMALL, "--overwrite"]) == 0
    assert not (f / "unrelated.txt").exists() and not (f / "sub").exists()
    assert (f / "maps" / "material.json").is_file()


def test_a_bad_guidance_is_refused_naming_it_before_the_run_folder_is_made(sample, tmp_path, capsys):
    """A folder of random PNGs was reported as "no manifest.json in ..." without naming
    --guidance; a corrupt guidance failed only after calibrate, fit and fly-outs had run."""
    from tests.photos.photoset import write_png

    pngs = tmp_path / "pngs"
    pngs.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        write_png(pngs / f"p{k}.png", rng.integers(0, 256, (24, 24, 3), dtype=np.uint8))
    corrupt = tmp_path / "corrupt.exr"
    corrupt.write_bytes(b"v/1\x01" + bytes(200))
    small = tmp_path / "small.png"
    write_png(small, rng.integers(0, 256, (40, 40, 3), dtype=np.uint8))
    cases = [(["--guidance", str(pngs)], "manifest.json"),
             (["--guidance", str(corrupt)], "cannot read"),
             (["--guidance", str(sample / "mid"), "--guidance-texel-mm", "1"], "px"),
             (["--guidance", str(small), "--transfer", "bogus"], "--transfer")]
    for extra, words in cases:
        run = tmp_path / "run"
        capsys.readouterr()
        assert main(["digitize", str(sample / "micro"), "-o", str(run), *extra, *ARGS]) == 2, extra
        err = _err(capsys)
        assert err.startswith("dualscale digitize: error: --guidance ") and words in err, err
        assert not run.exists(), extra


def test_a_corrupt_image_of_the_dataset_is_refused_before_any_stage(sample, tmp_path, capsys):
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(sample / "micro", ds)
    img = sorted((ds / "images").glob("*.exr"))[3]
    img.write_bytes(img.read_bytes()[:300])
    run = tmp_path / "run"
    assert main(["digitize", str(ds), "-o", str(run), *ARGS]) == 2
    err = _err(capsys)
    assert img.name in err and "cannot read" in err, err
    assert not run.exists()


def _digitize_fails_its_check(ds, run, capsys):
    """``digitize DS -o RUN --until fit`` exits 1, its last line naming the held-out check;
    ``(captured output, that last line)``."""
    capsys.readouterr()
    assert main(["digitize", str(ds), "-o", str(run), "--until", "fit", *ARGS]) == 1
    cap = capsys.readouterr()
    last = cap.err.strip().splitlines()[-1]
    assert last.startswith("dualscale digitize: check failed: fit held-out relative L1"), cap.err
    return cap, last


def test_a_run_that_fails_its_check_exits_1_naming_it(tmp_path, capsys):
    """Random-noise photographs: held-out L1 ~100 % reported, exit 0, and a warning to import
    the photographs that came from import.  Now exit 1, the last line names the check, the
    check is recorded in run.json, and the warning does not send the user to `dualscale import`."""
    from tests.photos.photoset import lights_one_side, render_sphere, write_png

    s = render_sphere(tmp_path / "ball", lights_one_side())
    rng = np.random.default_rng(1)
    for k in range(12):
        write_png(s.folder / f"ball.{k}.png", rng.integers(0, 256, (40, 40, 3), dtype=np.uint8))
    ds = tmp_path / "ds"
    assert main(["import", str(s.folder), "--lights", str(s.lp), "-o", str(ds), "--transfer", "srgb",
                 "--intensities", "equal", "--no-progress"]) == 0
    run = tmp_path / "run"
    cap, last = _digitize_fails_its_check(ds, run, capsys)
    assert "above the goal of at most 50 %" in last
    checks = json.loads((run / "run.json").read_text())["checks"]
    assert checks[0]["name"] == "fit held-out error" and checks[0]["ok"] is False and checks[0]["value"] > 0.5
    warns = json.loads((run / "stages" / "fit.json").read_text())["warnings"]
    assert not any("Import photographs with `dualscale import`" in w for w in warns), warns
    assert "Import photographs with `dualscale import`" not in cap.out + cap.err
    # the advice comes from the fit itself (fit/init.py: the observations know they were imported),
    # so a plain `dualscale fit` of the import gives it too
    assert any("came from `dualscale import`" in w for w in warns), warns
    capsys.readouterr()
    main(["fit", str(ds), "-o", str(tmp_path / "fit"), "--preset", "draft", "--no-progress", "--cv-pixels", "0"])
    err = capsys.readouterr().err
    assert "came from `dualscale import`" in err and "Import photographs with" not in err, err
    assert len(set(err.splitlines())) == len(err.splitlines()), err  # each warning once
    # a rerun (every stage up to date) fails the same check again
    assert main(["digitize", str(ds), "-o", str(run), "--until", "fit", *ARGS]) == 1


def test_the_epilog_lists_every_exit_code():
    from dualscale.cli.digitize import EXIT_EPILOG
    from dualscale.errors import EXIT_CODES
    from dualscale.pipeline import HELDOUT_L1_GOAL

    codes = [line.split()[0] for line in EXIT_EPILOG.splitlines()[1:] if line[:3].strip().isdigit()]
    assert sorted(int(c) for c in codes) == sorted(EXIT_CODES.values())
    assert f"{100 * HELDOUT_L1_GOAL:.0f} %" in EXIT_EPILOG


def test_noise_that_ignores_the_light_fails_the_constant_predictor_check(tmp_path, capsys):
    """Issue 24 trial: random-noise images passed the run's check (held-out 19-38 %, under the
    50 % goal), exit 0.  Now the fit must also predict the held-out lights better than each
    pixel's mean over the training lights (the per-pixel constant predictor): noise whose level
    ignores the light does not (measured: 2.5x the constant's error), so exit 1 naming that check;
    a real material beats it by far (the synthetic twill: 0.005x)."""
    from dualscale.pipeline import CONSTANT_MARGIN

    from .noise import make_noise_dataset

    ds = make_noise_dataset(tmp_path / "noise")
    run = tmp_path / "run"
    cap, last = _digitize_fails_its_check(ds, run, capsys)
    assert "the per-pixel constant predictor's" in last and f"below {CONSTANT_MARGIN:g}×" in last, last
    assert "check: " in cap.out and "✗" in cap.out
    checks = {c["name"]: c for c in json.loads((run / "run.json").read_text())["checks"]}
    assert checks["fit held-out error"]["ok"] is True  # the fixed goal alone cannot tell noise from a sample
    assert checks["fit against the constant predictor"]["ok"] is False
    assert checks["fit against the constant predictor"]["value"] > 1.5
    fit = json.loads((run / "stages" / "fit.json").read_text())["summary"]
    assert 0 < fit["heldout_constant_relative_l1"] < fit["heldout_relative_l1"]


def test_a_real_material_beats_the_constant_predictor_by_far(sample, tmp_path):
    run = tmp_path / "run"
    assert main(["digitize", str(sample / "micro"), "-o", str(run), "--until", "fit", *ARGS]) == 0
    checks = {c["name"]: c for c in json.loads((run / "run.json").read_text())["checks"]}
    assert [c["ok"] for c in checks.values()] == [True, True]
    assert checks["fit against the constant predictor"]["value"] < 0.1
