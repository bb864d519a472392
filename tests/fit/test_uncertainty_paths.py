"""Every fit path writes the maps' per-pixel uncertainty (issue 26), default on: the tiled fit
on Dask (stitched from its tiles, resumable) and the fit out of core (written by rows) give the
one-process fit's; ``uncertainty=False`` (``--no-uncertainty``) leaves no uncertainty folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from dualscale.fit import api, stream
from dualscale.fit.core import fit_observations
from dualscale.fit.observations import fit_layout, load_observations
from dualscale.fit.params import fit_components
from dualscale.fit.presets import get_preset
from dualscale.formats.maps import UNCERTAINTY_DIR, load_uncertainty, maps_sha256

P = get_preset("standard").scaled(0.2)
COMPS = fit_components(opaque=True, isotropic=False, tinted=False)


def _same_uncertainty(a, b) -> None:
    """The same sigma bit for bit (NaN where undetermined) and mask, map by map: pixels are
    independent, and the fused kernel's Jacobian rounds a pixel alike in any region (fit.tiled)."""
    assert list(a.sigma) == list(b.sigma) and list(a.undetermined) == list(b.undetermined)
    for n in a.sigma:
        assert torch.equal(a.undetermined[n], b.undetermined[n]), n
        assert torch.equal(a.sigma[n].nan_to_num(-1.0), b.sigma[n].nan_to_num(-1.0)), \
            (n, (a.sigma[n] - b.sigma[n]).abs().nan_to_num(0.0).max().item())


def test_the_tiled_fit_stitches_the_one_process_uncertainty_and_resumes_it(datasets, tmp_path):
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    from dualscale.engine import EngineSpec, connect
    from dualscale.fit.tiled import fit_tiled

    obs = load_observations(datasets("twill")).crop(0, 10, 0, 10)
    one = fit_observations(obs, P, COMPS, uncertainty=True)
    state = tmp_path / "tiles"
    with connect(EngineSpec(workers=2)) as client:
        off, _ = fit_tiled(obs, P, COMPS, client, tile=5, state=state)  # saved without uncertainty
        assert off.uncertainty is None and len(list(state.glob("*.pt"))) == 4

        def stop_after_two(done, total, what):
            if done == 2:
                raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):  # the tiles saved without it are fitted again
            fit_tiled(obs, P, COMPS, client, tile=5, state=state, progress=stop_after_two, uncertainty=True)
        res, info = fit_tiled(obs, P, COMPS, client, tile=5, state=state, uncertainty=True)
    assert info["resumed_tiles"] == 2 and info["tiles"] == 4  # the two with uncertainty, from the state
    for (k, v), (_, w) in zip(one.maps.items(), res.maps.items()):
        assert torch.equal(v, w), k
    _same_uncertainty(one.uncertainty, res.uncertainty)
    assert res.uncertainty.noise == one.uncertainty.noise and res.uncertainty.seconds > 0


@pytest.fixture
def small_parts(monkeypatch):
    monkeypatch.setattr(stream, "MIN_PART_PIXELS", 1)


def _budget(root: Path, pixels: int) -> int:
    return stream.RESERVE + pixels * fit_layout(root)[3] * stream.BYTES_PER_SAMPLE


def test_the_fit_out_of_core_writes_the_whole_map_uncertainty_by_rows(datasets, tmp_path, small_parts):
    root = datasets("twill", 12) / "micro"
    kw = dict(cv_pixels=0, previews=False, comps=COMPS)
    whole, _ = api.fit_dataset(root, tmp_path / "whole", P, memory=None, **kw)  # default: on
    assert whole.uncertainty is not None
    res, ex = api.fit_dataset(root, tmp_path / "bands", P, memory=_budget(root, 40), **kw)
    assert res.maps is None and ex["out_of_core"]["parts"] == 4  # 12 rows in bands of 3
    sa, ua, da = load_uncertainty(tmp_path / "whole")
    sb, ub, db = load_uncertainty(tmp_path / "bands")
    # each names the maps beside it (their EXR bytes, whose headers carry each path's own record)
    ids = [d["meta"].pop("maps_sha256") for d in (da, db)]
    assert ids == [maps_sha256(tmp_path / "whole"), maps_sha256(tmp_path / "bands")]
    assert da == db and list(sa) == list(sb)
    for n in sa:  # the same half floats
        assert np.array_equal(ua[n], ub[n]) and np.array_equal(sa[n], sb[n], equal_nan=True), n
    a = json.loads((tmp_path / "whole" / "fit.json").read_text())["uncertainty"]
    b = json.loads((tmp_path / "bands" / "fit.json").read_text())["uncertainty"]
    assert a["noise"] == b["noise"] and a["files"] == b["files"]
    assert a["maps"] == b["maps"]  # the summary of the same float32 sigma (spilled by rows), not of the half floats
    assert not list((tmp_path / "bands").glob(".tmp-*"))
    # without it, nothing is left of an earlier fit's uncertainty, on either path
    for name, memory in (("bands", _budget(root, 40)), ("whole", None)):
        api.fit_dataset(root, tmp_path / name, P, memory=memory, uncertainty=False, **kw)
        assert not (tmp_path / name / UNCERTAINTY_DIR).exists(), name
        assert "uncertainty" not in json.loads((tmp_path / name / "fit.json").read_text())


def test_the_cli_fit_writes_it_unless_told_not_to(datasets, tmp_path, capsys):
    from dualscale.cli import main

    ds = datasets("twill", 8) / "micro"
    common = ["--preset", "draft", "--anisotropy", "off", "--tint", "off", "--transmittance", "off",
              "--cv-pixels", "0", "--no-previews", "--no-progress", "--threads", "1"]
    assert main(["fit", str(ds), "-o", str(tmp_path / "on"), *common]) == 0
    assert (tmp_path / "on" / UNCERTAINTY_DIR / "uncertainty.json").is_file()
    rec = json.loads((tmp_path / "on" / "fit.json").read_text())["uncertainty"]
    said = capsys.readouterr().out  # the fit says what it wrote and what it means
    med = max(rec["maps"]["normal"]["median"])
    assert "median 1-sigma" in said and f"normal {med:.2g}°" in said and "not the calibration" in said
    assert main(["fit", str(ds), "-o", str(tmp_path / "on"), *common, "--no-uncertainty"]) == 0
    assert not (tmp_path / "on" / UNCERTAINTY_DIR).exists()
    said = capsys.readouterr().out
    assert "median 1-sigma" not in said and "the earlier fit's" in said and "was removed" in said


def test_a_ground_truth_of_another_size_is_refused_before_the_fit(datasets, tmp_path, capsys):
    """``fit --gt`` with maps of another size: exit 2 naming both sizes before any work (it was
    found only after the whole fit), the output folder untouched."""
    from dualscale.cli import main

    ds = datasets("twill", 8) / "micro"
    other = datasets("twill", 16) / "maps"
    out = tmp_path / "fit"
    assert main(["fit", str(ds), "-o", str(out), "--preset", "draft", "--gt", str(other), "--cv-pixels", "0",
                 "--no-progress", "--threads", "1"]) == 2
    err = capsys.readouterr().err
    assert "16 x 16" in err and "8 x 8" in err
    assert not (out / "fit.json").exists() and not (out / "material.json").exists()
