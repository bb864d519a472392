"""The fit out of core (issue 25 Sec. 1, ``dualscale.fit.stream``): a dataset over the memory
budget is read band by band and its maps written by rows, with the whole-map fit's maps bit for
bit, the same component decision and cross-validation, and losses within float64 summation;
the driver never reads an image whole; interrupted fits resume; bad budgets are refused."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from dualscale.errors import FormatError, InputError
from dualscale.fit import api, stream
from dualscale.fit.observations import fit_layout
from dualscale.fit.presets import get_preset
from dualscale.fit.stream import BYTES_PER_SAMPLE, RESERVE, band_boxes, parse_memory
from dualscale.formats.maps import load_maps


@pytest.fixture(autouse=True)
def small_parts(monkeypatch):
    """Parts of a few pixels, so that these tiny maps cut into several (the product's least is a
    64^2 tile: ``stream.MIN_PART_PIXELS``)."""
    monkeypatch.setattr(stream, "MIN_PART_PIXELS", 1)


def budget(root: Path, pixels: int) -> int:
    """A memory budget whose bands hold ``pixels`` pixels of the dataset ``root``."""
    images = fit_layout(root)[3]
    return RESERVE + pixels * images * BYTES_PER_SAMPLE


def _equal_maps(a: Path, b: Path) -> None:
    ma, _ = load_maps(a)
    mb, _ = load_maps(b)
    for (k, v), (k2, w) in zip(ma.items(), mb.items(), strict=True):
        assert k == k2
        assert torch.equal(v, w), f"{k}: max |diff| {(v - w).abs().max().item()}"


def _close_losses(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k] == pytest.approx(b[k], rel=1e-6, abs=1e-12), k


@pytest.fixture(scope="module")
def masked(datasets, tmp_path_factory):
    """A translucent sheer with a back-lit image, a sample mask and clipped samples (a saturation
    level below its brightest values): every whole-map statistic the survey gathers is in play."""
    import OpenImageIO as oiio

    src = datasets("sheer", 20) / "micro"
    root = tmp_path_factory.mktemp("masked") / "micro"
    shutil.copytree(src, root)
    man = json.loads((root / "manifest.json").read_text())
    rng = np.random.default_rng(3)
    mask = (rng.random((20, 20)) > 0.15).astype(np.float32)
    mask[:3] = 0  # whole rows out of the sample: a band without any sample pixel
    out = oiio.ImageOutput.create(str(root / "mask.exr"))
    out.open(str(root / "mask.exr"), oiio.ImageSpec(20, 20, 1, "float"))
    out.write_image(mask)
    out.close()
    man["mask"] = "mask.exr"
    for rec in man["images"]:
        rec["saturation"] = 0.35
    (root / "manifest.json").write_text(json.dumps(man))
    return root


def test_memory_budgets_parse_and_bad_ones_are_refused():
    from dualscale.cli.fit import DEFAULT_MEMORY as CLI_DEFAULT

    assert parse_memory(CLI_DEFAULT) == stream.DEFAULT_MEMORY == 2 * 1024 ** 3
    assert parse_memory("800M") == 800 * 1024 ** 2
    assert parse_memory("1.5GiB") == int(1.5 * 1024 ** 3)
    assert parse_memory("64k") == 65536 and parse_memory("123") == 123 and parse_memory(4096) == 4096
    assert parse_memory("unlimited") is None and parse_memory(None) is None
    for bad in ("lots", "2X", "-1G", "0", "G"):
        with pytest.raises(InputError, match="--memory"):
            parse_memory(bad)


def test_bands_cover_the_map_once_within_the_budget():
    for shape, images, pixels in (((300, 200), 10, 5000), ((1000, 512), 254, 70000), ((7, 5), 3, 6), ((9, 40), 2, 7),
                                  ((64, 64), 4, 10 ** 9)):
        boxes = band_boxes(shape, images, RESERVE + pixels * images * BYTES_PER_SAMPLE)
        cover = np.zeros(shape, int)
        for y0, y1, x0, x1 in boxes:
            assert (y1 - y0) * (x1 - x0) <= pixels
            cover[y0:y1, x0:x1] += 1
        assert (cover == 1).all(), shape
    rows = band_boxes((1000, 512), 254, RESERVE + 70000 * 254 * BYTES_PER_SAMPLE)
    assert {b[1] - b[0] for b in rows[:-1]} == {128}  # 136 rows fit: rounded down to the EXR chunks' 64
    assert band_boxes((9, 40), 2, RESERVE + 7 * 2 * BYTES_PER_SAMPLE)[0] == (0, 1, 0, 7)  # a row split in columns
    assert band_boxes((50, 50), 9, None) == [(0, 50, 0, 50)]
    with pytest.raises(InputError, match="below what a fit of 254 images needs"):
        band_boxes((512, 512), 254, RESERVE)


def test_the_least_budget_holds_a_64px_tile(monkeypatch):
    monkeypatch.setattr(stream, "MIN_PART_PIXELS", 4096)
    least = stream.minimum_memory(254)
    assert least == RESERVE + 4096 * 254 * BYTES_PER_SAMPLE
    assert len(band_boxes((4096, 4096), 254, least)) == 4096 * 4096 // 4096  # one-row runs of 4096 columns
    with pytest.raises(InputError, match=r"--memory 511 MiB is below what a fit of 254 images needs: 611 MiB"):
        band_boxes((64, 64), 254, least - 100 * 2 ** 20)
    with pytest.raises(InputError, match=r"--memory 500.0 KiB"):
        stream.check_memory(500 * 1024, 254)


@pytest.mark.parametrize("preset", ["standard", "adam-fast"])
def test_out_of_core_equals_the_whole_map_fit(masked, tmp_path, preset, monkeypatch):
    p = get_preset(preset).scaled(0.25)
    kw = dict(cv_pixels=60, cv_folds=4, previews=True, seed=2)
    whole, wx = api.fit_dataset(masked, tmp_path / "whole", p, memory=None, **kw)
    assert "out_of_core" not in wx

    from dualscale.formats.dataset import Dataset

    load = Dataset.load

    def only_regions(self, index, box=None):  # the fit out of core never reads an image whole
        assert box is not None, "an image was read whole"
        return load(self, index, box)

    monkeypatch.setattr(Dataset, "load", only_regions)
    res, ex = api.fit_dataset(masked, tmp_path / "bands", p, memory=budget(masked, 60), **kw)
    assert res.maps is None
    rec = ex["out_of_core"]
    assert rec["parts"] == 7 and rec["part_rows"] == 3 and rec["resumed_parts"] == 0  # 20 rows in bands of 3
    _equal_maps(tmp_path / "whole", tmp_path / "bands")
    _close_losses(whole.losses, res.losses)
    a = json.loads((tmp_path / "whole" / "fit.json").read_text())
    b = json.loads((tmp_path / "bands" / "fit.json").read_text())
    ta, tb = (x["selection"]["transmittance"]["evidence"].pop("backlit_mean") for x in (a, b))
    assert ta == pytest.approx(tb, rel=1e-12)  # float64 sums, over bands or over the whole map
    assert a["selection"] == b["selection"]  # the same decision, from the same sample pixels
    for k in ("ours", "baseline", "constant", "light_ids"):
        assert a["cross_validation"][k] == b["cross_validation"][k], k
    assert [h[:2] for h in a["loss_history"]] == [h[:2] for h in b["loss_history"]]
    for (_, _, x), (_, _, y) in zip(a["loss_history"], b["loss_history"], strict=True):
        assert x == pytest.approx(y, rel=1e-5)
    assert b["out_of_core"]["peak_rss_mib"] > 0 and b["memory"]["path"] == "out of core"
    assert (tmp_path / "bands" / "albedo.png").is_file() and not (tmp_path / "bands" / "tiles").exists()
    assert json.loads((tmp_path / "bands" / "material.json").read_text())["maps"] == \
        json.loads((tmp_path / "whole" / "material.json").read_text())["maps"]


def test_the_bright_albedo_check_counts_the_whole_map(masked):
    """The survey's statistics and the bands' albedo counts (the fit's own start) add up to the
    whole map's: the sample's pixels, the valid counts, the transmittance evidence, the share."""
    from dualscale.fit.init import check_albedo_range, photometric_stereo, start_params
    from dualscale.fit.observations import load_observations, read_tile
    from dualscale.fit.params import fit_components
    from dualscale.fit.stream import survey

    obs = load_observations(masked)
    share = check_albedo_range(obs, photometric_stereo(obs)[1])
    boxes = band_boxes(obs.shape, obs.n, budget(masked, 45))
    sv = survey(lambda b: read_tile(obs.origin, b), boxes, obs.shape)
    counts = [start_params(read_tile(obs.origin, b), fit_components(False, True, False))[1] for b in boxes]
    assert len(boxes) > 3 and sum(c[0] for c in counts) / sum(c[1] for c in counts) == share
    assert torch.equal(sv.fitted, obs.fitted_pixels)
    assert sv.counts.tolist() == obs.valid.sum(dim=(1, 2)).double().tolist()
    from dualscale.fit.select import transmission_evidence

    ev = transmission_evidence(obs)
    assert sv.transmission["transmits"] == ev["transmits"]
    for k in ("backlit_mean", "backlit_p99", "fraction_above_level"):
        assert sv.transmission[k] == pytest.approx(ev[k], rel=1e-6), k


def test_a_bright_map_is_warned_about_once_after_its_bands(datasets, tmp_path, monkeypatch):
    """Photographs brighter than relative radiance: the out-of-core fit warns once, with the
    whole map's share (the bands' own warnings are not raised)."""
    import warnings

    from dualscale.fit import init

    monkeypatch.setattr(init, "BRIGHT_SHARE", -1.0)  # any share warns
    root = datasets("twill", 16) / "micro"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        api.fit_dataset(root, tmp_path / "m", get_preset("draft").scaled(0.2), cv_pixels=0, previews=False,
                        memory=budget(root, 64), comps=replace(stream_comps(), opaque=True))
    bright = [w for w in caught if "Lambertian albedo" in str(w.message)]
    assert len(bright) == 1, [str(w.message) for w in caught]


def stream_comps():
    from dualscale.fit.params import fit_components

    return fit_components(True, True, False)


def test_an_interrupted_fit_resumes_from_its_finished_bands(datasets, tmp_path, monkeypatch):
    root = datasets("twill", 16) / "micro"
    p = get_preset("standard").scaled(0.2)
    kw = dict(cv_pixels=0, previews=False, memory=budget(root, 64))  # 4 bands of 4 rows
    calls = []
    real = stream.fit_observations

    def stop_at_the_third(*a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(stream, "fit_observations", stop_at_the_third)
    with pytest.raises(KeyboardInterrupt):
        api.fit_dataset(root, tmp_path / "m", p, **kw)
    assert len(list((tmp_path / "m" / "tiles").glob("*.pt"))) == 2 and not (tmp_path / "m" / "fit.json").exists()
    monkeypatch.setattr(stream, "fit_observations", real)
    with pytest.raises(FormatError, match="a part of a different fit"):  # another preset: the saved bands are foreign
        api.fit_dataset(root, tmp_path / "m", replace(p, shadow_ratio=0.3), **kw)
    _, ex = api.fit_dataset(root, tmp_path / "m", p, **kw)
    assert ex["out_of_core"]["resumed_parts"] == 2 and ex["out_of_core"]["parts"] == 4
    api.fit_dataset(root, tmp_path / "whole", p, cv_pixels=0, previews=False, memory=None)
    _equal_maps(tmp_path / "whole", tmp_path / "m")


def test_what_the_fit_out_of_core_cannot_run_is_refused_before_any_work(datasets, tmp_path, capsys):
    from dualscale.cli import main

    root = datasets("twill", 16) / "micro"
    with pytest.raises(InputError, match="bands of 2 rows at least"):  # a coarse level needs whole 2 x 2 blocks
        api.fit_dataset(root, tmp_path / "c", "coarse-to-fine", memory=budget(root, 12))
    assert not (tmp_path / "c").exists()
    assert main(["fit", str(root), "-o", str(tmp_path / "d"), "--memory", "lots"]) == 2
    assert "--memory 'lots'" in capsys.readouterr().err
    assert main(["fit", str(root), "-o", str(tmp_path / "e"), "--memory", "100M"]) == 2
    assert "below what a fit of 254 images needs" in capsys.readouterr().err
    assert main(["fit", str(root), "-o", str(tmp_path / "f"), "--memory", "0.5"]) == 2
    assert "at least one byte (a plain number is bytes" in capsys.readouterr().err
    assert not any((tmp_path / n).exists() for n in "cdef")


def test_the_cli_says_it_fitted_out_of_core(datasets, tmp_path, capsys):
    from dualscale.cli import main

    root = datasets("twill", 16) / "micro"
    mem = str(budget(root, 128))
    args = ["--preset", "draft", "--anisotropy", "on", "--tint", "off", "--no-previews", "--no-progress",
            "--threads", "1", "--cv-pixels", "0"]
    assert main(["fit", str(root), "-o", str(tmp_path / "a"), *args, "--memory", mem]) == 0
    out = capsys.readouterr().out
    assert "memory: out of core (estimated" in out and ": 2 bands of 8 rows x 16 columns; peak " in out, out
    assert main(["fit", str(root), "-o", str(tmp_path / "b"), *args, "--memory", "unlimited"]) == 0
    out = capsys.readouterr().out
    assert "memory: in memory (estimated" in out and "within no budget" in out, out
    rec = json.loads((tmp_path / "b" / "fit.json").read_text())["memory"]
    assert rec["path"] == "in memory" and rec["memory_bytes"] is None and rec["estimate_bytes"] > RESERVE
    _equal_maps(tmp_path / "a", tmp_path / "b")


def test_on_a_cluster_the_driver_reads_bands_and_ships_no_pixels(masked, tmp_path, monkeypatch):
    """Issue 25 Sec. 1 and 2 together: with ``engine`` and a dataset, the driver reads no pixel
    (the workers run the survey, the gather and the tiles, each reading its part), every task
    carries coordinates (a few kB), and the maps are the whole-map fit's bit for bit."""
    pytest.importorskip("distributed", reason="the dask extra is not installed (pip install 'dualscale[dask]')")
    import contextlib

    import cloudpickle

    from dualscale.engine import EngineSpec, connect

    p = get_preset("standard").scaled(0.25)
    kw = dict(cv_pixels=0, previews=False, seed=2)
    api.fit_dataset(masked, tmp_path / "whole", p, memory=None, **kw)
    sent = []

    @contextlib.contextmanager
    def counting(spec):
        with connect(spec) as client:
            real = client.submit

            def submit(fn, *args, **k):
                sent.append(len(cloudpickle.dumps((fn, args))))
                return real(fn, *args, **k)

            client.submit = submit
            yield client

    monkeypatch.setattr(api, "connect", counting)
    from dualscale.formats.dataset import Dataset

    load = Dataset.load
    driver = []

    def only_regions(self, index, box=None):  # (this process only: the workers are other processes)
        driver.append(box)
        assert box is not None, "the driver read an image whole"
        return load(self, index, box)

    monkeypatch.setattr(Dataset, "load", only_regions)
    res, ex = api.fit_dataset(masked, tmp_path / "tiles", p, engine=EngineSpec(workers=2), tile_px=8,
                              memory=budget(masked, 100), **kw)
    assert ex["tiled"]["tiles"] == 9 and ex["tiled"]["tile_data"].startswith("read by the workers")
    assert ex["out_of_core"]["parts"] == 9 and driver == []  # the survey and the gather ran on the workers too
    tile_images = 8 * 8 * fit_layout(masked)[3] * 3 * 4
    assert len(sent) == 9 + 4 + 4 and max(sent) < min(tile_images / 4, 20_000), sent  # tiles; survey, gather bands
    _equal_maps(tmp_path / "whole", tmp_path / "tiles")


def test_the_flyouts_confidence_map_by_bands_is_the_whole_maps(datasets):
    """digitize's flyouts stage over the budget reads the two light rings it needs band by band."""
    from dualscale.fit.flyouts import confidence_by_bands, confidence_map
    from dualscale.fit.observations import load_observations

    obs = load_observations(datasets("twill", 16) / "micro")
    boxes = band_boxes(obs.shape, obs.n, RESERVE + 40 * obs.n * BYTES_PER_SAMPLE)
    assert len(boxes) > 4
    assert np.array_equal(confidence_by_bands(obs.origin, boxes, obs.shape), confidence_map(obs))


@pytest.mark.slow  # 10 s; the tiled fit's own killed-worker test (test_tiled.py) stays in make test
def test_out_of_core_on_a_cluster_survives_a_worker_killed_mid_tile(datasets, tmp_path, monkeypatch):
    """SIGKILL the worker fitting a tile of an out-of-core fit: the task carries coordinates, so
    the scheduler reruns it on another worker, and the maps are still the whole-map fit's."""
    pytest.importorskip("distributed", reason="the dask extra is not installed (pip install 'dualscale[dask]')")
    import contextlib

    from dask_kill import run_killing_a_busy_worker
    from dualscale.engine import EngineSpec, connect

    root = datasets("twill", 16) / "micro"
    p = get_preset("standard").scaled(0.3)
    kw = dict(cv_pixels=0, previews=False)
    api.fit_dataset(root, tmp_path / "whole", p, memory=None, **kw)
    with connect(EngineSpec(workers=2)) as c:
        monkeypatch.setattr(api, "connect", lambda spec: contextlib.nullcontext(c))
        out = run_killing_a_busy_worker(c, lambda: api.fit_dataset(root, tmp_path / "tiles", p,
                                                                   engine=EngineSpec(workers=2), tile_px=6, **kw),
                                        "fit-part")
        assert out["killed"] is not None, "no worker was seen fitting a tile"
        assert "error" not in out, out.get("error")
    _equal_maps(tmp_path / "whole", tmp_path / "tiles")


def test_coarse_to_fine_out_of_core_equals_the_whole_map_fit_and_resumes(masked, tmp_path, monkeypatch):
    """The coarse level band by band (``fit.stream_coarse``): bands of a multiple of 2 rows, each
    downsampled and fitted, each fine band started from its rows' coarse maps and a one-cell
    halo: the whole-map coarse-to-fine maps bit for bit; the coarse maps are saved and reused by
    a rerun."""
    from dualscale.fit import stream_coarse

    p = get_preset("coarse-to-fine").scaled(0.34)
    kw = dict(cv_pixels=0, previews=False, seed=1)
    api.fit_dataset(masked, tmp_path / "whole", p, memory=None, **kw)
    mem = budget(masked, 70)  # 3 rows, rounded down to 2: ten bands of 2 rows
    assert [b[1] - b[0] for b in band_boxes((20, 20), fit_layout(masked)[3], mem, 2)] == [2] * 10
    calls = []
    real = stream.fit_observations

    def stop_at_the_fourth_band(*a, **k):
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(stream, "fit_observations", stop_at_the_fourth_band)
    with pytest.raises(KeyboardInterrupt):
        api.fit_dataset(masked, tmp_path / "bands", p, memory=mem, **kw)
    state = tmp_path / "bands" / "tiles"
    assert len(list(state.glob("coarse_*.pt"))) == 10 and len(list(state.glob("0*.pt"))) == 3
    monkeypatch.setattr(stream, "fit_observations", real)
    coarse_fits = []
    real_coarse = stream_coarse.coarse_part
    monkeypatch.setattr(stream_coarse, "coarse_part", lambda *a, **k: coarse_fits.append(1) or real_coarse(*a, **k))
    res, ex = api.fit_dataset(masked, tmp_path / "bands", p, memory=mem, **kw)
    assert coarse_fits == [] and ex["out_of_core"]["resumed_parts"] == 3 and ex["out_of_core"]["parts"] == 10
    _equal_maps(tmp_path / "whole", tmp_path / "bands")
    assert not state.exists()
    with pytest.raises(InputError, match="bands of 2 rows at least"):  # one row: no whole block
        api.fit_dataset(masked, tmp_path / "c", p, memory=budget(masked, 25), **kw)
    assert not (tmp_path / "c").exists()


def test_gt_out_of_core_scores_by_rows_with_the_in_memory_numbers(datasets, masked, tmp_path, monkeypatch):
    """``--gt`` out of core (``fit.score``): both maps read by bands of rows, never whole, the
    terms spilled to memory-mapped files: the in-memory scoring's numbers, exactly (means and
    the normal angle's 95th percentile), on a translucent ground truth (every term)."""
    import dualscale.formats.maps as maps_mod
    from dualscale.fit import score
    from dualscale.fit.metrics import map_errors

    gt = datasets("sheer", 20) / "maps"
    p = get_preset("standard").scaled(0.2)
    kw = dict(cv_pixels=0, previews=False, gt=gt)
    _, wx = api.fit_dataset(masked, tmp_path / "whole", p, memory=None, **kw)
    load = maps_mod.load_maps

    def by_rows(root, dtype=torch.float32, box=None):
        assert box is not None and box[1] - box[0] in (2, 3), "maps read whole"
        return load(root, dtype, box)

    monkeypatch.setattr(score, "BAND_PIXELS", 60)  # bands of 3 rows of 20 (the last one 2)
    monkeypatch.setattr(maps_mod, "load_maps", by_rows)
    _, ex = api.fit_dataset(masked, tmp_path / "bands", p, memory=budget(masked, 60), **kw)
    monkeypatch.setattr(maps_mod, "load_maps", load)
    got = ex["ground_truth"]["errors"]
    assert set(got) >= {"transmittance_rmse", "albedo_opacity_rmse", "normal_p95_deg"}
    assert got == wx["ground_truth"]["errors"]  # the same maps (bit for bit), the same numbers
    ior = json.loads((tmp_path / "bands" / "fit.json").read_text())["selection"]["components"]["ior"]
    assert got == map_errors(load(tmp_path / "bands")[0], load(gt)[0], ior)
    assert json.loads((tmp_path / "bands" / "fit.json").read_text())["ground_truth"]["errors"] == got
    assert not list((tmp_path / "bands").glob("score-*"))


def test_coarse_to_fine_on_a_cluster_over_the_budget_runs_in_bands_read_by_the_workers(masked, tmp_path, monkeypatch):
    """With ``engine`` over the budget, the coarse level and the fine bands are tasks that read
    their bands themselves; the driver reads no pixel, sends each fine band its coarse rows only,
    and the maps are the in-memory coarse-to-fine fit's bit for bit."""
    pytest.importorskip("distributed", reason="the dask extra is not installed (pip install 'dualscale[dask]')")
    import contextlib

    import cloudpickle

    from dualscale.engine import EngineSpec, connect
    from dualscale.formats.dataset import Dataset

    p = get_preset("coarse-to-fine").scaled(0.34)
    kw = dict(cv_pixels=0, previews=False, seed=1)
    api.fit_dataset(masked, tmp_path / "whole", p, memory=None, **kw)
    sent = []

    @contextlib.contextmanager
    def counting(spec):
        with connect(spec) as client:
            real = client.submit

            def submit(fn, *args, **k):
                sent.append((fn.__name__, len(cloudpickle.dumps((fn, args)))))
                return real(fn, *args, **k)

            client.submit = submit
            yield client

    monkeypatch.setattr(api, "connect", counting)
    load = Dataset.load
    driver = []

    def only_regions(self, index, box=None):  # (this process only: the workers are other processes)
        driver.append(box)
        return load(self, index, box)

    monkeypatch.setattr(Dataset, "load", only_regions)
    res, ex = api.fit_dataset(masked, tmp_path / "bands", p, engine=EngineSpec(workers=2), memory=budget(masked, 90),
                              **kw)  # 4 rows: five bands
    assert driver == [] and ex["out_of_core"]["part_kind"] == "bands" and ex["out_of_core"]["parts"] == 5
    assert ex["tiled"]["tile_px"] is None and ex["tiled"]["part_kind"] == "bands"
    names = [n for n, _ in sent]
    assert names.count("coarse_task") == 5 and names.count("fine_task") == 5, names
    band_images = 4 * 20 * fit_layout(masked)[3] * 3 * 4
    assert max(size for _, size in sent) < band_images / 4, sent
    _equal_maps(tmp_path / "whole", tmp_path / "bands")
