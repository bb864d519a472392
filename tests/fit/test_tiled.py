"""The tiled fit on a local Dask cluster (issue 16): the same maps as one process, bit for bit;
a worker killed mid-tile is survived; finished tiles are resumed; bad options are refused."""

from __future__ import annotations

import json
import os
from dataclasses import replace

import pytest
import torch

pytest.importorskip("distributed", reason="the dask extra is not installed (pip install 'dualscale[dask]')")

from dualscale.engine import EngineSpec, connect  # noqa: E402
from dualscale.errors import FormatError, InputError, ToolError  # noqa: E402
from dualscale.fit.core import fit_observations  # noqa: E402
from dualscale.fit.observations import load_observations  # noqa: E402
from dualscale.fit.params import fit_components  # noqa: E402
from dualscale.fit.presets import get_preset  # noqa: E402
from dualscale.fit.tiled import fit_tiled, tiles  # noqa: E402

from dask_kill import run_killing_a_busy_worker  # noqa: E402



@pytest.fixture(scope="module")
def client():
    with connect(EngineSpec(workers=2)) as c:
        yield c


def synth(root, material, size, extra=()):
    from dualscale.cli import main

    assert main(["synth", material, "-o", str(root), "--size", str(size), "--texel-um", "9", "--dataset",
                 "--no-previews", "--no-progress", *extra]) == 0
    return root


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    base = tmp_path_factory.mktemp("tiled")
    out = {}
    out["twill"] = load_observations(synth(base / "twill", "twill", 24, extra=("--lights", "mod3")) / "micro")
    # translucent, with cast shadows and samples set aside (as clipping would): back-lit image and
    # valid masks
    sheer = load_observations(synth(base / "sheer", "sheer", 20, extra=("--lights", "mod3", "--shadows")) / "micro")
    assert sheer.backlight is not None
    g = torch.Generator().manual_seed(1)
    out["sheer"] = replace(sheer, valid=torch.rand(sheer.images.shape[:3], generator=g) > 0.1,
                           back_valid=torch.rand(sheer.shape, generator=g) > 0.1)
    return out


def _equal(a, b) -> None:
    for (k, v), (k2, w) in zip(a, b, strict=True):
        assert k == k2
        assert torch.equal(v, w), f"{k}: max |diff| {(v - w).abs().max().item()}"


def test_tiles_cover_the_map_once():
    boxes = tiles((10, 7), 4)
    cover = torch.zeros(10, 7, dtype=torch.int32)
    for y0, y1, x0, x1 in boxes:
        cover[y0:y1, x0:x1] += 1
    assert bool((cover == 1).all()) and len(boxes) == 6
    with pytest.raises(InputError, match="tile-px"):
        tiles((10, 7), 0)


SHORT = {"iterations": (15, 10, 15)}  # Adam presets, cut short: the same code, fewer iterations


@pytest.mark.parametrize("name,preset,comps,change", [
    ("twill", "standard", fit_components(True, False, False), {}),
    ("twill", "coarse-to-fine", fit_components(True, False, True), {}),
    ("sheer", "draft", fit_components(False, True, False), {}),
    ("twill", "adam-fast", fit_components(True, False, False), SHORT),  # light batches of 64
    ("sheer", "paper", fit_components(False, True, True), SHORT),  # whole-map mean over valid samples
])
def test_tiled_fit_equals_the_single_process_fit_bit_for_bit(client, data, name, preset, comps, change):
    obs = data[name]
    p = replace(get_preset(preset), **change)
    one = fit_observations(obs, p, comps)
    tiled, info = fit_tiled(obs, p, comps, client, tile=7)  # edge tiles cut short
    assert info["tiles"] == len(tiles(obs.shape, 7)) and info["workers"] == 2
    _equal(one.maps.items(), tiled.maps.items())
    assert tiled.losses == one.losses
    assert [h[:2] for h in tiled.history] == [h[:2] for h in one.history]
    assert [h[2] for h in tiled.history] == pytest.approx([h[2] for h in one.history], rel=1e-5)


def test_a_task_ships_its_tile_not_the_whole_map(data):
    """A crop is a view; pickled as is, it would carry the whole map's images to every task."""
    import pickle

    from dualscale.fit.tiled import _own

    obs = data["sheer"]
    whole = len(pickle.dumps(obs))
    tile = len(pickle.dumps(_own(obs.crop(0, 5, 0, 5))))
    assert tile < whole / 10, (tile, whole)


@pytest.mark.parametrize("kernel", ["eager", "compiled"])
def test_reference_kernels_are_refused(client, data, kernel):
    """Their tiles would differ from the one-process fit in the last bits (module doc of
    fit/tiled.py), amplified to ~1e-5 by the forward differences: refused, not approximated."""
    with pytest.raises(InputError, match=f"the {kernel} kernel"):
        fit_tiled(data["twill"], replace(get_preset("draft"), kernel=kernel), fit_components(True, True, False),
                  client)


def test_finished_tiles_are_resumed_and_foreign_ones_refused(client, data, tmp_path):
    obs, comps, p = data["twill"], fit_components(True, True, False), get_preset("draft")
    state = tmp_path / "tiles"
    seen = []

    def stop_after_two(done, total, what):
        seen.append(done)
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_tiled(obs, p, comps, client, tile=12, state=state, progress=stop_after_two)
    assert len(list(state.glob("*.pt"))) == 2
    res, info = fit_tiled(obs, p, comps, client, tile=12, state=state)
    assert info["resumed_tiles"] == 2 and info["tiles"] == 4
    _equal(fit_observations(obs, p, comps).maps.items(), res.maps.items())
    with pytest.raises(FormatError, match="different fit"):
        fit_tiled(obs, replace(p, shadow_ratio=0.3), comps, client, tile=12, state=state)


def test_a_worker_killed_mid_tile_is_survived(data, tmp_path):
    """SIGKILL the worker process that is fitting a tile: the scheduler reruns the tile on the
    other worker (or the nanny's restarted one), and the maps are still the single-process fit's."""
    obs, comps, p = data["twill"], fit_components(True, False, False), get_preset("standard")
    with connect(EngineSpec(workers=2)) as c:
        out = run_killing_a_busy_worker(c, lambda: fit_tiled(obs, p, comps, c, tile=12), "fit-tile")
        killed = out["killed"]
        assert killed is not None, "no worker was seen fitting a tile"
        assert "error" not in out, out.get("error")
        assert killed not in c.run(os.getpid).values()  # the killed process is gone (restarted by its nanny)
    res, info = out["res"]
    _equal(fit_observations(obs, p, comps).maps.items(), res.maps.items())


def test_fit_cli_with_workers_and_with_a_scheduler_address(client, datasets, tmp_path, capsys):
    from dualscale.cli import main
    from dualscale.formats.maps import load_maps

    ds = datasets("twill", 16) / "micro"
    common = ["--preset", "draft", "--anisotropy", "on", "--tint", "off", "--transmittance", "off",
              "--no-previews", "--no-progress", "--threads", "1"]
    assert main(["fit", str(ds), "-o", str(tmp_path / "one"), *common]) == 0
    assert main(["fit", str(ds), "-o", str(tmp_path / "two"), *common, "--workers", "2", "--tile-px", "8"]) == 0
    out = capsys.readouterr().out
    assert "(kernel fused, tiled on local (2 workers x 1 thread))" in out and "tiles: 4 of 8 px on 2 workers" in out
    addr = client.scheduler.address
    assert main(["fit", str(ds), "-o", str(tmp_path / "addr"), *common, "--scheduler", addr]) == 0
    one, _ = load_maps(tmp_path / "one")
    for run in ("two", "addr"):
        other, _ = load_maps(tmp_path / run)
        _equal(one.items(), other.items())
        rec = json.loads((tmp_path / run / "fit.json").read_text())
        assert rec["tiled"]["tiles"] >= 1 and not (tmp_path / run / "tiles").exists()
    assert json.loads((tmp_path / "addr" / "fit.json").read_text())["tiled"]["engine"] == f"scheduler {addr}"


def test_fit_cli_refuses_what_it_cannot_tile(datasets, tmp_path, capsys, monkeypatch):
    from dualscale.cli import main

    ds = datasets("twill", 16) / "micro"
    assert main(["fit", str(ds), "-o", str(tmp_path / "a"), "--workers", "2", "--kernel", "eager"]) == 2
    assert "the eager kernel" in capsys.readouterr().err
    assert main(["fit", str(ds), "-o", str(tmp_path / "b"), "--workers", "2", "--tile-px", "0"]) == 2
    assert main(["fit", str(ds), "-o", str(tmp_path / "c"), "--workers", "0"]) == 2
    import dualscale.engine as engine

    monkeypatch.setattr(engine, "available", lambda: False)
    assert main(["fit", str(ds), "-o", str(tmp_path / "d"), "--workers", "2"]) == ToolError.exit_code
    assert "pip install 'dualscale[dask]'" in capsys.readouterr().err
    assert not any((tmp_path / x).exists() for x in "abcd")


def test_the_tile_bar_is_full_when_every_tile_was_already_done(client, data, tmp_path, capsys):
    """A rerun whose tiles were all saved before (issue 24 §8): the bar shows N/N, not 0/N; the
    callable form sees every tile counted done."""
    obs, comps, p = data["twill"], fit_components(True, True, False), get_preset("draft")
    state = tmp_path / "tiles"
    fit_tiled(obs, p, comps, client, tile=12, state=state)
    assert len(list(state.glob("*.pt"))) == 4
    capsys.readouterr()
    seen = []
    _, info = fit_tiled(obs, p, comps, client, tile=12, state=state, progress=lambda d, t, w: seen.append((d, t)))
    assert info["resumed_tiles"] == 4 and seen and seen[-1] == (4, 4) and all(d > 0 for d, _ in seen)
    _, info = fit_tiled(obs, p, comps, client, tile=12, state=state, progress=True)
    err = capsys.readouterr().err
    assert info["resumed_tiles"] == 4 and "4/4" in err, err


class _Counting:
    """The real Dask client, measuring the pickled size of every task it is given (the
    function and its arguments: what the driver sends to the scheduler for the workers)."""

    def __init__(self, client):
        self.client, self.sent = client, []

    def submit(self, fn, *args, **kw):
        import cloudpickle

        self.sent.append(len(cloudpickle.dumps((fn, args))))
        return self.client.submit(fn, *args, **kw)

    def __getattr__(self, name):
        return getattr(self.client, name)


@pytest.mark.parametrize("preset,comps", [("standard", fit_components(True, False, False)),
                                          ("adam-fast", fit_components(True, False, False))])
def test_workers_read_their_tiles_and_the_driver_ships_no_pixels(client, data, preset, comps):
    """Issue 25 Sec. 2: observations as read from the dataset go to the workers as the dataset's
    path and the tile's coordinates; each worker reads its tile itself, and the maps are the
    one-process fit's bit for bit.  Observations changed after loading are sent with each task."""
    obs = data["twill"]
    assert obs.unchanged() and obs.origin is not None
    p = replace(get_preset(preset), **(SHORT if preset.startswith("adam") else {}))
    one = fit_observations(obs, p, comps)
    counting = _Counting(client)
    tiled, info = fit_tiled(obs, p, comps, counting, tile=7)
    assert info["tile_data"].startswith("read by the workers")
    _equal(one.maps.items(), tiled.maps.items())
    pixels = 7 * 7 * obs.n * 3 * 4  # one full tile's float32 images
    assert len(counting.sent) == info["tiles"] and max(counting.sent) < min(pixels / 4, 20_000), counting.sent
    # changed after loading (a replaced mask): the tasks carry the tiles' pixels
    changed = replace(obs, valid=torch.ones(obs.images.shape[:3], dtype=torch.bool))
    assert not changed.unchanged()
    counting = _Counting(client)
    _, info = fit_tiled(changed, p, comps, counting, tile=7)
    assert info["tile_data"].startswith("sent with each task") and max(counting.sent) > pixels


def test_a_tile_read_from_the_dataset_is_the_crop_of_the_whole(data):
    from dualscale.fit.observations import read_tile

    obs = data["twill"]
    part = read_tile(obs.origin, (3, 17, 5, 21))
    crop = obs.crop(3, 17, 5, 21)
    assert torch.equal(part.images, crop.images) and torch.equal(part.led_ids, crop.led_ids)
    assert (part.valid is None) == (crop.valid is None)
    with pytest.raises(ValueError, match="outside"):
        read_tile(obs.origin, (0, 99, 0, 5))
