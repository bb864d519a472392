"""The exchange EXR set carries the maps' 1-sigma uncertainty (issue 26): ``<input>_sigma.exr``
in the exchange units where the input is a linear function of our map, our units (so stated)
otherwise, the undetermined mask, the record in ``exchange.json``; a maps folder without an
uncertainty exports as before; a changed uncertainty redoes the exr set only."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dualscale.export.material import export_material, read_export
from dualscale.export.readback import read_exchange_exr
from dualscale.formats.exr import read_exr
from dualscale.formats.maps import SIGMA_CHANNELS, load_uncertainty, save_maps, save_uncertainty
from dualscale.sim.materials import generate

N = 16


def _folder(root: Path, kind: str, seed: int = 0, n: int = N) -> Path:
    mat = generate(kind, size=n, texel_mm=0.02, seed=1)
    save_maps(root, mat.maps, {"material": kind}, texel_mm=0.02)
    rng = np.random.default_rng(seed)
    names = [n for n, _ in mat.maps.items() if n in SIGMA_CHANNELS]
    sigma = {k: rng.uniform(0.001, 0.1 if k not in ("normal", "tangent") else 30.0, (n, n, SIGMA_CHANNELS[k]))
             for k in names}
    und = {k: rng.random(sigma[k].shape) < 0.15 for k in names}
    save_uncertainty(root, sigma, und, meta={"noise": "robust residual scale", "preset": "test"})
    return root


def _sigma(folder: Path, stem: str, chans) -> np.ndarray:
    return read_exr(folder / f"{stem}_sigma.exr", chans)


def test_the_exr_set_carries_sigma_in_the_exchange_units(tmp_path):
    maps = _folder(tmp_path / "twill" / "maps", "twill")
    export_material(maps, tmp_path / "out", ["exr"])
    exr = tmp_path / "out" / "exr"
    s, u, _ = load_uncertainty(maps)
    doc = json.loads((exr / "exchange.json").read_text())
    rec = doc["uncertainty"]
    assert rec["noise"] == "robust residual scale" and rec["left_out"] == {}
    assert set(rec["files"]) == {"base_color", "specular_roughness", "specular_anisotropy", "specular_rotation",
                                 "specular_IOR", "normal", "specular_color"}
    scale = {"base_color": ("albedo", 1.0), "specular_roughness": ("roughness", 1.0),
             "specular_anisotropy": ("anisotropy", 0.9), "specular_rotation": ("tangent", 1 / 180),
             "specular_IOR": ("ior", 1.0), "normal": ("normal", 1.0), "specular_color": ("specular_tint", 1.0)}
    for stem, (ours, k) in scale.items():
        r = rec["files"][stem]
        assert r["of"] == ours and r["file"] == f"{stem}_sigma.exr"
        assert r["exchange_unit"] is (stem != "specular_color"), stem
        got = _sigma(exr, stem, tuple(r["channels"]))
        np.testing.assert_array_equal(np.isnan(got), u[ours])
        np.testing.assert_allclose(got[~u[ours]], k * s[ours][~u[ours]], rtol=1e-6)
        names = tuple(f"{stem}_sigma.{c}" for c in r["channels"])  # read by name: OpenEXR sorts channels
        assert set(names) <= set(rec["mask"]["channels"])
        np.testing.assert_array_equal(read_exr(exr / "sigma_undetermined.exr", names) > 0.5, u[ours])
    assert rec["files"]["normal"]["unit"].startswith("degrees")
    assert "180" in rec["files"]["specular_rotation"]["mapping"]
    assert "not specular_color" in rec["files"]["specular_color"]["unit"]
    # the readers of the set see the maps as before (the sigma files are not maps)
    assert not any(m.endswith("_sigma") for m in doc["maps"])
    assert set(read_exchange_exr(exr)) >= {"base_color", "specular_roughness"}
    assert {f"exr/{stem}_sigma.exr" for stem in scale} <= set(read_export(tmp_path / "out")["formats"]["exr"])


def test_a_transmitting_sample_keeps_our_units_where_the_split_is_not_linear(tmp_path):
    maps = _folder(tmp_path / "sheer" / "maps", "sheer")
    export_material(maps, tmp_path / "out", ["exr"])
    exr = tmp_path / "out" / "exr"
    rec = json.loads((exr / "exchange.json").read_text())["uncertainty"]
    s, u, _ = load_uncertainty(maps)
    base = rec["files"]["base_color"]
    assert base["of"] == "albedo" and not base["exchange_unit"] and "not base_color" in base["unit"]
    t = rec["files"]["transmittance"]
    assert t["of"] == "transmittance" and not t["exchange_unit"] and "subsurface" in t["mapping"]
    got = _sigma(exr, "transmittance", ("R", "G", "B"))
    np.testing.assert_allclose(got[~u["transmittance"]], s["transmittance"][~u["transmittance"]], rtol=1e-6)
    assert rec["files"]["opacity"]["exchange_unit"]


def test_without_uncertainty_the_export_is_as_before(tmp_path):
    root = tmp_path / "plain" / "maps"
    save_maps(root, generate("twill", size=N, texel_mm=0.02, seed=1).maps, texel_mm=0.02)
    doc = export_material(root, tmp_path / "out", ["exr"])
    exr = tmp_path / "out" / "exr"
    assert json.loads((exr / "exchange.json").read_text())["uncertainty"] is None
    assert not list(exr.glob("*sigma*")) and doc["uncertainty_sha256"] is None


def test_a_tiled_export_says_why_it_has_no_sigma(tmp_path):
    maps = _folder(tmp_path / "twill" / "maps", "twill", n=64)
    export_material(maps, tmp_path / "out", ["exr"], tile=True)
    exr = tmp_path / "out" / "exr"
    rec = json.loads((exr / "exchange.json").read_text())["uncertainty"]
    assert rec["files"] == {} and "tile" in rec["left_out"]["*"] and not list(exr.glob("*sigma*"))


def test_a_changed_uncertainty_redoes_the_exr_set_only(tmp_path):
    maps = _folder(tmp_path / "twill" / "maps", "twill")
    out = tmp_path / "out"
    export_material(maps, out, ["exr", "mtlx"])
    assert sorted(export_material(maps, out, ["exr", "mtlx"])["reused"]) == ["exr", "mtlx"]
    _folder(maps, "twill", seed=5)  # the same maps, another uncertainty
    doc = export_material(maps, out, ["exr", "mtlx"])
    assert doc["reused"] == ["mtlx"]
    s, u, _ = load_uncertainty(maps)
    got = _sigma(out / "exr", "specular_roughness", ("Y",))
    np.testing.assert_allclose(got[~u["roughness"]], s["roughness"][~u["roughness"]], rtol=1e-6)
    # removed: the exr set no longer matches, and is dropped when not asked for
    _folder(maps, "twill", seed=6)
    doc = export_material(maps, out, ["mtlx"])
    assert "exr" not in doc["formats"] and not (out / "exr").exists()


def test_an_uncertainty_of_another_size_is_refused_before_writing(tmp_path):
    from dualscale.errors import FormatError

    maps = _folder(tmp_path / "twill" / "maps", "twill")
    rng = np.random.default_rng(0)
    save_uncertainty(maps, {"roughness": rng.uniform(0, 0.1, (N - 1, N, 1))},
                     {"roughness": np.zeros((N - 1, N, 1), bool)})
    with pytest.raises(FormatError, match="the uncertainty is"):
        export_material(maps, tmp_path / "out", ["exr"])
    assert not (tmp_path / "out").exists()


def test_an_uncertainty_of_other_maps_is_refused_before_writing(tmp_path):
    """The uncertainty a fit writes names its maps (``meta.maps_sha256``); one copied in beside
    other maps of the same size (a fresh user's trial: leather's sigma exported as the twill's)
    is refused, and a folder whose record names these maps, or none (earlier fits), exports."""
    import shutil

    from dualscale.errors import FormatError
    from dualscale.formats.maps import maps_sha256

    twill = _folder(tmp_path / "twill" / "maps", "twill")
    leather = _folder(tmp_path / "leather" / "maps", "leather")
    s, u, _ = load_uncertainty(leather)
    save_uncertainty(leather, s, u, meta={"noise": "n", "maps_sha256": maps_sha256(leather)})
    export_material(leather, tmp_path / "ok", ["exr"])  # its own: exported
    shutil.rmtree(twill / "uncertainty")
    shutil.copytree(leather / "uncertainty", twill / "uncertainty")
    with pytest.raises(FormatError, match="belongs to other maps"):
        export_material(twill, tmp_path / "out", ["exr"])
    assert not (tmp_path / "out").exists()


def test_the_exports_maps_keep_their_uncertainty_for_the_viewer(tmp_path):
    """An untiled export's ``maps/`` copy carries the uncertainty beside it, bound to the copy
    (its ``maps_sha256``), so ``dualscale view`` finds sigma there once the source has moved
    (a fresh user's trial: the viewer had looked only at the source folder); a tiled export's
    copy has none."""
    from dualscale.formats.maps import maps_sha256
    from dualscale.view.scene import _sigma_source

    maps = _folder(tmp_path / "twill" / "maps", "twill")
    out = tmp_path / "out"
    doc = export_material(maps, out, ["mtlx"])
    assert "maps/uncertainty/uncertainty.json" in doc["formats"]["maps"]
    s0, u0, _ = load_uncertainty(maps)
    s1, u1, d1 = load_uncertainty(out / "maps")
    assert d1["meta"]["maps_sha256"] == maps_sha256(out / "maps")
    for k in s0:
        assert np.array_equal(u0[k], u1[k]) and np.array_equal(np.nan_to_num(s0[k]), np.nan_to_num(s1[k]))
    moved = tmp_path / "elsewhere"
    (tmp_path / "twill").rename(moved)
    assert _sigma_source(out, str(maps)) == out / "maps"
    big = _folder(tmp_path / "big" / "maps", "twill", n=64)
    tiled = export_material(big, tmp_path / "tiled", ["mtlx"], tile=True)
    assert not (tmp_path / "tiled" / "maps" / "uncertainty").exists() and tiled["uncertainty_sha256"]


def test_the_export_command_says_where_sigma_went(tmp_path, capsys):
    from dualscale.cli import main

    maps = _folder(tmp_path / "twill" / "maps", "twill")
    assert main(["export", str(maps), "-o", str(tmp_path / "out"), "--format", "exr,mtlx"]) == 0
    said = capsys.readouterr().out
    assert "sigma: the maps' 1-sigma uncertainty in exr/*_sigma.exr" in said and "no field for it" in said
    plain = tmp_path / "plain" / "maps"
    save_maps(plain, generate("twill", size=N, texel_mm=0.02, seed=1).maps, texel_mm=0.02)
    assert main(["export", str(plain), "-o", str(tmp_path / "out2"), "--format", "mtlx"]) == 0
    assert "sigma" not in capsys.readouterr().out
