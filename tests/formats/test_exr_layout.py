"""Dataset image layout (issue 25 Sec. 3): tiled EXR as written for the micro camera reads,
whole and by any region, bit for bit as the plain scanline file does; a synthetic micro
dataset written tiled loads to exactly the observations of the plain layout; the importer and
the other readers still read plain files."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from dualscale.errors import FormatError, GeometryError
from dualscale.formats.dataset import TILED_CAMERAS, read_dataset
from dualscale.formats.exr import read_exr, read_exr_attributes, write_exr

H, W, T = 70, 90, 16  # edge tiles cut short both ways: 70 = 4*16 + 6, 90 = 5*16 + 10


def _tile_width(path: Path) -> int:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    try:
        return inp.spec().tile_width
    finally:
        inp.close()


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("layout")
    rng = np.random.default_rng(3)
    # every float32 bit pattern class that matters: negatives, tiny, large, exact zeros
    img = (rng.standard_normal((H, W, 3)) * np.exp(rng.uniform(-20, 20, (H, W, 1)))).astype(np.float32)
    img[5, 7] = 0.0
    write_exr(d / "plain.exr", img)
    write_exr(d / "tiled.exr", img, tile=T)
    return img, d / "plain.exr", d / "tiled.exr"


def test_the_writer_writes_the_layout_asked_for(pair):
    _, plain, tiled = pair
    assert _tile_width(plain) == 0 and _tile_width(tiled) == T


def test_whole_reads_equal_bit_for_bit(pair):
    img, plain, tiled = pair
    a, b = read_exr(plain), read_exr(tiled)
    assert a.dtype == b.dtype == np.float32 and a.shape == b.shape == (H, W, 3)
    assert a.tobytes() == b.tobytes() == img.tobytes()
    assert read_exr(tiled, ("B", "R")).tobytes() == img[..., [2, 0]].tobytes()


def _boxes():
    edges_y = [0, 1, 15, 16, 17, 31, 63, 64, 65, 69, 70]
    out = []
    for y0 in edges_y:
        for y1 in edges_y:
            if y1 <= y0:
                continue
            for x0, x1 in ((0, 90), (0, 1), (15, 17), (16, 32), (17, 81), (80, 90), (89, 90), (3, 88)):
                out.append((y0, y1, x0, x1))
    # every 1-pixel box along the diagonal and the edges, the whole image as a box
    out += [(y, y + 1, x, x + 1) for y, x in zip(range(0, H), range(0, W))]
    out += [(H - 1, H, x, x + 1) for x in range(W)] + [(y, y + 1, W - 1, W) for y in range(H)]
    out += [(0, H, 0, W)]
    return out


def test_every_box_reads_bit_for_bit_the_crop(pair):
    img, plain, tiled = pair
    boxes = _boxes()
    assert len(boxes) > 500
    for box in boxes:
        y0, y1, x0, x1 = box
        want = np.ascontiguousarray(img[y0:y1, x0:x1])
        for path in (plain, tiled):
            got = read_exr(path, box=box, size=(H, W))
            assert got.shape == want.shape and got.tobytes() == want.tobytes(), (path.name, box)
        got = read_exr(tiled, ("G",), box=box)
        assert got.tobytes() == np.ascontiguousarray(img[y0:y1, x0:x1, 1:2]).tobytes(), box


def test_random_boxes_and_tile_sizes(tmp_path):
    rng = np.random.default_rng(7)
    img = rng.random((37, 53, 4), dtype=np.float32)
    for tile in (1, 5, 16, 64):
        write_exr(tmp_path / f"t{tile}.exr", img, tile=tile)
        for _ in range(40):
            y0, y1 = sorted(rng.choice(38, 2, replace=False))
            x0, x1 = sorted(rng.choice(54, 2, replace=False))
            got = read_exr(tmp_path / f"t{tile}.exr", box=(y0, y1, x0, x1))
            assert got.tobytes() == np.ascontiguousarray(img[y0:y1, x0:x1]).tobytes(), (tile, y0, y1, x0, x1)


def test_refusals_are_the_same_in_both_layouts(pair, tmp_path):
    _, plain, tiled = pair
    for path in (plain, tiled):
        with pytest.raises(ValueError, match="outside"):
            read_exr(path, box=(0, H + 1, 0, 1))
        with pytest.raises(ValueError, match="outside"):
            read_exr(path, box=(3, 3, 0, 1))
        with pytest.raises(ValueError, match="expected"):
            read_exr(path, box=(0, 1, 0, 1), size=(W, H))
        with pytest.raises(ValueError, match="no channel"):
            read_exr(path, ("Z",), box=(0, 1, 0, 1))
    for bad in (0, -16, 16.0, True):
        with pytest.raises(ValueError, match="tile"):
            write_exr(tmp_path / "bad.exr", np.zeros((4, 4, 3)), tile=bad)
    # a shifted data window is refused in the tiled layout too
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(32, 32, 3, "float")
    spec.tile_width = spec.tile_height = 16
    spec.x = 8
    out = oiio.ImageOutput.create(str(tmp_path / "shift.exr"))
    assert out.open(str(tmp_path / "shift.exr"), spec)
    out.write_image(np.zeros((32, 32, 3), np.float32))
    out.close()
    with pytest.raises(GeometryError, match="data window"):
        read_exr(tmp_path / "shift.exr", box=(0, 16, 0, 16))
    # a truncated tiled file is a FormatError, as a truncated scanline file
    data = tiled.read_bytes()
    (tmp_path / "short.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError):
        read_exr(tmp_path / "short.exr", box=(H - 16, H, W - 16, W))


def test_region_reads_touch_only_their_tiles(tmp_path):
    """The tiled reader decodes the tiles a box needs, not every row it crosses: a file cut short
    (its last chunk, the bottom-right tile, lost) still gives a box that avoids that tile, while
    the scanline file cut the same way fails for the same box (its last chunk holds whole rows)."""
    img = np.random.default_rng(1).random((64, 64, 3), dtype=np.float32)
    write_exr(tmp_path / "t.exr", img, tile=16)
    write_exr(tmp_path / "s.exr", img)
    for name in ("t.exr", "s.exr"):
        b = (tmp_path / name).read_bytes()
        (tmp_path / name).write_bytes(b[:-100])
    got = read_exr(tmp_path / "t.exr", box=(48, 64, 0, 48))  # bottom row of tiles but the damaged one
    assert got.tobytes() == np.ascontiguousarray(img[48:64, :48]).tobytes()
    with pytest.raises(FormatError):
        read_exr(tmp_path / "t.exr", box=(48, 64, 47, 49))
    with pytest.raises(FormatError):
        read_exr(tmp_path / "s.exr", box=(48, 64, 0, 48))


def _synth(root: Path) -> Path:
    from dualscale.cli import main

    assert main(["synth", "twill", "-o", str(root), "--size", "40", "--texel-um", "9", "--dataset", "--lights",
                 "mod9", "--no-previews", "--no-progress"]) == 0
    return root / "micro"


def _plain_copy(ds: Path, out: Path) -> Path:
    """The same dataset with every image rewritten in the plain scanline layout."""
    shutil.copytree(ds, out)
    for p in sorted((out / "images").glob("*.exr")):
        attrs = {f"dualscale:{k}": v for k, v in read_exr_attributes(p).items()}
        write_exr(p, read_exr(p, ("R", "G", "B")), attributes=attrs)
        assert _tile_width(p) == 0
    return out


def test_a_synth_micro_dataset_is_tiled_and_loads_as_the_plain_one(tmp_path):
    from dualscale.fit.observations import load_observations

    ds = _synth(tmp_path / "syn")
    files = sorted((ds / "images").glob("*.exr"))
    assert files and all(_tile_width(p) == TILED_CAMERAS["micro"] for p in files)
    if (ds / "mask.exr").exists():
        assert _tile_width(ds / "mask.exr") == 0  # the mask is read whole: always plain
    plain = _plain_copy(ds, tmp_path / "plain")
    assert (plain / "manifest.json").read_bytes() == (ds / "manifest.json").read_bytes()
    a, b = load_observations(ds), load_observations(plain)
    boxes = [None, (0, 40, 0, 40), (3, 29, 5, 40), (39, 40, 0, 1), (0, 17, 33, 40)]
    for box in boxes:
        a, b = load_observations(ds, box=box), load_observations(plain, box=box)
        for name in ("images", "dirs", "w_s", "w_p", "w_d", "led_ids", "backlight", "view", "valid", "back_valid"):
            u, v = getattr(a, name), getattr(b, name)
            assert (u is None) == (v is None), name
            if u is not None:
                assert u.dtype == v.dtype and torch.equal(u, v), (name, box)
    # the plain dataset's reader sees the same pixels image by image
    ta, tb = read_dataset(ds), read_dataset(plain)
    for i in range(len(ta.records)):
        assert ta.load(i).tobytes() == tb.load(i).tobytes()


def test_the_writer_can_write_the_plain_layout(tmp_path):
    from dualscale.formats.dataset import DatasetWriter
    from dualscale.geometry.cameras import Camera

    cam = Camera("micro", "orthographic", 20, 12, (0.2, 0.12))
    img = np.random.default_rng(0).random((12, 20, 3), dtype=np.float32)
    for tiled in (True, False):
        with DatasetWriter(tmp_path / str(tiled), tiled=tiled) as w:
            rec = w.add(img, cam, "diffuse")
            w.add(img, Camera("mid", "orthographic", 20, 12, (2.0, 1.2)), "diffuse")
        assert _tile_width(tmp_path / str(tiled) / rec.file) == (64 if tiled else 0)
        assert _tile_width(tmp_path / str(tiled) / "images" / "mid_diffuse_nopol.exr") == 0
        assert read_dataset(tmp_path / str(tiled)).load(0).tobytes() == img.tobytes()


def test_the_importer_reads_plain_and_tiled_exr_photographs(tmp_path):
    """Photographs given as EXR (float, linear) in either layout import to the same dataset."""
    from dualscale.calib.photo_import import import_photos

    rng = np.random.default_rng(2)
    dirs = rng.normal(size=(8, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) + 1.0
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    normal = np.array([0.0, 0.0, 1.0])
    base = 0.2 + 0.6 * rng.random((24, 30, 3))
    got = {}
    for layout, tile in (("plain", None), ("tiled", 8)):
        folder = tmp_path / layout
        folder.mkdir()
        for k, d in enumerate(dirs):
            write_exr(folder / f"p.{k}.exr", (base * max(float(d @ normal), 0.05)).astype(np.float32), tile=tile)
        lp = tmp_path / f"{layout}.lp"
        lp.write_text(f"{len(dirs)}\n" + "".join(f"p.{k}.exr {d[0]:.9f} {d[1]:.9f} {d[2]:.9f}\n"
                                                 for k, d in enumerate(dirs)))
        import_photos(folder, lp, tmp_path / f"ds_{layout}", "linear", mask=None, scale=1.0)
        ds = read_dataset(tmp_path / f"ds_{layout}")
        got[layout] = [ds.load(i) for i in range(len(ds.records))]
    assert len(got["plain"]) == len(dirs)
    for a, b in zip(got["plain"], got["tiled"], strict=True):
        assert a.tobytes() == b.tobytes()


def test_a_rig_capture_writes_the_micro_dataset_tiled_and_it_loads_as_the_plain_one(tmp_path):
    from dualscale.cli import main
    from dualscale.rig.launcher import sim_binary

    if not sim_binary().exists():
        pytest.skip("POSIX simulator not built (make -C firmware posix)")
    assert main(["capture", "micro", "-o", str(tmp_path / "cap"), "--port", "sim", "--camera",
                 "sim:micro?material=leather&size=12&texel_um=9&readout_ms=1", "--lights", "MOD32",
                 "--rig-id", "virtual-dome-0", "--sim-speed", "10", "--no-progress"]) == 0
    cap = read_dataset(tmp_path / "cap")
    assert cap.records and all(_tile_width(tmp_path / "cap" / r.file) == 64 for r in cap.records)
    plain = read_dataset(_plain_copy(tmp_path / "cap", tmp_path / "plain"))
    for i, r in enumerate(cap.records):
        assert cap.load(i).tobytes() == plain.load(i).tobytes()
        assert cap.load(i, box=(3, 11, 5, 12)).tobytes() == plain.load(i, box=(3, 11, 5, 12)).tobytes()


def test_the_write_check_catches_a_tiled_file_cut_short(pair, tmp_path):
    """verify_image (run on every write) reads a tiled EXR's last tile: a short file is an OutputError."""
    import OpenImageIO as oiio

    from dualscale.errors import OutputError
    from dualscale.formats.exr import verify_image

    _, _, tiled = pair
    spec = oiio.ImageSpec(W, H, 3, "float")
    verify_image(tiled, spec)
    data = tiled.read_bytes()
    (tmp_path / "short.exr").write_bytes(data[:-64])
    with pytest.raises(OutputError):
        verify_image(tmp_path / "short.exr", spec)
