"""``dualscale export``: every format from one maps folder, the manifest, resume, refusals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dualscale.cli import main
from dualscale.export.material import ALL_FORMATS, OPTIONAL_FORMATS, export_material, formats_available, read_export
from dualscale.formats.exr import read_exr
from dualscale.formats.maps import load_maps, save_maps
from dualscale.sim.materials import generate


@pytest.fixture(scope="module")
def twill(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("twill") / "maps"
    mat = generate("twill", size=32, texel_mm=0.02, seed=1)
    save_maps(root, mat.maps, {"material": "twill"}, texel_mm=0.02)
    return root


def test_every_format_is_registered():
    assert set(formats_available()) == set(ALL_FORMATS) | set(OPTIONAL_FORMATS)


def test_export_writes_every_format_and_a_manifest(twill, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["export", str(twill), "-o", str(out), "--name", "twill"]) == 0
    doc = read_export(out)
    assert doc["name"] == "twill" and set(doc["formats"]) == {"maps", *ALL_FORMATS}
    assert doc["repeat_mm"] == pytest.approx([0.64, 0.64]) and not doc["tiled"]
    for files in doc["formats"].values():
        assert files and all((out / f).is_file() for f in files)
    assert not [p for p in out.rglob("*") if p.name.startswith(".tmp-")]
    text = capsys.readouterr().out
    assert "0.64 x 0.64 mm" in text and str(out / "glb" / "twill.glb") in text
    maps, meta = load_maps(out / "maps")  # our own conventions, beside the exchange set
    assert meta["texel_mm"] == pytest.approx(0.02) and maps.shape == (32, 32)


def test_exchange_exr_is_full_precision_standard_surface(twill, tmp_path):
    export_material(twill, tmp_path, ["exr"])
    maps, _ = load_maps(twill)
    ex = json.loads((tmp_path / "exr" / "exchange.json").read_text())
    assert ex["repeat_mm"] == pytest.approx([0.64, 0.64])
    np.testing.assert_array_equal(read_exr(tmp_path / "exr" / "base_color.exr", ("R", "G", "B")),
                                  maps.albedo.numpy())
    np.testing.assert_array_equal(read_exr(tmp_path / "exr" / "specular_roughness.exr", ("Y",)),
                                  maps.roughness.numpy())
    n = read_exr(tmp_path / "exr" / "normal.exr", ("X", "Y", "Z"))
    np.testing.assert_array_equal(n, maps.normal.numpy())


def test_rerun_skips_complete_formats_and_redoes_a_missing_one(twill, tmp_path):
    out = tmp_path / "out"
    export_material(twill, out, ["exr", "glb"])
    glb = next((out / "glb").glob("*.glb"))
    stamp = glb.stat().st_mtime_ns
    (out / "exr" / "base_color.exr").unlink()
    doc = export_material(twill, out, ["exr", "glb"])
    assert glb.stat().st_mtime_ns == stamp  # unchanged: skipped
    assert (out / "exr" / "base_color.exr").is_file() and set(doc["formats"]) == {"maps", "exr", "glb"}


@pytest.mark.parametrize("argv, says", [
    (["--format", "obj"], "--format 'obj'"),
    (["--name", "bad name!"], "material name"),
    (["--swatch-mm", "-3"], "--swatch-mm"),
])
def test_bad_options_exit_2_and_write_nothing(twill, tmp_path, capsys, argv, says):
    out = tmp_path / "out"
    assert main(["export", str(twill), "-o", str(out), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0]
    assert not out.exists() or not any(out.iterdir())


def test_not_a_maps_folder_exits_2(tmp_path, capsys):
    assert main(["export", str(tmp_path), "-o", str(tmp_path / "out")]) == 2
    assert "material.json" in capsys.readouterr().err


def test_unknown_size_refuses_u3m_before_writing_and_all_leaves_it_out(tmp_path, capsys):
    mat = generate("twill", size=16, texel_mm=0.02, seed=1)
    save_maps(tmp_path / "maps", mat.maps, {})  # no texel size
    assert main(["export", str(tmp_path / "maps"), "-o", str(tmp_path / "a"), "--format", "gltf,u3m"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "texel" in err[0] and "U3M" in err[0]
    assert not (tmp_path / "a").exists()  # refused before anything was written
    assert main(["export", str(tmp_path / "maps"), "-o", str(tmp_path / "b")]) == 0  # all: U3M left out, said so
    assert "u3m   left out: U3M needs the physical size" in capsys.readouterr().out
    doc = read_export(tmp_path / "b")
    assert doc["repeat_mm"] is None and "u3m" in doc["skipped"]
    assert set(doc["formats"]) == {"maps", "exr", "mtlx", "gltf", "glb"}


def test_an_output_folder_holding_the_source_is_refused(twill, tmp_path, capsys):
    """Exporting into the folder above the maps (e.g. -o RUN/fit for RUN/fit/maps) would replace
    the source maps: refused, and the source is untouched."""
    import shutil

    src = tmp_path / "run" / "fit" / "maps"
    shutil.copytree(twill, src)
    (src / "geometry.exr").write_bytes(b"keep")
    before = sorted(p.name for p in src.iterdir())
    for out in (src.parent, src, tmp_path / "run"):
        assert main(["export", str(src), "-o", str(out)]) == 2
        assert "holds the source maps" in capsys.readouterr().err
    assert sorted(p.name for p in src.iterdir()) == before and (src / "geometry.exr").read_bytes() == b"keep"


def test_manifest_keeps_earlier_formats_and_drops_stale_ones(twill, tmp_path):
    out = tmp_path / "out"
    export_material(twill, out, ["mtlx"])
    doc = export_material(twill, out, ["glb"])  # same source: mtlx stays in the manifest
    assert {"mtlx", "glb"} <= set(doc["formats"]) and (out / "mtlx").is_dir()
    other = tmp_path / "other" / "maps"
    save_maps(other, generate("satin", size=16, texel_mm=0.02, seed=4).maps, {}, texel_mm=0.02)
    doc = export_material(other, out, ["gltf"])  # another source: the stale formats go
    assert set(doc["formats"]) == {"maps", "gltf"}
    assert not (out / "mtlx").exists() and not (out / "glb").exists()


def test_tile_carries_its_physical_size_into_every_format(tmp_path, capsys):
    """A 2/2 twill of 0.3 mm pitch repeats every 1.2 mm: the tile is 1.2 mm square in every format
    (glTF swatch of 2 x 2 tiles, U3M width/height, MaterialX real-world size, EXR record)."""
    import zipfile

    mat = generate("twill", size=80, texel_mm=0.035, seed=3)
    save_maps(tmp_path / "maps", mat.maps, {}, texel_mm=0.035)
    out = tmp_path / "out"
    assert main(["export", str(tmp_path / "maps"), "-o", str(out), "--tile", "--name", "tw"]) == 0
    assert "seamless tile, 1.2 x 1.2 mm" in capsys.readouterr().out
    doc = read_export(out)
    assert doc["tiled"] and doc["repeat_mm"] == pytest.approx([1.2, 1.2], abs=0.002)
    assert doc["repeat_mm"] == pytest.approx(doc["tile"]["size_mm"], abs=1e-6)  # the tile's own size
    assert doc["tile"]["seam"]["tile"] <= 1.1
    _, meta = load_maps(out / "maps")
    assert meta["tile"]["size_mm"] == pytest.approx([1.2, 1.2], abs=0.002)
    gltf = json.loads((out / "gltf" / "tw.gltf").read_text())
    ext = gltf["asset"]["extras"]["dualscale"]
    assert ext["repeat_mm"] == pytest.approx([1.2, 1.2], abs=0.002) and ext["repeats"] == [2.0, 2.0]
    pos = np.array(gltf["accessors"][gltf["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]["max"])
    assert 2 * pos[0] == pytest.approx(0.0024, abs=4e-6)  # metres: 2 tiles of 1.2 mm
    with zipfile.ZipFile(out / "u3m" / "tw.u3ma") as z:
        u3m = json.loads(z.read("tw.u3m"))
    img = u3m["material"]["front"]["basecolor"]["texture"]["image"]
    assert img["width"] == pytest.approx(1.2, abs=0.002) and img["height"] == pytest.approx(1.2, abs=0.002)
    assert "realworldimagesize" in (out / "mtlx" / "tw.mtlx").read_text()
    ex = json.loads((out / "exr" / "exchange.json").read_text())
    assert ex["tiled"] and ex["repeat_mm"] == pytest.approx([1.2, 1.2], abs=0.002)


def test_another_sources_export_folder_needs_overwrite(twill, tmp_path, capsys):
    """An export folder of another material is refused (issue 13: foreign outputs) unless
    --overwrite; a rerun of the same export into its own folder is not foreign."""
    out = tmp_path / "out"
    assert main(["export", str(twill), "-o", str(out), "--format", "glb"]) == 0
    assert main(["export", str(twill), "-o", str(out), "--format", "glb,mtlx"]) == 0  # same source: fine
    other = tmp_path / "other" / "maps"
    save_maps(other, generate("satin", size=16, texel_mm=0.02, seed=4).maps, {}, texel_mm=0.02)
    capsys.readouterr()
    assert main(["export", str(other), "-o", str(out), "--format", "glb"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert read_export(out)["source"] == str(twill)  # untouched
    assert main(["export", str(other), "-o", str(out), "--format", "glb", "--overwrite"]) == 0
    doc = read_export(out)
    assert doc["source"] == str(other) and set(doc["formats"]) == {"maps", "glb"}
