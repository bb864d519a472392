"""Dataset image layout (issue 25 Sec. 3; docs/APPEARANCE.md, "Image layout"): how long
OpenImageIO takes to read a whole image, a full-width band of rows and a square tile of a float32
RGB EXR (as :func:`dualscale.formats.exr.write_exr` writes every dataset image) in each layout --
scanline zip (the plain layout), tiled zip with 64 and 128 px tiles, tiled piz and zips with 64 px
tiles -- and the file sizes; the region reads go through ``read_exr(box=...)``, the fit's reader.
Medians of ``--repeats`` reads from the page cache, one thread; the ratio is against scanline zip
in the same run.

    PYTHONPATH=host python bench/bench_layout.py [--size 2048] [--repeats 7] [--region 64]

The image is smooth noise plus a ramp (a photograph's spatial correlation, so that the
compressors see something like real data, not incompressible white noise).  Prints a markdown
table with the machine, its load average and the date.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "host"))


def image(size: int, seed: int = 0) -> np.ndarray:
    """``(size, size, 3)`` float32: a ramp plus noise blurred over a few pixels, plus sensor-like noise."""
    rng = np.random.default_rng(seed)
    n = rng.standard_normal((size, size, 3)).astype(np.float32)
    k = np.ones(5, np.float32) / 5
    for ax in (0, 1):
        n = np.apply_along_axis(lambda v: np.convolve(v, k, "same"), ax, n) if size <= 256 else \
            sum(np.roll(n, s, ax) for s in range(-2, 3)) / 5
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    img = 0.3 + 0.2 * (x + y)[..., None] + 0.05 * n + 0.005 * rng.standard_normal((size, size, 3)).astype(np.float32)
    return np.clip(img, 0, None).astype(np.float32)


def write(path: Path, img: np.ndarray, tile: int | None, compression: str) -> None:
    import OpenImageIO as oiio

    from dualscale.formats.exr import write_exr, write_pixels

    if compression == "zip":
        write_exr(path, img, tile=tile)
        return
    spec = oiio.ImageSpec(img.shape[1], img.shape[0], 3, "float")
    spec.channelnames = ("R", "G", "B")
    spec.attribute("compression", compression)
    spec.attribute("DateTime", "")
    if tile:
        spec.tile_width = spec.tile_height = tile
    write_pixels(path, img, spec)


def median_s(fn, repeats: int) -> float:
    fn()  # warm: the file in the page cache, OpenImageIO's plugin loaded
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--region", type=int, default=64, help="band height and square tile side, px")
    a = ap.parse_args()
    import OpenImageIO as oiio

    from dualscale.formats.exr import read_exr

    oiio.attribute("threads", 1)
    oiio.attribute("exr_threads", 1)
    r, n = a.region, a.size
    # the region a tile fit reads: away from the edges, aligned to the 64 px grid (fit.tiled.TILE)
    y0 = x0 = (n // 2) // r * r
    layouts = [("scanline zip (plain)", None, "zip"), ("tiled zip 64", 64, "zip"), ("tiled zip 128", 128, "zip"),
               ("tiled piz 64", 64, "piz"), ("tiled zips 64", 64, "zips")]
    print(f"machine: {platform.node()} ({platform.processor() or platform.machine()}, {os.cpu_count()} cpus, shared); "
          f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}; "
          f"{datetime.datetime.now():%Y-%m-%d %H:%M}; OpenImageIO {oiio.__version__}, 1 thread")
    print(f"\n{n}x{n} float32 RGB ({n * n * 12 / 2 ** 20:.0f} MiB of pixels), medians of {a.repeats} reads from "
          f"the page cache; band = rows {y0}..{y0 + r} at full width, tile = {r}x{r} at ({y0}, {x0}); "
          "ratio = time / scanline zip's\n")
    img = image(n)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for name, tile, comp in layouts:
            p = Path(d) / f"{name.split()[0]}_{comp}_{tile}.exr"
            t0 = time.perf_counter()
            write(p, img, tile, comp)
            t_write = time.perf_counter() - t0
            full = median_s(lambda: read_exr(p), a.repeats)
            band = median_s(lambda: read_exr(p, box=(y0, y0 + r, 0, n)), a.repeats)
            sq = median_s(lambda: read_exr(p, box=(y0, y0 + r, x0, x0 + r)), a.repeats)
            got = read_exr(p, box=(y0, y0 + r, x0, x0 + r))
            assert np.array_equal(got, img[y0:y0 + r, x0:x0 + r]), name
            rows.append((name, p.stat().st_size, t_write, full, band, sq))
    base = rows[0]
    print("| layout | file (MiB) | write (s) | whole (ms) | ratio | band (ms) | ratio | tile (ms) | ratio | "
          "all tiles one by one (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, size, tw, full, band, sq in rows:
        print(f"| {name} | {size / 2 ** 20:.2f} | {tw:.2f} | {full * 1e3:.1f} | {full / base[3]:.2f} | "
              f"{band * 1e3:.2f} | {band / base[4]:.2f} | {sq * 1e3:.2f} | {sq / base[5]:.3f} | "
              f"{sq * (n // r) ** 2:.2f} |")
    # the whole read at smaller sizes: what tiling costs an image that is always read whole
    print(f"\nwhole read, scanline zip against tiled zip 64, medians of {a.repeats}\n")
    print("| size | scanline (ms) | tiled 64 (ms) | ratio | scanline (MiB) | tiled (MiB) |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as d:
        for m in (90, 256, 1024):
            small, t = image(m), {}
            for tile in (None, 64):
                p = Path(d) / f"{m}_{tile}.exr"
                write(p, small, tile, "zip")
                t[tile] = (median_s(lambda: read_exr(p), a.repeats), p.stat().st_size)
            print(f"| {m}x{m} | {t[None][0] * 1e3:.2f} | {t[64][0] * 1e3:.2f} | {t[64][0] / t[None][0]:.2f} | "
                  f"{t[None][1] / 2 ** 20:.3f} | {t[64][1] / 2 ** 20:.3f} |")


if __name__ == "__main__":
    main()
