"""Fly-out resolvability (issue 24 Sec. 4): whether the texel resolves the fibres, and the
precision measured on the simulated rig for that regime (``dualscale.fit.flyouts.SIMULATED``,
from ``bench/bench_flyouts.py --resolution``), in ``flyouts.json`` and in the flyouts stage's
record with a warning when under-resolved."""

from __future__ import annotations

import inspect
import json

import numpy as np
import pytest
import torch

from dualscale.fit import flyouts as fo


def test_criterion_and_nearest_regime():
    demo = fo.resolvability(0.0072)  # make demo: 7.2 um texels
    assert demo["texels_across"] == pytest.approx(12 / 7.2) and not demo["resolved"]
    assert demo["simulated_precision"]["texels_across"] == 1.67
    assert demo["simulated_precision"]["source"].startswith("bench/bench_flyouts.py --resolution")
    w = demo["warning"]
    assert "under-resolves" in w and "1.7 texels across" in w and "73%" in w and "2.4 um per texel" in w
    paper = fo.resolvability(0.0018)  # the paper's pitch
    assert paper["resolved"] and paper["warning"] is None and paper["simulated_precision"]["median"] >= 0.9
    assert fo.resolvability(0.0024)["resolved"] and not fo.resolvability(0.0025)["resolved"]
    with pytest.raises(ValueError):
        fo.resolvability(0.0)


def test_the_table_is_monotone_where_it_decides_and_the_fibre_is_the_simulators():
    """Above the criterion every regime's median precision beats every regime's below it, and
    the assumed diameter is the simulator's fibre (``add_flyouts``' default radius x 2)."""
    from dualscale.sim.materials.fabrics import add_flyouts

    radius = inspect.signature(add_flyouts).parameters["radius_mm"].default
    assert fo.FIBRE_DIAMETER_MM == pytest.approx(2 * radius)
    above = [r[1] for r in fo.SIMULATED if r[0] >= fo.RESOLVED_TEXELS]
    below = [r[1] for r in fo.SIMULATED if r[0] < fo.RESOLVED_TEXELS]
    assert above and below and min(above) > max(below)
    assert all(r[2] <= r[1] <= r[3] for r in fo.SIMULATED)


@pytest.mark.parametrize("material", ["twill", "plain", "denim"])
def test_the_simulated_precision_is_reproduced(material):
    """The coarsest regime of the table (9.6 um, 1.25 texels across), seed 0, rerun as the bench
    runs it: the precision lies within the row's recorded range, far below the resolved rows'."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
    from bench_flyouts import run_resolution

    torch.set_num_threads(1)
    row = run_resolution([material], [0], 0.6912, [9.6])[0]
    ratio, median, lo, hi, *_ = next(r for r in fo.SIMULATED if r[0] == 1.25)
    assert row["texels_across"] == pytest.approx(ratio, abs=0.01)
    assert row["precision"] is not None and lo - 0.005 <= row["precision"] <= hi + 0.005, row  # 2 decimals
    assert row["precision"] < min(r[2] for r in fo.SIMULATED if r[0] >= fo.RESOLVED_TEXELS)


@pytest.fixture(scope="module")
def coarse_sample(tmp_path_factory):
    """A tiny twill at 9 um (12 um fibres 1.3 texels across), every 4th LED, P0/P90."""
    from dualscale.cli import main

    root = tmp_path_factory.mktemp("flyres") / "sample"
    assert main(["synth", "twill", "-o", str(root), "--size", "48", "--texel-um", "9", "--dataset", "--lights",
                 "mod4", "--no-previews", "--no-progress"]) == 0
    return root


def test_flyouts_json_and_the_stage_record_say_under_resolved(coarse_sample, tmp_path):
    from dualscale.pipeline import Digitizer, DigitizeOptions

    import shutil

    from dualscale.pipeline import input_dataset

    d = Digitizer(DigitizeOptions(input=coarse_sample, run=tmp_path / "RUN", threads=1, progress=False))
    shutil.copytree(input_dataset(coarse_sample), d.dataset)  # what the calibrate stage hands on
    work = tmp_path / "work"
    work.mkdir()
    summary = d._flyouts(work)
    res = summary["resolvability"]
    assert res["resolved"] is False and res["texels_across"] == pytest.approx(12 / 9)
    assert res["simulated_precision"]["texels_across"] == 1.25
    assert summary["warnings"][0] == res["warning"] and "under-resolves" in res["warning"]
    doc = json.loads((work / "flyouts.json").read_text())
    assert doc["resolvability"] == json.loads(json.dumps(res))
    assert np.isfinite(doc["resolvability"]["simulated_precision"]["median"])
