"""Issue 15 §2: the inference session options, the int8 option and the streamed maps writer."""

import json
import shutil
import threading

import numpy as np
import pytest
import torch

from dualscale.bsdf import MaterialMaps
from dualscale.errors import FormatError, InputError
from dualscale.formats.exr import read_exr, read_exr_attributes, write_exr
from dualscale.formats.maps import MapsWriter, load_maps, save_maps
from dualscale.propagate.export import export_model
from dualscale.propagate.infer import OnnxModel, run_tiled

OPT_TOLERANCE = 1e-5  # max abs difference between graph optimisation levels (fp32 reordering only)


@pytest.fixture(scope="module")
def model_dir(tiny_model, tmp_path_factory):
    """A private copy of the tiny model with its fp32, fp16 and int8 exports."""
    d = tmp_path_factory.mktemp("speed")
    shutil.copy(tiny_model, d / "m.dsp")
    export_model(d / "m.dsp", check=False, int8=True)
    return d


def _guidance(tmp_path, h=72, w=88):
    rng = np.random.default_rng(1)
    img = (0.2 + 0.3 * rng.random((h, w, 3))).astype(np.float32)
    write_exr(tmp_path / "g.exr", img)
    return tmp_path / "g.exr", img


def test_optimised_session_equals_plain(model_dir):
    """ORT_ENABLE_ALL (fusions, NCHWc layout) gives the unoptimised graph's outputs within 1e-5."""
    x = (0.1 + 0.4 * np.random.default_rng(0).random((2, 3, 48, 64))).astype(np.float32)
    plain = OnnxModel.open(model_dir / "m.onnx", 1, optimization="none")(x)
    for level in ("basic", "extended", "all"):
        got = OnnxModel.open(model_dir / "m.onnx", 1, optimization=level)(x)
        assert np.abs(got - plain).max() < OPT_TOLERANCE, level
    with pytest.raises(ValueError, match="optimization"):
        OnnxModel.open(model_dir / "m.onnx", optimization="fast")


def test_int8_is_explicit_and_close(model_dir, tmp_path):
    fp32 = OnnxModel.open(model_dir / "m.onnx")
    assert fp32.precision == "fp32"
    q = OnnxModel.open(model_dir / "m.dsp", precision="int8")  # resolved next to the model file
    assert q.precision == "int8" and not q.half and q.maps == fp32.maps
    x = (0.1 + 0.4 * np.random.default_rng(0).random((1, 3, 32, 48))).astype(np.float32)
    d = np.abs(q(x) - fp32(x))
    assert 0 < d.max() < 0.2  # quantised (not the same graph), but still the same network
    path, _ = _guidance(tmp_path)
    s = run_tiled(q, path, tmp_path / "o", tile=48, overlap=16, exposure=1.0, progress=False)
    assert s["precision"] == "int8"
    assert json.loads((tmp_path / "o" / "material.json").read_text())["meta"]["propagate"]["precision"] == "int8"


def test_int8_refused_clearly(model_dir, tmp_path):
    shutil.copy(model_dir / "m.dsp", tmp_path / "n.dsp")
    export_model(tmp_path / "n.dsp", check=False)  # fp32 and fp16 only
    with pytest.raises(InputError, match=r"n\.int8\.onnx.*int8=True"):
        OnnxModel.open(tmp_path / "n.dsp", precision="int8")
    with pytest.raises(FormatError, match="is a fp32 model, not int8"):
        OnnxModel.open(tmp_path / "n.onnx", precision="int8")
    with pytest.raises(InputError, match="precision must be"):
        OnnxModel.open(tmp_path / "n.onnx", precision="int4")
    # an int8 file quantised from another fp32 export than the one beside it is stale
    shutil.copy(model_dir / "m.int8.onnx", tmp_path / "n.int8.onnx")
    meta = OnnxModel.open(model_dir / "m.int8.onnx").session.get_modelmeta().custom_metadata_map
    assert meta["dualscale:quantised_from"] == "m.onnx"
    shutil.copy(model_dir / "m.int8.onnx", tmp_path / "m.int8.onnx")
    (tmp_path / "m.onnx").write_bytes(b"another export")
    with pytest.raises(FormatError, match="stale"):
        OnnxModel.open(tmp_path / "m.int8.onnx", precision="int8")


def _maps(h=37, w=29, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = torch.randn(h, w, 3, generator=g)
    n[..., 2] = n[..., 2].abs() + 0.5
    return MaterialMaps(albedo=torch.rand(h, w, 3, generator=g), roughness=torch.rand(h, w, 1, generator=g),
                        normal=n / n.norm(dim=-1, keepdim=True), tangent=torch.rand(h, w, 1, generator=g))


def test_maps_writer_by_rows_writes_what_save_maps_writes(tmp_path):
    maps = _maps()
    meta = {"x": 1}
    save_maps(tmp_path / "a", maps, meta, previews=True, texel_mm=0.02, attributes={"dualscale:k": "v"})
    names = [n for n, _ in maps.items()]
    with MapsWriter(tmp_path / "b", names, 37, 29, meta, True, 0.02, {"dualscale:k": "v"}) as w:
        for y0, y1 in ((0, 5), (5, 21), (21, 37)):
            w.write(y0, {n: t[y0:y1].numpy() for n, t in maps.items()})
    assert json.loads((tmp_path / "a" / "material.json").read_text()) == \
        json.loads((tmp_path / "b" / "material.json").read_text())
    for n in names:
        assert np.array_equal(read_exr(tmp_path / "a" / f"{n}.exr"), read_exr(tmp_path / "b" / f"{n}.exr")), n
        assert np.array_equal(read_exr(tmp_path / "a" / f"{n}.png"), read_exr(tmp_path / "b" / f"{n}.png")), n
        assert read_exr_attributes(tmp_path / "b" / f"{n}.exr") == {"k": "v", "map": n}
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == sorted(p.name for p in (tmp_path / "b").iterdir())
    load_maps(tmp_path / "b")


def test_maps_writer_refuses_and_leaves_nothing(tmp_path):
    maps = _maps()
    save_maps(tmp_path / "m", maps, previews=False)  # an earlier, complete set
    before = {p.name: p.read_bytes() for p in (tmp_path / "m").iterdir() if p.suffix == ".exr"}
    rows = {n: t[:10].numpy() for n, t in maps.items()}
    bad = dict(rows, roughness=np.full((10, 29, 1), np.nan, np.float32))
    for call, match in ((lambda w: w.write(0, bad), r"'roughness' contains NaN or Inf \(rows 0\.\.9\)"),
                        (lambda w: w.write(5, rows), "rows must come in order"),
                        (lambda w: w.write(0, {"albedo": rows["albedo"]}), "rows for maps"),
                        (lambda w: w.write(0, rows), "10 of 37 rows written")):
        with pytest.raises(ValueError, match=match):
            with MapsWriter(tmp_path / "m", [n for n, _ in maps.items()], 37, 29, previews=True) as w:
                call(w)
        files = {p.name for p in (tmp_path / "m").iterdir()}
        assert not any(f.startswith(".tmp-") for f in files) and "material.json" not in files, files
        assert not any(f.endswith(".png") for f in files), files
        assert {f: (tmp_path / "m" / f).read_bytes() for f in before} == before  # the old maps untouched


class _Stopping:
    """An OnnxModel that raises ``exc`` on its ``n``-th tile."""

    def __init__(self, model, n, exc):
        self.model, self.n, self.exc, self.calls = model, n, exc, 0

    def __getattr__(self, name):
        return getattr(self.model, name)

    def __call__(self, x):
        self.calls += 1
        if self.calls == self.n:
            raise self.exc
        return self.model(x)


def test_streamed_run_equals_held_maps(model_dir, tmp_path, monkeypatch):
    """The streamed writer (rows written while the next strip computes) writes exactly the files
    that the maps held whole and saved by save_maps give, previews included; it gets strips of
    rows, the first before the last tile is computed."""
    path, _ = _guidance(tmp_path)
    om = OnnxModel.open(model_dir / "m.onnx", 1)
    a = run_tiled(om, path, tmp_path / "held", tile=32, overlap=8, exposure=1.0, progress=False, stream=False,
                  previews=True)
    model, real, writes = _Stopping(om, 0, None), MapsWriter.write, []

    def write(self, y0, rows):
        writes.append((y0, len(rows["albedo"]), model.calls))
        real(self, y0, rows)

    monkeypatch.setattr(MapsWriter, "write", write)
    b = run_tiled(model, path, tmp_path / "streamed", tile=32, overlap=8, exposure=1.0, progress=False,
                  previews=True)
    assert a == b and a["tiles"] == 12
    assert [w[:2] for w in writes] == [(0, 24), (24, 16), (40, 32)]
    assert writes[0][2] < 12  # the first strip was handed over while tiles were still to compute
    files = sorted(p.name for p in (tmp_path / "held").iterdir())
    assert files == sorted(p.name for p in (tmp_path / "streamed").iterdir()) and "normal.png" in files
    for f in files:
        if f.endswith((".exr", ".png")):
            assert np.array_equal(read_exr(tmp_path / "held" / f), read_exr(tmp_path / "streamed" / f)), f
    assert (tmp_path / "held" / "material.json").read_text() == (tmp_path / "streamed" / "material.json").read_text()


@pytest.mark.parametrize("where", ["compute", "writer"])
def test_interrupted_stream_leaves_no_partial_file(model_dir, tmp_path, monkeypatch, where):
    """Ctrl-C during the tiles, or a disk error in the writer thread after some strips were
    written: the error reaches the caller, the writer thread ends, and no map, preview or
    material.json appears; only the files that were there before remain."""
    path, _ = _guidance(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    om = OnnxModel.open(model_dir / "m.onnx", 1)
    if where == "compute":
        model, exc = _Stopping(om, 7, KeyboardInterrupt()), KeyboardInterrupt
    else:
        model, exc = om, OSError
        real, calls = MapsWriter.write, []

        def write(self, y0, rows):
            calls.append(y0)
            if len(calls) == 3:
                raise OSError(28, "No space left on device", str(out / "albedo.exr"))
            real(self, y0, rows)

        monkeypatch.setattr(MapsWriter, "write", write)
    threads = threading.active_count()
    with pytest.raises(exc):
        run_tiled(model, path, out, tile=32, overlap=8, exposure=1.0, progress=False, previews=True)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    assert threading.active_count() == threads
    if where == "writer":
        assert calls == [0, 24, 40]  # two strips had been written (to temporary files) before the error


@pytest.mark.parametrize("n,tile,overlap", [(4072, 1024, 64), (4072, 512, 64), (4072, 768, 64), (4200, 512, 64),
                                            (100, 48, 16), (33, 48, 16), (515, 128, 0)])
def test_tiles_fitted_to_the_image(n, tile, overlap):
    """The fewest tiles of at most `tile` px cover the image with at least `overlap`, each as small
    as that count allows (4072 px at 1024: 5 tiles of 880 instead of 5 of 1024)."""
    from dualscale.propagate.infer import TilePlan, tile_positions

    plan = TilePlan.make(n, n, tile, overlap)
    t, pos = plan.th, plan.ys
    assert t % 16 == 0 and t <= tile and pos[0] == 0
    assert pos[-1] + t == n if n > t else pos == (0,)
    assert all(b - a <= t - overlap for a, b in zip(pos, pos[1:]))  # every neighbour overlaps >= overlap
    fewest = len(tile_positions(n, tile, tile - overlap))
    assert len(pos) == fewest
    if n > tile:
        assert len(tile_positions(n, t - 16, t - 16 - overlap)) > fewest  # a smaller tile needs more
    if (n, tile) == (4072, 1024):
        assert (t, plan.tiles) == (880, 25)
