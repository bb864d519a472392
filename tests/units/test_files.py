"""Files: atomic, honest, readable (issue 13 §3).

A full disk leaves no short or empty file under a final name and no completion record beside
missing maps; a finished training run killed while saving its model is finished by ``--resume``;
damaged checkpoints and models are one-line errors naming the file; an output folder holding
another run's outputs is refused unless ``--overwrite``; an output folder that cannot be written
fails before any work; written files honour the umask."""

from __future__ import annotations

import errno
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dualscale.cli import main
from tests.units.conftest import small_dataset

ROOT = Path(__file__).resolve().parents[2]
FIT = ["--preset", "draft", "--threads", "1", "--cv-pixels", "0", "--no-previews"]


def _files(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): p.stat().st_size for p in root.rglob("*") if p.is_file()}


def _one_line(err: str) -> bool:
    return err.count("\n") == 1 and "Traceback" not in err


# ---- atomic outputs: a full disk ---------------------------------------------------------------

def _enospc_on(monkeypatch, name: str) -> None:
    """Make the maps writer fail with ENOSPC on the map file ``name`` (the disk fills up there)."""
    import dualscale.formats.maps as fmaps

    real = fmaps.write_exr

    def write_exr(path, *a, **k):
        if Path(path).name == name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(fmaps, "write_exr", write_exr)


def test_a_full_disk_leaves_no_fit_record_beside_missing_maps(tmp_path, monkeypatch, capsys):
    ds = small_dataset(tmp_path / "ds", size=8)
    out = tmp_path / "out"
    assert main(["fit", str(ds), "-o", str(out), *FIT]) == 0  # a complete earlier fit in the folder
    capsys.readouterr()
    _enospc_on(monkeypatch, "normal.exr")
    assert main(["fit", str(ds), "-o", str(out), *FIT, "--seed", "1"]) == 4
    err = capsys.readouterr().err
    assert _one_line(err) and "No space left on device" in err and "normal.exr" in err, err
    files = _files(out)
    # neither the fit's record nor the maps' record may vouch for a half-rewritten folder
    assert "fit.json" not in files and "material.json" not in files, files
    assert all(size > 0 for size in files.values()) and not any(".tmp-" in f for f in files), files


def _limited(limit: int):
    def pre() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return pre


def test_a_write_refused_by_the_kernel_leaves_no_short_file(tmp_path):
    """The real writers (OpenImageIO's EXR, JSON) under a file-size limit: every file that got
    past the limit fails, and nothing short or empty appears under a final name."""
    ds = small_dataset(tmp_path / "ds", size=8)
    out = tmp_path / "out"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env.pop("DUALSCALE_DEBUG", None)
    r = subprocess.run([sys.executable, "-m", "dualscale.cli", "fit", str(ds), "-o", str(out), *FIT],
                       capture_output=True, text=True, env=env, timeout=120, preexec_fn=_limited(1500))
    assert r.returncode == 4, r.stderr
    last = r.stderr.splitlines()[-1]  # (the fit's warnings about this random dataset come before)
    assert last.startswith("dualscale fit: error: ") and "File too large" in last and str(out) in last, r.stderr
    assert "Traceback" not in r.stderr
    files = _files(out)
    assert "fit.json" not in files and "material.json" not in files, files  # the maps did not all fit
    assert all(size > 0 for size in files.values()) and not any(".tmp-" in f for f in files), files


# ---- the propagation model: a crash while saving it, damaged files -----------------------------

@pytest.fixture(scope="module")
def twill(tmp_path_factory):
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("prop") / "twill"
    assert main(["synth", "twill", "-o", str(root), "--size", "32", "--texel-um", "6", "--dataset",
                 "--lights", "mod16", "--no-previews"]) == 0
    return root


TRAIN = ["--preset", "quick", "--batch", "2", "--crop", "32", "--width", "8", "--threads", "1",
         "--checkpoint-every", "2", "--no-amp"]


def test_a_finished_run_killed_while_saving_its_model_is_finished_by_resume(twill, tmp_path, capsys):
    """The last checkpoint is written before the model: with the model lost (the process died in
    its save), ``--resume`` writes it from the checkpoint, without training, even when the rerun
    names fewer iterations than the finished run had."""
    from dualscale.formats.model import read_model_file

    model = tmp_path / "m.dsp"
    assert main(["propagate", "train", str(twill), "-o", str(model), *TRAIN, "--iterations", "4"]) == 0
    first = read_model_file(model)
    model.unlink()  # the kill: the atomic save left no model file (and no partial one)
    assert main(["propagate", "train", str(twill), "-o", str(model), *TRAIN, "--iterations", "2",
                 "--resume"]) == 0, capsys.readouterr().err
    again = read_model_file(model)
    assert again["train"]["iterations"] == 4 and again["train"]["resumed_from"] == 4
    for k, v in first["state_dict"].items():
        assert torch.equal(v, again["state_dict"][k]), k


def _zero_middle(path: Path) -> None:
    b = bytearray(path.read_bytes())
    mid = len(b) // 2
    b[mid:mid + 4096] = bytes(min(4096, len(b) - mid))
    path.write_bytes(bytes(b))


def test_damaged_models_and_checkpoints_are_one_line_errors_naming_the_file(twill, tmp_path, capsys):
    from dualscale.errors import FormatError
    from dualscale.fit.checkpoint import Checkpointer
    from dualscale.formats.model import read_model_file

    model = tmp_path / "m.dsp"
    assert main(["propagate", "train", str(twill), "-o", str(model), *TRAIN, "--iterations", "2"]) == 0
    capsys.readouterr()
    # a block of zeros inside the weights (lost sectors): torch would load it silently
    _zero_middle(model)
    with pytest.raises(FormatError, match=r"m\.dsp: damaged dualscale propagation model: .*checksum"):
        read_model_file(model)
    assert main(["propagate", "export", str(model)]) == 2
    err = capsys.readouterr().err
    assert _one_line(err) and str(model) in err and "damaged" in err, err
    # a truncated training checkpoint: one line, exit 2, naming it and what to do
    ckpt = Path(str(model) + ".ckpt")
    ckpt.write_bytes(ckpt.read_bytes()[:1000])
    assert main(["propagate", "train", str(twill), "-o", str(model), *TRAIN, "--iterations", "2",
                 "--resume"]) == 2
    err = capsys.readouterr().err
    assert _one_line(err) and str(ckpt) in err and "truncated" in err and "miniz" not in err, err
    # an emptied fit checkpoint
    fck = tmp_path / "checkpoint.pt"
    fck.write_bytes(b"")
    with pytest.raises(FormatError, match=r"checkpoint\.pt: damaged fit checkpoint: the file is empty"):
        Checkpointer(fck, "x").load()


# ---- foreign outputs ---------------------------------------------------------------------------

SYNTH = ["--size", "16", "--no-previews", "--threads", "1"]


def test_another_materials_folder_is_refused_unless_overwrite(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["synth", "twill", "-o", str(out), *SYNTH]) == 0
    assert (out / "maps" / "flyouts.json").is_file()
    assert main(["synth", "twill", "-o", str(out), *SYNTH]) == 0  # its own rerun: not foreign
    capsys.readouterr()
    assert main(["synth", "leather", "-o", str(out), *SYNTH]) == 2
    err = capsys.readouterr().err
    assert _one_line(err) and "--overwrite" in err and "twill" in err, err
    assert main(["synth", "leather", "-o", str(out), *SYNTH, "--overwrite"]) == 0
    # nothing of the twill survives: no fibres for a leather (render --shadows would use its relief)
    assert not (out / "maps" / "flyouts.json").exists()
    assert main(["fit", str(out), "-o", str(out), *FIT]) == 2  # another command's folder
    assert "synth" in capsys.readouterr().err


def test_a_material_without_relief_or_fibres_removes_the_stale_ones(tmp_path):
    from dualscale.sim.materials import generate
    from dualscale.sim.materials.io import save_material

    twill = generate("twill", 16, 0.0018, 0)
    save_material(tmp_path, twill, previews=False)
    assert (tmp_path / "geometry.exr").is_file() and (tmp_path / "flyouts.json").is_file()
    flat = generate("leather", 16, 0.0018, 0)
    flat.geometry = None  # a material with no relief
    save_material(tmp_path, flat, previews=False)
    assert not (tmp_path / "geometry.exr").exists() and not (tmp_path / "flyouts.json").exists()


def test_a_model_of_other_datasets_is_refused_unless_overwrite(twill, tmp_path, capsys):
    from dualscale.formats.model import read_model_file, write_model_file

    model = tmp_path / "m.dsp"
    doc = {"config": {"maps": ["albedo"]}, "state_dict": {}, "input_reference": [1, 1, 1],
           "train": {"datasets": ["another-material"]}}
    write_model_file(model, doc["config"], doc["state_dict"], doc["input_reference"], doc["train"])
    assert main(["propagate", "train", str(twill), "-o", str(model), *TRAIN, "--iterations", "2"]) == 2
    err = capsys.readouterr().err
    assert _one_line(err) and "another-material" in err and "--overwrite" in err, err
    assert read_model_file(model)["train"]["datasets"] == ["another-material"]


# ---- fail fast ---------------------------------------------------------------------------------

def test_an_output_folder_that_cannot_be_written_fails_before_any_work(tmp_path, monkeypatch, capsys):
    import dualscale.fit.api as api

    ds = small_dataset(tmp_path / "ds", size=8)
    (tmp_path / "afile").write_text("x")
    called = []
    monkeypatch.setattr(api, "fit_dataset", lambda *a, **k: called.append(1))
    assert main(["fit", str(ds), "-o", str(tmp_path / "afile" / "out"), *FIT]) == 2
    err = capsys.readouterr().err
    assert _one_line(err) and "cannot write the output folder" in err and "afile" in err, err
    assert not called


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_output_folder_fails_before_any_work(tmp_path, monkeypatch, capsys):
    import dualscale.fit.api as api

    ds = small_dataset(tmp_path / "ds", size=8)
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    called = []
    monkeypatch.setattr(api, "fit_dataset", lambda *a, **k: called.append(1))
    assert main(["fit", str(ds), "-o", str(ro / "out"), *FIT]) == 2
    assert "Permission denied" in capsys.readouterr().err and not called


def test_an_input_error_leaves_no_output_folder(tmp_path, capsys):
    out = tmp_path / "a" / "b"
    assert main(["fit", str(tmp_path / "missing"), "-o", str(out), *FIT]) == 2
    assert not (tmp_path / "a").exists()


# ---- permissions -------------------------------------------------------------------------------

def test_written_files_honour_the_umask(tmp_path):
    """Calibrations, maps, EXR, models and checkpoints get 0666 & ~umask, as open() gives,
    never mkstemp's 0600: the lab's other accounts read them."""
    from dualscale.bsdf import MaterialMaps
    from dualscale.fit.checkpoint import Checkpointer
    from dualscale.formats.atomic import atomic_dir, write_json
    from dualscale.formats.exr import write_exr
    from dualscale.formats.maps import save_maps
    from dualscale.formats.model import write_model_file

    old = os.umask(0o022)
    try:
        write_json(tmp_path / "calibration.json", {"a": 1})
        write_exr(tmp_path / "x.exr", np.zeros((4, 4, 3)))
        save_maps(tmp_path / "maps", MaterialMaps(albedo=torch.full((4, 4, 3), 0.5),
                                                  roughness=torch.full((4, 4, 1), 0.5)))
        write_model_file(tmp_path / "m.dsp", {}, {"w": torch.zeros(2)}, [1, 1, 1], {})
        Checkpointer(tmp_path / "checkpoint.pt", "f").save({"step": 1})
        with atomic_dir(tmp_path / "dir") as d:
            (d / "f").write_text("x")
        files = [p for p in tmp_path.rglob("*") if p.is_file() and p.name != "f"]
        assert len(files) >= 8
        for p in files:
            assert p.stat().st_mode & 0o777 == 0o644, (p, oct(p.stat().st_mode))
        assert (tmp_path / "dir").stat().st_mode & 0o777 == 0o755
    finally:
        os.umask(old)


# ---- a quiet exit ------------------------------------------------------------------------------

@pytest.mark.parametrize("entry", [["-m", "dualscale.cli"], ["-c", "from dualscale.cli import run; run()"]])
def test_no_nanobind_leak_report_at_exit(tmp_path, entry):
    out = tmp_path / "s"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run([sys.executable, *entry, "synth", "twill", "-o", str(out), "--size", "16", "--threads", "1"],
                       capture_output=True, text=True, env=env, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert "leaked" not in r.stderr and "nanobind" not in r.stderr, r.stderr
