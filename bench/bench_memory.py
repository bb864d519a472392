"""The fit out of core (issue 25): peak resident memory and time of the micro fit before
(``--memory unlimited``: the whole dataset loaded and fitted as one map) and after (the default
budget, ``--memory 2G``: bands read from disk), and the driver's memory and the bytes it ships
for a tiled fit on 2 local workers, before (the whole dataset loaded in the driver, every tile's
pixels sent with its task) and after (the workers read their own tiles); the baseline is
measured in the same run.  Prints markdown tables for docs/SCALE.md.

    PYTHONPATH=host python bench/bench_memory.py [--quick] [--sizes 256,512,1024[,2048]]
        [--tiled-sizes 512,1024] [--threads 2] [--workdir DIR] [--json out.json]

The datasets are ``dualscale synth twill --size N --dataset`` (254 LED images + the back light),
made once and kept in ``--workdir`` as ``t{N}/`` (default ``/tmp/dualscale-bench-memory``, which
persists, so that a rerun reuses them; a ``t{N}`` that another process is still writing is waited
for).  The components are fixed, twill's (``--anisotropy on --tint on --transmittance off``), so
that selection stays out of the timings; ``--cv-pixels 0``, ``--no-progress --no-previews``.

- **Fit** (``--sizes``): ``dualscale fit --preset standard --threads T`` per size, before and
  after, each in a fresh process under ``/usr/bin/time -v`` (its "Maximum resident set size"
  and "Elapsed (wall clock) time"); the bands come from ``fit.json``'s ``out_of_core`` record
  (1 = fitted whole); the maps of the two runs are compared bit for bit (``load_maps`` +
  ``torch.equal``).  *Before* is not run where its estimated peak exceeds the machine's
  ``MemAvailable`` (/proc/meminfo, read before each size): the estimate is linear in pixels x
  images, fitted to the sizes measured before it in the same run (least squares from two, through
  the origin from one, else the budget model of ``dualscale.fit.stream``: RESERVE +
  BYTES_PER_SAMPLE per pixel and image).  The time ratio of such a size compares its µs per
  pixel with the largest measured *before*'s, and says so.
- **Tiled** (``--tiled-sizes``, 2 local workers, 64 px tiles, preset ``draft`` to keep it short):
  *after* is ``dualscale fit DATASET --workers 2 --tile-px 64`` run by a child process of this
  script (``dualscale.cli.main``), whose peak is ``fit.json``'s ``out_of_core.peak_rss_mib`` (the
  driver's own ``getrusage(RUSAGE_SELF)``; ``/usr/bin/time``'s figure would be the largest of the
  driver and its worker processes); *before* is the way the tiled fit worked when the issue was
  filed: ``load_observations`` of the whole dataset, ``select_components``, then
  ``fit_tiled(obs, preset, comps, client, tile=64)`` with ``dataclasses.replace(obs,
  origin=None)`` (so each task carries its tile's pixels), in a child process printing its own
  ``ru_maxrss``.  In both, ``client.submit`` is wrapped to sum the pickled size of each task
  (function and arguments, ``cloudpickle``: as ``tests/fit/test_tiled.py`` measures it).

Every row records ``os.getloadavg()`` at its start and end.  Each dataset's files are read once
before its size's runs (page cache), so that *before*, which runs first, does not pay the disk
alone.  ``--quick`` (a smoke run: 5.6 min on the shared 2-core VM at load 3-5, with the 128²
synth; at that size and 256² the default budget fits the map whole, 1 band): sizes 128,256 for
both tables.  ``make bench`` runs it with no arguments (sizes 256,512,1024 and tiled 512,1024:
estimated 20-25 min on a quiet 2-core VM, twice that at load 3-4; the 1024² *before* is skipped
there for memory, 24 GB).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
#: the material; its components, fixed so that selection stays out of the timings
MATERIAL = "twill"
COMPONENT_ARGS = ["--anisotropy", "on", "--tint", "on", "--transmittance", "off"]
OVERRIDES = {"transmittance": False, "anisotropy": True, "tint": True}
#: LED images of a full micro capture (127 LEDs x P0/P90; the back light apart)
LED_IMAGES = 254
DEFAULT_WORKDIR = Path("/tmp/dualscale-bench-memory")
#: the tiled fit's workers, tile side and preset
WORKERS, TILE, TILED_PRESET = 2, 64, "draft"
#: how long to wait for a dataset another process is writing (seconds without a change)
STALE_S = 900


# --------------------------------------------------------------------------- helpers

def loadavg() -> str:
    return "/".join(f"{v:.2f}" for v in os.getloadavg())


def mem_available() -> int:
    for line in open("/proc/meminfo"):
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no MemAvailable in /proc/meminfo")


def machine() -> str:
    """bench_scale's machine line (the CPU model, cores and usable cores, the host), marked shared."""
    from bench_scale import machine as cpu

    return f"{platform.platform()}, {cpu()} (shared)"


def commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def dualscale_cmd() -> list[str]:
    exe = Path(sys.executable).parent / "dualscale"
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "dualscale"]


def child_env() -> dict[str, str]:
    env = dict(os.environ)
    host = str(REPO / "host")
    env["PYTHONPATH"] = host + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def parse_elapsed(text: str) -> float:
    """``/usr/bin/time -v``'s "h:mm:ss" or "m:ss.ss" in seconds."""
    s = 0.0
    for part in text.strip().split(":"):
        s = s * 60 + float(part)
    return s


def timed(cmd: list[str], log: Path) -> dict:
    """Run ``cmd`` under ``/usr/bin/time -v``; its peak RSS (bytes), wall seconds and stdout."""
    t0 = time.perf_counter()
    p = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True, env=child_env())
    wall = time.perf_counter() - t0
    log.write_text(f"$ {' '.join(cmd)}\n--- stdout\n{p.stdout}\n--- stderr\n{p.stderr}")
    if p.returncode != 0:
        raise RuntimeError(f"exit {p.returncode}: {' '.join(cmd)}\n{p.stderr[-3000:]}")
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr)
    el = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): (\S+)", p.stderr)
    return {"peak_bytes": int(rss.group(1)) * 1024 if rss else None,
            "wall_s": parse_elapsed(el.group(1)) if el else wall, "stdout": p.stdout}


def gb(b: float | None) -> str:
    return "–" if b is None else f"{b / 1e9:.2f}"


# --------------------------------------------------------------------------- datasets

def dataset(workdir: Path, n: int, threads: int) -> Path:
    """``workdir/t{n}`` (a ``synth --dataset`` output), made unless present; one that another
    process is still writing (files changed in the last STALE_S s) is waited for."""
    root = workdir / f"t{n}"
    manifest = root / "micro" / "manifest.json"
    told = False
    while root.exists() and not manifest.is_file():
        newest = max((p.stat().st_mtime for p in root.rglob("*")), default=root.stat().st_mtime)
        if time.time() - newest > STALE_S:
            break  # abandoned: made again below
        if not told:
            print(f"  waiting for {manifest} (another process is writing {root}) ...", flush=True)
            told = True
        time.sleep(10)
    if manifest.is_file():
        return root
    print(f"  synth {MATERIAL} --size {n} --dataset -> {root} ...", flush=True)
    t0 = time.perf_counter()
    subprocess.run([*dualscale_cmd(), "synth", MATERIAL, "--size", str(n), "--dataset", "-o", str(root),
                    "--no-previews", "--no-progress", "--threads", str(threads), "--overwrite"],
                   check=True, capture_output=True, env=child_env())
    print(f"  ... {time.perf_counter() - t0:.0f} s", flush=True)
    return root


def warm(ds: Path) -> None:
    """Read the dataset's files once, so that the first of two runs does not pay the disk alone."""
    for f in (ds / "micro").rglob("*"):
        if f.is_file():
            with open(f, "rb") as fh:
                while fh.read(1 << 23):
                    pass


# --------------------------------------------------------------------------- part 1: the fit

def fit_args(ds: Path, out: Path, memory: str, threads: int) -> list[str]:
    return [*dualscale_cmd(), "fit", str(ds), "-o", str(out), "--overwrite", "--preset", "standard",
            "--memory", memory, "--threads", str(threads), "--no-progress", "--no-previews", "--cv-pixels", "0",
            *COMPONENT_ARGS]


def maps_equal(a: Path, b: Path) -> tuple[bool, float]:
    import torch

    from dualscale.formats.maps import load_maps

    ma, mb = load_maps(a)[0], load_maps(b)[0]
    ka, kb = dict(ma.items()), dict(mb.items())
    if ka.keys() != kb.keys():
        return False, float("inf")
    equal, worst = True, 0.0
    for k, v in ka.items():
        if not torch.equal(v, kb[k]):
            equal = False
            worst = max(worst, float((v - kb[k]).abs().max()))
    return equal, worst


def estimate_before(measured: list[tuple[int, int]], samples: int) -> tuple[float, str]:
    """The before-peak (bytes) of a fit of ``samples`` pixels x images, from the ``(samples,
    peak)`` pairs measured so far; and how it was estimated."""
    if len(measured) >= 2:
        n = len(measured)
        mx = sum(x for x, _ in measured) / n
        my = sum(y for _, y in measured) / n
        sxx = sum((x - mx) ** 2 for x, _ in measured)
        b = sum((x - mx) * (y - my) for x, y in measured) / sxx
        a = my - b * mx
        return a + b * samples, f"linear fit to {n} measured sizes: {a / 1e6:.0f} MB + {b:.1f} B per pixel-image"
    if measured:
        x, y = measured[0]
        return y * samples / x, f"proportional to the measured size ({y / x:.1f} B per pixel-image)"
    from dualscale.fit.stream import BYTES_PER_SAMPLE, RESERVE

    return RESERVE + BYTES_PER_SAMPLE * samples, "fit.stream's model (nothing measured yet)"


def fit_row(n: int, ds: Path, out: Path, threads: int, measured: list[tuple[int, int]],
            before_us: list[tuple[int, float]]) -> dict:
    pixels = n * n
    samples = pixels * LED_IMAGES
    row: dict = {"size": n, "pixels": pixels, "load_start": loadavg()}
    avail = mem_available()
    est, how = estimate_before(measured, samples)
    row["available_bytes"], row["before_estimate_bytes"], row["before_estimate"] = avail, est, how
    runs: dict = {}
    warm(ds)
    if est > avail:
        row["before_skipped"] = f"not run: estimated {est / 1e9:.1f} GB > {avail / 1e9:.1f} GB available ({how})"
        print(f"  {n}²: before {row['before_skipped']}", flush=True)
    for mode, memory in (("before", "unlimited"), ("after", "2G")):
        if mode == "before" and "before_skipped" in row:
            continue
        dest = out / f"fit{n}_{mode}"
        load0 = loadavg()
        r = timed(fit_args(ds, dest, memory, threads), out / f"fit{n}_{mode}.log")
        doc = json.loads((dest / "fit.json").read_text())
        ooc = doc.get("out_of_core")
        r.pop("stdout")
        r.update({"us_per_pixel": r["wall_s"] / pixels * 1e6, "bands": ooc["parts"] if ooc else 1,
                  "part_rows": ooc["part_rows"] if ooc else n, "out_of_core": ooc,
                  "load": f"{load0} → {loadavg()}"})
        runs[mode] = r
        print(f"  {n}² {mode}: peak {gb(r['peak_bytes'])} GB, {r['wall_s']:.1f} s, {r['us_per_pixel']:.1f} µs/px, "
              f"{r['bands']} band(s); load {r['load']}", flush=True)
    row["runs"] = runs
    a = runs["after"]
    if "before" in runs:
        b = runs["before"]
        measured.append((samples, b["peak_bytes"]))
        before_us.append((n, b["us_per_pixel"]))
        row["memory_ratio"] = a["peak_bytes"] / b["peak_bytes"]
        row["time_ratio"] = a["wall_s"] / b["wall_s"]
        row["time_ratio_basis"] = "same size"
        row["maps_equal"], row["maps_max_diff"] = maps_equal(out / f"fit{n}_before", out / f"fit{n}_after")
    else:
        row["memory_ratio"] = None
        if before_us:
            m, us = max(before_us)
            row["time_ratio"] = a["us_per_pixel"] / us
            row["time_ratio_basis"] = f"µs/px vs the {m}² before"
        else:
            row["time_ratio"], row["time_ratio_basis"] = None, "no before measured"
        row["maps_equal"], row["maps_max_diff"] = None, None
    row["load_end"] = loadavg()
    return row


def fit_table(rows: list[dict], threads: int) -> str:
    out = [f"**Fit, `--preset standard --threads {threads}`**, 254 LED images + back light, twill's components "
           "fixed, no cross-validation; before = `--memory unlimited`, after = the default `--memory 2G`; "
           "each a fresh process under `/usr/bin/time -v`.", "",
           "| map | mode | peak GB | wall s | µs/px | bands | memory after/before | time after/before | "
           "maps bit-equal | load (1/5/15 min) start → end |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        n = r["size"]
        b = r["runs"].get("before")
        if b:
            out.append(f"| {n}² | before | {gb(b['peak_bytes'])} | {b['wall_s']:.1f} | {b['us_per_pixel']:.1f} | "
                       f"{b['bands']} | | | | {b['load']} |")
        else:
            out.append(f"| {n}² | before | {r['before_skipped']} | | | | | | | |")
        a = r["runs"]["after"]
        mr = "–" if r["memory_ratio"] is None else f"{r['memory_ratio']:.2f}"
        tr = "–" if r["time_ratio"] is None else f"{r['time_ratio']:.2f}"
        if r["time_ratio_basis"] != "same size":
            tr += f" ({r['time_ratio_basis']})"
        eq = "–" if r["maps_equal"] is None else ("yes" if r["maps_equal"] else f"no (max {r['maps_max_diff']:.3g})")
        out.append(f"| {n}² | after | {gb(a['peak_bytes'])} | {a['wall_s']:.1f} | {a['us_per_pixel']:.1f} | "
                   f"{a['bands']} × {a['part_rows']} rows | {mr} | {tr} | {eq} | {a['load']} |")
    return "\n".join(out)


# --------------------------------------------------------------------------- part 2: tiled (children)

class Counting:
    """A Dask client whose ``submit`` sums the pickled size of each task (function and arguments,
    as tests/fit/test_tiled.py's ``_Counting``)."""

    def __init__(self, client):
        self.client, self.sent = client, []

    def submit(self, fn, *args, **kw):
        import cloudpickle

        self.sent.append(len(cloudpickle.dumps((fn, args))))
        return self.client.submit(fn, *args, **kw)

    def __getattr__(self, name):
        return getattr(self.client, name)


def child_tiled(mode: str, ds: str, out: str, threads: int) -> None:
    """Run in a child process: one tiled fit (module doc); prints one JSON line."""
    import resource
    from contextlib import contextmanager

    counting: list[Counting] = []
    t0 = time.perf_counter()
    if mode == "after":
        import dualscale.fit.api as api
        from dualscale.cli import main as cli_main

        real = api.connect

        @contextmanager
        def counted(spec):
            with real(spec) as client:
                counting.append(Counting(client))
                yield counting[-1]

        api.connect = counted
        rc = cli_main(["fit", ds, "-o", out, "--overwrite", "--preset", TILED_PRESET, "--workers", str(WORKERS),
                       "--tile-px", str(TILE), "--threads", str(threads), "--no-progress", "--no-previews",
                       "--cv-pixels", "0", *COMPONENT_ARGS])
        assert rc == 0, rc
        doc = json.loads((Path(out) / "fit.json").read_text())
        driver_mb = doc["out_of_core"]["peak_rss_mib"]
        tiles = doc["tiled"]["tiles"]
        tile_data = doc["tiled"].get("tile_data")
    else:
        from dataclasses import replace

        from dualscale.engine import EngineSpec, connect
        from dualscale.fit.observations import load_observations
        from dualscale.fit.presets import get_preset
        from dualscale.fit.select import preset_for, select_components
        from dualscale.fit.tiled import fit_tiled
        from dualscale.formats.maps import save_maps
        from dualscale.threads import set_threads

        set_threads(threads)
        obs = replace(load_observations(ds), origin=None)  # the pixels go with each task (as when filed)
        comps, sel = select_components(obs, OVERRIDES, seed=0)
        p = preset_for(get_preset(TILED_PRESET), sel)
        with connect(EngineSpec(workers=WORKERS)) as client:
            counting.append(Counting(client))
            res, info = fit_tiled(obs, p, comps, counting[-1], tile=TILE)
        save_maps(out, res.maps, previews=False, texel_mm=obs.pixel_mm)
        driver_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        tiles, tile_data = info["tiles"], info.get("tile_data")
    sent = [s for c in counting for s in c.sent]
    print("BENCH " + json.dumps({"driver_mb": driver_mb, "self_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                                 "tiles": tiles, "tasks": len(sent), "sent_bytes": sum(sent),
                                 "max_task_bytes": max(sent, default=0), "tile_data": tile_data,
                                 "seconds": time.perf_counter() - t0}), flush=True)


def tiled_row(n: int, ds: Path, out: Path, threads: int) -> dict:
    row: dict = {"size": n, "load_start": loadavg(), "runs": {}}
    warm(ds)
    for mode in ("before", "after"):
        dest = out / f"tiled{n}_{mode}"
        load0 = loadavg()
        r = timed([sys.executable, str(Path(__file__).resolve()), "--child-tiled", mode, str(ds), str(dest),
                   "--threads", str(threads)], out / f"tiled{n}_{mode}.log")
        line = [ln for ln in r.pop("stdout").splitlines() if ln.startswith("BENCH ")][-1]
        r.update(json.loads(line[6:]))
        r["load"] = f"{load0} → {loadavg()}"
        row["runs"][mode] = r
        print(f"  tiled {n}² {mode}: driver peak {r['driver_mb'] / 1e3:.2f} GB, {r['wall_s']:.1f} s, "
              f"{r['tasks']} tasks, {r['sent_bytes'] / 1e6:.2f} MB shipped; load {r['load']}", flush=True)
    b, a = row["runs"]["before"], row["runs"]["after"]
    row["memory_ratio"] = a["driver_mb"] / b["driver_mb"]
    row["shipped_ratio"] = a["sent_bytes"] / b["sent_bytes"] if b["sent_bytes"] else None
    row["maps_equal"], row["maps_max_diff"] = maps_equal(out / f"tiled{n}_before", out / f"tiled{n}_after")
    row["load_end"] = loadavg()
    return row


def tiled_table(rows: list[dict]) -> str:
    out = [f"**Tiled fit, {WORKERS} local workers x 1 thread, {TILE} px tiles, `--preset {TILED_PRESET}`** (to keep "
           "it short); the driver's own peak (`getrusage(RUSAGE_SELF)`; after: `fit.json` `out_of_core.peak_rss_mib`); "
           "shipped = the pickled tasks (function + arguments) the driver submits.  Before = the whole dataset "
           "loaded in the driver, each tile's pixels sent with its task (origin None); after = `dualscale fit "
           f"DATASET --workers {WORKERS} --tile-px {TILE}`, the workers read their own tiles.", "",
           "| map | mode | driver peak GB | wall s | tasks | shipped MB | largest task kB | driver memory "
           "after/before | shipped after/before | maps bit-equal | load start → end |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        n = r["size"]
        for mode in ("before", "after"):
            x = r["runs"][mode]
            extra = "| | | |"
            if mode == "after":
                sr = "–" if r["shipped_ratio"] is None else f"{r['shipped_ratio']:.2g}"
                eq = "yes" if r["maps_equal"] else f"no (max {r['maps_max_diff']:.3g})"
                extra = f"| {r['memory_ratio']:.2f} | {sr} | {eq} |"
            out.append(f"| {n}² | {mode} | {x['driver_mb'] / 1e3:.2f} | {x['wall_s']:.1f} | {x['tasks']} | "
                       f"{x['sent_bytes'] / 1e6:.4g} | {x['max_task_bytes'] / 1e3:.1f} {extra} {x['load']} |")
    return "\n".join(out)


# --------------------------------------------------------------------------- main

def sizes_arg(text: str) -> list[int]:
    return [int(s) for s in text.split(",") if s.strip()]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=sizes_arg, default=[256, 512, 1024], help="map sides of the fit table")
    ap.add_argument("--tiled-sizes", type=sizes_arg, default=[512, 1024], help="map sides of the tiled table")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR, help="datasets (kept) and outputs")
    ap.add_argument("--quick", action="store_true", help="sizes 128,256 only (smoke run)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--child-tiled", nargs=3, metavar=("MODE", "DATASET", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child_tiled:
        child_tiled(*args.child_tiled, threads=args.threads)
        return 0
    if args.quick:
        args.sizes = args.tiled_sizes = [128, 256]
    sys.path.insert(0, str(REPO / "host"))
    work = args.workdir
    out = work / "out"
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    head = {"machine": machine(), "date": datetime.now().isoformat(timespec="seconds"), "commit": commit(),
            "threads": args.threads, "mem_available_bytes": mem_available(), "load_start": loadavg()}
    print(f"machine: {head['machine']}\ndate: {head['date']}, commit {head['commit']}, load {head['load_start']}, "
          f"MemAvailable {head['mem_available_bytes'] / 1e9:.1f} GB", flush=True)
    datasets = {n: dataset(work, n, args.threads) for n in sorted(set(args.sizes) | set(args.tiled_sizes))}
    measured: list[tuple[int, int]] = []
    before_us: list[tuple[int, float]] = []
    fits = [fit_row(n, datasets[n], out, args.threads, measured, before_us) for n in sorted(args.sizes)]
    tiled = [tiled_row(n, datasets[n], out, args.threads) for n in sorted(args.tiled_sizes)]
    head["load_end"], head["total_s"] = loadavg(), time.perf_counter() - t_start
    print()
    print(f"Machine: {head['machine']}; {head['date']}, commit `{head['commit']}`; load {head['load_start']} at "
          f"the start, {head['load_end']} at the end; MemAvailable {head['mem_available_bytes'] / 1e9:.1f} GB; "
          f"total {head['total_s'] / 60:.1f} min.")
    print()
    print(fit_table(fits, args.threads))
    for r in fits:
        if "before_skipped" in r:
            print(f"\n{r['size']}²: before {r['before_skipped']}.")
    print()
    print(tiled_table(tiled))
    if args.json:
        args.json.write_text(json.dumps({**head, "fit": fits, "tiled": tiled}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
