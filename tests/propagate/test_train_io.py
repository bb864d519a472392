from dataclasses import replace

import pytest
import torch

from dualscale.propagate.data import load_source, sample_batch
from dualscale.formats.model import read_model_file
from dualscale.propagate.model import load_model, save_model
from dualscale.propagate.train import (PHASES, TrainOptions, build, checkpoint_path, preset_with, train, train_step,
                                       warm_start)
from dualscale.propagate.unet import PropagationUNet, UNetConfig


def test_presets():
    p = preset_with("paper")
    assert (p.lr, p.batch, p.iterations, p.weight_decay, p.crop) == (0.002, 40, 5000, 0.0, 128)
    with pytest.raises(ValueError):
        preset_with("slowest")


def _opts(**kw):
    return TrainOptions(width=8, progress=False, checkpoint_every=2, **kw)


def test_resume_equals_uninterrupted(twill, tmp_path):
    """A constant-rate run may be resumed to more iterations (a one-cycle one may not: its own test)."""
    src = [load_source(twill)]
    pre = lambda n: preset_with("quick", iterations=n, batch=2, crop=16)  # noqa: E731
    full = train(src, pre(6), tmp_path / "full.dsp", _opts(amp=False, schedule="constant")).model
    train(src, pre(4), tmp_path / "part.dsp", _opts(amp=False, schedule="constant"))
    res = train(src, pre(6), tmp_path / "part.dsp", _opts(amp=False, resume=True, schedule="constant"))
    assert res.resumed_from == 4 and len(res.history) == 6
    for (k, a), b in zip(full.state_dict().items(), res.model.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-6), k
    with pytest.raises(ValueError, match="different run"):
        train(src, preset_with("quick", iterations=8, batch=3, crop=16), tmp_path / "part.dsp",
              _opts(resume=True))
    assert checkpoint_path(tmp_path / "part.dsp").is_file()


def test_onecycle_schedule_trace_and_resume(twill, tmp_path, monkeypatch):
    """``--schedule onecycle``: the learning rates follow OneCycleLR (lr/25 -> peak lr after 30 %
    of the steps -> lr/25e4 at the last, cosine both ways; Adam's beta1 inversely); a run killed
    after its checkpoint at iteration 4 and resumed equals the uninterrupted run (the scheduler
    state is in the checkpoint); a one-cycle checkpoint is not extended to more iterations."""
    import dualscale.propagate.train as tr
    from dualscale.cli import main
    from dualscale.formats.torchfile import load_torch

    lr, n = 0.01, 10
    args = ["propagate", "train", str(twill), "-o", str(tmp_path / "full.dsp"), "--preset", "quick", "--iterations",
            str(n), "--batch", "2", "--crop", "16", "--width", "8", "--no-amp", "--no-progress", "--lr", str(lr),
            "--schedule", "onecycle"]
    assert main(args) == 0
    trace = [h["lr"] for h in load_torch(checkpoint_path(tmp_path / "full.dsp"), "ckpt")["history"]]
    peak = round(0.3 * n) - 1  # OneCycleLR's warm-up ends at step pct_start * total - 1 = 2
    assert trace[0] == pytest.approx(lr / 25) and trace[peak] == pytest.approx(lr)
    assert trace[-1] == pytest.approx(lr / 25e4)
    assert all(a < b for a, b in zip(trace[:peak], trace[1:peak + 1]))
    assert all(a > b for a, b in zip(trace[peak:-1], trace[peak + 1:]))
    mid = (peak + n - 1) / 2  # cosine annealing: half way down at the middle of the second phase
    assert trace[int(mid)] > (lr + lr / 25e4) / 2 > trace[int(mid) + 1]
    full, _ = load_model(tmp_path / "full.dsp")

    src = [load_source(twill)]
    pre = preset_with("quick", iterations=n, batch=2, crop=16, lr=lr)
    real_step = tr.train_step

    def killed_at_5(*a, **kw):  # the process dies during iteration 5, after the checkpoint at 4
        if a[-1] == 4:
            raise KeyboardInterrupt
        return real_step(*a, **kw)

    monkeypatch.setattr(tr, "train_step", killed_at_5)
    with pytest.raises(KeyboardInterrupt):
        train(src, pre, tmp_path / "part.dsp", _opts(amp=False, schedule="onecycle"))
    monkeypatch.setattr(tr, "train_step", real_step)
    assert load_torch(checkpoint_path(tmp_path / "part.dsp"), "ckpt")["iteration"] == 4
    res = train(src, pre, tmp_path / "part.dsp", _opts(amp=False, resume=True, schedule="onecycle"))
    assert res.resumed_from == 4 and [h["lr"] for h in res.history] == pytest.approx(trace)
    for (k, a), b in zip(full.state_dict().items(), res.model.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-6), k
    with pytest.raises(ValueError, match="cannot continue as a 12-iteration run"):
        train(src, replace(pre, iterations=12), tmp_path / "part.dsp", _opts(amp=False, resume=True,
                                                                              schedule="onecycle"))
    with pytest.raises(ValueError, match="different run"):  # a constant-lr run does not take the one-cycle checkpoint
        train(src, pre, tmp_path / "part.dsp", _opts(amp=False, resume=True, schedule="constant"))
    with pytest.raises(ValueError, match="schedule must be one of"):
        train(src, pre, tmp_path / "x.dsp", _opts(schedule="cosine"))


def test_train_step_phases_and_channels_last(twill):
    """train_step runs every phase in order; a channels-last model takes the same steps (float32)."""
    from contextlib import contextmanager

    src = [load_source(twill)]
    preset = preset_with("quick", iterations=2, batch=2, crop=16)
    losses = {}
    for cl in (False, True):
        opts = _opts(amp=False, channels_last=cl)
        model, optim, scaler, loss_fn = build(src, preset, opts)
        gen, seen = torch.Generator().manual_seed(0), []

        @contextmanager
        def phase(name):
            seen.append(name)
            yield

        losses[cl] = [train_step(model, optim, scaler, loss_fn, src, preset, gen, opts, i, phase)[0] for i in range(3)]
        assert seen == list(PHASES) * 3
        assert model.enc[0].conv1.weight.is_contiguous(memory_format=torch.channels_last) == cl
    assert losses[True] == pytest.approx(losses[False], rel=1e-4)


def test_training_reduces_loss(twill, tmp_path):
    res = train([load_source(twill)], preset_with("quick", iterations=40, batch=4, crop=32), tmp_path / "m.dsp",
                _opts(seed=1))
    first = sum(h["loss"] for h in res.history[:5]) / 5
    last = sum(h["loss"] for h in res.history[-5:]) / 5
    assert last < 0.8 * first


def test_model_file_roundtrip_and_versions(tmp_path, tiny_model):
    m, doc = load_model(tiny_model)
    assert doc["version"] == 2 and len(doc["input_reference"]) == 3
    x = torch.rand(1, 3, 32, 32)
    save_model(tmp_path / "half.dsp", m, doc["input_reference"], {}, half=True)
    h, _ = load_model(tmp_path / "half.dsp")
    with torch.no_grad():
        assert float((m(x) - h(x)).abs().max()) < 1e-2
    doc["version"] = 1
    torch.save(doc, tmp_path / "old.dsp")
    with pytest.raises(ValueError, match="version 1 is incompatible"):
        read_model_file(tmp_path / "old.dsp")
    (tmp_path / "junk.dsp").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="not a dualscale propagation model"):
        load_model(tmp_path / "junk.dsp")


def test_warm_start_copies_matching(tiny_model):
    src, _ = load_model(tiny_model)
    dst = PropagationUNet(UNetConfig(("albedo", "roughness", "opacity"), 8))
    copied = warm_start(dst, tiny_model)
    assert any(k.startswith("enc.") for k in copied) and any(k.startswith("decoders.albedo") for k in copied)
    assert not any(k.startswith("decoders.opacity") for k in copied)
    assert torch.equal(dst.enc[0].conv1.weight, src.enc[0].conv1.weight)
    with pytest.raises(ValueError, match="width"):
        warm_start(PropagationUNet(UNetConfig(("albedo",), 16)), tiny_model)


def test_sources_must_agree(twill, tmp_path):
    from dualscale.propagate.data import check_sources

    a = load_source(twill)
    b = load_source(twill)
    b.maps.pop("ior")
    with pytest.raises(ValueError, match="different maps"):
        check_sources([a, b])
    x, _ = sample_batch([a, a], 2, 16, torch.Generator())
    assert x.shape[0] == 2


def test_style_and_diffuse_options_enter_the_run(twill, tmp_path):
    """style_weight=0 drops the style term from the loss; a checkpoint of a run with other loss
    options is not resumed by a run with the defaults."""
    src = [load_source(twill)]
    pre = preset_with("quick", iterations=2, batch=2, crop=16)
    res = train(src, pre, tmp_path / "a.dsp", _opts(style_weight=0.0))
    assert "style" not in res.history[-1]
    res = train(src, pre, tmp_path / "b.dsp", _opts())
    assert "style" in res.history[-1]
    train(src, pre, tmp_path / "c.dsp", _opts(style_triplets=1))
    info = read_model_file(tmp_path / "c.dsp")["train"]
    assert info["style"] == [0.25, 1]
    with pytest.raises(ValueError, match="different run"):
        train(src, preset_with("quick", iterations=4, batch=2, crop=16), tmp_path / "c.dsp", _opts(resume=True))


def test_resolve_init_and_packaged_warm_start():
    """The packaged warm-start model is used where the preset warm-starts and the network is its
    width; an explicit --init wins, 'none' trains from random weights."""
    from dualscale.propagate.train import WARM_START, Preset, resolve_init

    assert WARM_START.is_file()
    warm, cold = Preset("w", 1, 1, warm_start=True), Preset("c", 1, 1)
    w16, w32 = UNetConfig(("albedo",), 16), UNetConfig(("albedo",), 32)
    assert resolve_init(warm, TrainOptions(), w16) == str(WARM_START)
    assert resolve_init(warm, TrainOptions(), w32) is None  # the packaged model is W = 16
    assert resolve_init(cold, TrainOptions(), w16) is None
    assert resolve_init(warm, TrainOptions(init="none"), w16) is None
    assert resolve_init(cold, TrainOptions(init="/x/m.dsp"), w16) == "/x/m.dsp"
    src, _ = load_model(WARM_START)
    assert (src.config.width, src.config.decoder_ratio) == (16, 0.5)


def test_bad_training_settings_are_refused_before_training(twill, tmp_path):
    """Iterations, batch, crop, lr and diffuse fraction out of range are a ValueError naming the
    field (exit 2 at the command line), before any file is written; an empty --init too."""
    for kw, what in (({"iterations": 0}, "iterations must be at least 1"), ({"batch": 0}, "batch must be at least 1"),
                     ({"crop": 33}, "crop must be a positive multiple of 16"), ({"lr": 0.0}, "lr must be positive"),
                     ({"diffuse_fraction": 1.5}, r"diffuse_fraction must be in \[0, 1\]")):
        with pytest.raises(ValueError, match=what):
            preset_with("quick", **kw)
    src = [load_source(twill)]
    pre = preset_with("quick", iterations=2, batch=2, crop=16)
    with pytest.raises(ValueError, match="checkpoint_every"):
        train(src, pre, tmp_path / "a.dsp", TrainOptions(width=8, progress=False, checkpoint_every=0))
    with pytest.raises(ValueError, match="init must name"):
        train(src, pre, tmp_path / "a.dsp", _opts(init=""))
    assert not list(tmp_path.iterdir())


def test_warm_start_is_in_the_run_and_skips_are_said(twill, tmp_path):
    """A warm-started checkpoint is not resumed from random weights (--init none is another run);
    a preset's warm start that does not fit the network, and a diffuse fraction with no diffuse
    light, are warned about and recorded as what was used."""
    from dualscale.propagate.train import WARM_START

    src = [load_source(twill)]
    pre = preset_with("quick", iterations=2, batch=2, crop=16)
    with pytest.warns(UserWarning) as rec:  # W = 8: the packaged W = 16 model does not fit; mod16: no diffuse light
        train(src, pre, tmp_path / "c.dsp", _opts())
    text = " ".join(str(w.message) for w in rec)
    assert "training from random weights" in text and "has no effect: no training source has a diffuse" in text
    info = read_model_file(tmp_path / "c.dsp")["train"]
    assert info["init"] is None and info["diffuse_fraction"] == 0.0
    opts16 = TrainOptions(width=16, progress=False, checkpoint_every=1)
    train(src, replace(pre, iterations=1), tmp_path / "w.dsp", opts16)
    assert read_model_file(tmp_path / "w.dsp")["train"]["init"] == str(WARM_START)
    with pytest.raises(ValueError, match="different run"):
        train(src, pre, tmp_path / "w.dsp", replace(opts16, resume=True, init="none"))
