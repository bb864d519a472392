"""Scale-out of the micro fit on Dask (issue 16 §4): the tiled fit on 1 and 2 local workers
against the single-process fit in the same run, Dask's per-task overhead, the tile side that
amortises it, and the extrapolation to a 4096² micro map and a 500-material library on 8, 64 and
512 cores; prints markdown tables for docs/SCALE.md.

    PYTHONPATH=host python bench/bench_scale.py [--quick] [--size 128] [--lights mod2]
        [--tile 32] [--tiles 16,32,64,128] [--workers 1,2] [--threads 1,2] [--repeats 3]
        [--noop-tasks 2000] [--json out.json]

The dataset is ``dualscale synth twill --size SIZE --dataset --lights LIGHTS`` (renderer radiance,
synth's default 1.8 um texels), loaded with ``load_observations``; the
components are fixed (opaque, anisotropic, tinted: twill's) so that selection stays out of the
timings (it is timed apart, as a driver cost); preset ``standard`` (fused kernel); no held-out
lights.  Every time is the median of ``--repeats`` runs unless a table says otherwise.

- **In-process**: ``fit_observations`` on the whole map at each ``--threads`` count (the
  baseline: 1 thread); and the same function on square crops of 8..64 px (1 thread), whose
  times give the fit's fixed cost per call and its marginal cost per pixel, and on a crop with
  half the LEDs (the cost per image).
- **Tiled**: per ``--workers`` count, a fresh ``LocalCluster`` (1 thread per worker): its start,
  a small tile on each worker *cold* (the worker imports dualscale and numba loads the fused
  kernels from its on-disk cache: the counts are printed) and again *warm*, then the tiled fit
  of the whole map at ``--tile``; its maps are compared with the single-process maps bit for
  bit.  At the largest worker count: a batch of no-op tasks (scheduler throughput), one no-op
  task at a time (round trip), tasks carrying a tile's payload (``K x tile² x 3`` float32 in,
  ``tile² x C`` float32 out, C = the map channels), and the tiled fit at every ``--tiles`` side.
- **Extrapolation**: from the measured costs (module ``extrapolate``; the assumptions are printed
  with the table).

``--quick`` (about 1.5 min here): a 64² map, tiles 16,32,64, 500 no-op tasks.  ``make bench``
runs it with no arguments (4 min on the shared 2-core VM at load 1-2).  The in-process synth
command sets the thread count globally; the script sets it back after it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import tempfile
import time
import warnings
from datetime import datetime
from pathlib import Path

import torch

#: the material, and its components (opaque, anisotropic, tinted: what selection finds for twill)
MATERIAL = "twill"
#: LED images of a full micro capture: 127 LEDs x P0/P90 (spec Sec. 3; the back light apart)
FULL_LED_IMAGES = 254
#: the cores of the extrapolation
CORES = (8, 64, 512)
#: the micro map of the extrapolation
BIG = 4096
#: the library of the extrapolation
LIBRARY = 500
#: Dask's documented per-task overhead: "somewhere between 200us and 1ms" (Dask Best Practices,
#: "Avoid Very Large Graphs"); distributed's docs: "each task suffers about 1ms of overhead"
DASK_DOC_OVERHEAD_S = (200e-6, 1e-3)
#: per-material stage times of `digitize --quality standard` on a 128² synthetic twill, one
#: thread (docs/DIGITIZE.md, the demo's digitize stages: calibrate, fit, flyouts, propagate,
#: export, report)
DIGITIZE_STAGES_S = (1.3, 23.1, 0.2, 44.7, 0.5, 7.3)
#: a worker's first task pays its imports (docs/BATCH.md: 2.5 s, of which the stage 0.13 s)
WORKER_FIRST_TASK_S = 2.4
#: the network the extrapolation assumes for the driver and the storage (bytes/s): 10 GbE
NETWORK_BPS = 1.25e9
#: the shared storage's read rate the extrapolation assumes (a 10 Gb/s file server)
STORAGE_BPS = NETWORK_BPS


# --------------------------------------------------------------------------- measuring helpers

def load() -> str:
    return " ".join(open("/proc/loadavg").read().split()[:3])


def machine() -> str:
    model = platform.processor() or platform.machine()
    try:
        for line in subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout.splitlines():
            if line.startswith("Model name:"):
                model = line.split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{model}, {os.cpu_count()} cores ({usable} usable), {platform.node()}"


def median_time(fn, repeats: int) -> tuple[float, list[float], object]:
    """``(median seconds, all seconds, the first result)`` of ``repeats`` calls of ``fn()``."""
    times, first = [], None
    for i in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
        if i == 0:
            first = out
    return statistics.median(times), times, first


def own(obs):
    """A crop with storage of its own (pickling a view ships the whole map's images)."""
    from dataclasses import replace

    def c(t):
        return None if t is None else t.clone()

    return replace(obs, images=c(obs.images), backlight=c(obs.backlight), valid=c(obs.valid),
                   back_valid=c(obs.back_valid), view=c(obs.view))


def same_maps(a, b) -> tuple[bool, float]:
    """``(bit for bit equal, max |difference|)`` of two MaterialMaps."""
    equal, worst = True, 0.0
    for (k, v), (k2, w) in zip(a.items(), b.items(), strict=True):
        assert k == k2
        if not torch.equal(v, w):
            equal = False
            worst = max(worst, float((v - w).abs().max()))
    return equal, worst


# --------------------------------------------------------------------------- Dask tasks

def noop(i):
    return i


def payload_task(images: torch.Tensor, channels: int) -> torch.Tensor:
    """A tile's data movement without its fit: ``(K, n, 3)`` float32 in, ``(n, channels)`` out."""
    return torch.zeros(images.shape[1], channels, dtype=torch.float32)


def probe(obs, preset, comps) -> dict:
    """``fit_tile`` on a small tile, timed inside the worker, with numba's cache statistics of
    the fused kernels (functions loaded from the on-disk cache, functions compiled)."""
    t0 = time.perf_counter()
    import numba

    from dualscale.fit import fused
    from dualscale.fit.tiled import fit_tile

    t1 = time.perf_counter()
    fit_tile(obs, preset, comps, None, 0, 1)
    t2 = time.perf_counter()
    ds = [v for v in vars(fused).values() if isinstance(v, numba.core.registry.CPUDispatcher)]
    return {"pid": os.getpid(), "import_s": t1 - t0, "fit_s": t2 - t1,
            "cache_hits": sum(sum(d.stats.cache_hits.values()) for d in ds),
            "compiled": sum(sum(d.stats.cache_misses.values()) for d in ds)}


# --------------------------------------------------------------------------- the run

def make_dataset(root: Path, size: int, lights: str):
    from dualscale.cli import main as cli_main
    from dualscale.fit.observations import load_observations
    from dualscale.threads import set_threads

    threads = torch.get_num_threads()
    t0 = time.perf_counter()
    rc = cli_main(["synth", MATERIAL, "-o", str(root), "--size", str(size), "--dataset", "--lights", lights,
                   "--no-previews", "--no-progress", "--threads", "1"])
    assert rc == 0
    t_synth = time.perf_counter() - t0
    set_threads(threads)  # the in-process command applied its own count
    files = sorted((root / "micro" / "images").glob("*.exr"))
    t0 = time.perf_counter()
    obs = load_observations(root / "micro")
    t_load = time.perf_counter() - t0
    return obs, {"synth_s": t_synth, "load_s": t_load, "exr_files": len(files),
                 "exr_bytes": sum(p.stat().st_size for p in files)}


def in_process(obs, preset, comps, threads: list[int], repeats: int, crops: list[int]) -> dict:
    from dualscale.fit.core import fit_losses, fit_observations
    from dualscale.fit.init import check_albedo_range, photometric_stereo
    from dualscale.fit.select import select_components
    from dualscale.threads import set_threads

    set_threads(1)
    fit_observations(obs.crop(0, 8, 0, 8), preset, comps)  # numba cache, thread pools, allocator
    out: dict = {"whole": {}}
    ref = None
    for n in threads:
        set_threads(n)
        med, times, res = median_time(lambda: fit_observations(obs, preset, comps), repeats)
        if ref is None:
            ref = res
        eq, diff = same_maps(ref.maps, res.maps)
        out["whole"][n] = {"median_s": med, "times_s": times, "equal_to_first": eq, "max_diff": diff,
                           "load": load()}
        print(f"  in-process, {n} thread(s): {med:.2f} s (runs {', '.join(f'{t:.2f}' for t in times)}); "
              f"load {load()}", flush=True)
    set_threads(1)
    h, w = obs.shape
    crop_rows = []
    for t in crops:
        t = min(t, h, w)
        y0, x0 = (h - t) // 2, (w - t) // 2
        c = obs.crop(y0, y0 + t, x0, x0 + t)
        med, times, _ = median_time(lambda: fit_observations(c, preset, comps), max(3, repeats))
        crop_rows.append({"side": t, "median_s": med})
    # fixed cost per call a and marginal cost per pixel b: least squares of t = a + b n over the crops
    ns = [r["side"] ** 2 for r in crop_rows]
    ts = [r["median_s"] for r in crop_rows]
    nm, tm = statistics.fmean(ns), statistics.fmean(ts)
    b = sum((x - nm) * (y - tm) for x, y in zip(ns, ts)) / sum((x - nm) ** 2 for x in ns)
    a = tm - b * nm
    # cost per LED image: the largest crop with half the LEDs
    side = crop_rows[-1]["side"]
    y0, x0 = (h - side) // 2, (w - side) // 2
    ids = sorted(set(obs.led_ids.tolist()))
    half = obs.select_leds(set(ids[::2])).crop(y0, y0 + side, x0, x0 + side)
    t_half, _, _ = median_time(lambda: fit_observations(half, preset, comps), max(3, repeats))
    b_half = (t_half - a) / side ** 2
    # the driver's whole-map work in a tiled fit (fit_tiled): the albedo check, the report's losses;
    # and component selection (fit_dataset, once, on a sample of pixels)
    t_ps, _, _ = median_time(lambda: check_albedo_range(obs, photometric_stereo(obs)[1]), repeats)
    t_loss, _, _ = median_time(lambda: fit_losses(ref.maps, comps, obs), repeats)
    t0 = time.perf_counter()
    select_components(obs)
    t_sel = time.perf_counter() - t0
    out.update({"crops": crop_rows, "fixed_s": a, "per_pixel_s": b, "images": obs.n, "half_images": half.n,
                "per_pixel_half_s": b_half, "driver_albedo_check_s": t_ps, "driver_losses_s": t_loss,
                "selection_s": t_sel, "channels": sum(v.shape[-1] for _, v in ref.maps.items()),
                "load_end": load()})
    print(f"  crops: fixed {1e3 * a:.1f} ms per call, {1e3 * b:.3f} ms per pixel ({obs.n} images), "
          f"{1e3 * b_half:.3f} ms ({half.n} images); driver: albedo check {t_ps:.2f} s, losses {t_loss:.2f} s, "
          f"selection {t_sel:.1f} s; load {load()}", flush=True)
    return out, ref


#: the variable Dask's nannies set in every worker process (``distributed.nanny.pre-spawn-environ``)
TRIM = "MALLOC_TRIM_THRESHOLD_"


def tiled(obs, preset, comps, ref, workers: int, tile: int, repeats: int, sweep: list[int] | None,
          noop_tasks: int, channels: int, unset_trim: bool = False) -> dict:
    """One fresh local cluster of ``workers`` (``dualscale.engine.connect``, as ``dualscale fit
    --workers`` opens it); ``unset_trim``: without Dask's ``MALLOC_TRIM_THRESHOLD_`` in the
    workers' environment (a config value of None unsets it)."""
    out: dict = {"workers": workers, "load_start": load(), "unset_trim": unset_trim}
    cfg = {f"distributed.nanny.pre-spawn-environ.{TRIM}": None} if unset_trim else {}
    # a local cluster's nannies live in this process and copy their pre-spawn environment into
    # os.environ before spawning a worker, so an earlier cluster's value would be inherited
    import dualscale.engine as engine

    saved, saved_user = os.environ.get(TRIM), engine._USER_MALLOC_TRIM
    if unset_trim:
        os.environ.pop(TRIM, None)
    else:  # Dask's default, as a user who sets it gets it (engine.connect unsets it otherwise)
        os.environ[TRIM] = engine._USER_MALLOC_TRIM = "65536"
    try:
        return _tiled(out, cfg, obs, preset, comps, ref, workers, tile, repeats, sweep, noop_tasks, channels,
                      unset_trim)
    finally:
        engine._USER_MALLOC_TRIM = saved_user
        if saved is None:
            os.environ.pop(TRIM, None)
        else:
            os.environ[TRIM] = saved


def _tiled(out, cfg, obs, preset, comps, ref, workers, tile, repeats, sweep, noop_tasks, channels,
           unset_trim) -> dict:
    import dask
    from distributed import as_completed

    from dualscale.engine import EngineSpec, connect
    from dualscale.fit.tiled import fit_tiled

    t0 = time.perf_counter()
    with dask.config.set(cfg), connect(EngineSpec(workers=workers)) as client:
        client.wait_for_workers(workers)
        out["start_s"] = time.perf_counter() - t0
        out["worker_trim"] = sorted(set(map(str, client.run(lambda: os.environ.get(TRIM)).values())))
        addrs = sorted(client.scheduler_info(n_workers=-1)["workers"])
        small = own(obs.crop(0, 8, 0, 8))

        def probe_all() -> tuple[float, list[dict]]:
            t = time.perf_counter()
            futs = [client.submit(probe, small, preset, comps, workers=[a], allow_other_workers=False, pure=False)
                    for a in addrs]
            recs = client.gather(futs)
            return time.perf_counter() - t, recs

        out["cold_s"], out["cold"] = probe_all()
        out["warm_s"], out["warm"] = probe_all()
        side = min(tile, *obs.shape)
        y0, x0 = (obs.shape[0] - side) // 2, (obs.shape[1] - side) // 2
        one = own(obs.crop(y0, y0 + side, x0, x0 + side))
        tile_fits = [client.submit(probe, one, preset, comps, workers=[addrs[0]], allow_other_workers=False,
                                   pure=False).result()["fit_s"] for _ in range(max(5, repeats))]
        out["tile_in_worker_s"] = statistics.median(tile_fits)
        out["tile_side"] = side
        # the same tile in this process right now (the machine's load drifts between phases)
        from dualscale.fit.core import fit_observations

        out["tile_here_s"], _, _ = median_time(lambda: fit_observations(one, preset, comps), max(3, repeats))
        c = out["cold"]
        print(f"  {workers} worker(s){' (' + TRIM + ' unset)' if unset_trim else ''}: cluster start "
              f"{out['start_s']:.2f} s, small tile cold {out['cold_s']:.2f} s (in the task: fit "
              f"{max(r['fit_s'] for r in c):.2f} s; numba: {c[0]['cache_hits']} kernels from the cache, "
              f"{c[0]['compiled']} compiled), warm {out['warm_s']:.2f} s; a {side} px tile in a worker "
              f"{out['tile_in_worker_s']:.3f} s (in-process {out['tile_here_s']:.3f} s)"
              + f"; workers' {TRIM}: {', '.join(out['worker_trim'])}", flush=True)

        def run(t):
            res, info = fit_tiled(obs, preset, comps, client, tile=t)
            return res, info

        med, times, (res, info) = median_time(lambda: run(tile), repeats)
        eq, diff = same_maps(ref.maps, res.maps)
        out.update({"tile": tile, "tiles": info["tiles"], "median_s": med, "times_s": times, "equal": eq,
                    "max_diff": diff})
        print(f"  {workers} worker(s), tile {tile}: {med:.2f} s (runs {', '.join(f'{t:.2f}' for t in times)}), "
              f"{info['tiles']} tiles, bit-identical to one process: {'yes' if eq else f'NO (max {diff:.3g})'}; "
              f"load {load()}", flush=True)
        if sweep:
            rows = []
            for t in sweep:
                m, ts, (r, inf) = median_time(lambda: run(t), repeats)
                e, d = same_maps(ref.maps, r.maps)
                rows.append({"tile": t, "tiles": inf["tiles"], "median_s": m, "times_s": ts, "equal": e,
                             "max_diff": d, "load": load()})
                print(f"    tile {t:4d}: {m:.2f} s, {inf['tiles']} tiles, identical {e}; load {load()}", flush=True)
            out["sweep"] = rows
            # scheduler throughput: many no-op tasks at once; round trip: one at a time
            client.gather(client.map(noop, range(50), pure=False))
            t = time.perf_counter()
            client.gather(client.map(noop, range(noop_tasks), pure=False))
            out["noop_batch_s_per_task"] = (time.perf_counter() - t) / noop_tasks
            n_rt = max(20, noop_tasks // 20)
            t = time.perf_counter()
            for i in range(n_rt):
                client.submit(noop, i, pure=False).result()
            out["noop_roundtrip_s"] = (time.perf_counter() - t) / n_rt
            # a tile's payload, as fit_tiled ships it: at most 2 per worker in flight
            pay = []
            for t in sweep:
                nbytes = obs.n * t * t * 3 * 4
                count = max(4 * workers, min(100, int(1.5e9 / nbytes)))
                x = torch.rand(obs.n, t * t, 3)
                client.gather(client.submit(payload_task, x, channels, pure=False))
                t1 = time.perf_counter()
                for _ in range(min(10, count)):
                    client.submit(payload_task, x, channels, pure=False).result()
                rt = (time.perf_counter() - t1) / min(10, count)
                t1 = time.perf_counter()
                limit = 2 * workers
                futs = [client.submit(payload_task, x, channels, pure=False) for _ in range(min(limit, count))]
                left = count - len(futs)
                pending = as_completed(futs)
                for f in pending:
                    f.result()
                    f.release()
                    if left:
                        left -= 1
                        pending.add(client.submit(payload_task, x, channels, pure=False))
                thr = (time.perf_counter() - t1) / count
                pay.append({"tile": t, "in_bytes": nbytes, "out_bytes": t * t * channels * 4, "tasks": count,
                            "roundtrip_s": rt, "throughput_s_per_task": thr})
                print(f"    payload {t:4d} px ({nbytes / 1e6:.2f} MB in): round trip {1e3 * rt:.1f} ms, "
                      f"{1e3 * thr:.1f} ms per task with {limit} in flight", flush=True)
            out["payload"] = pay
            print(f"    no-op: {1e3 * out['noop_batch_s_per_task']:.2f} ms per task in a batch of {noop_tasks}, "
                  f"round trip {1e3 * out['noop_roundtrip_s']:.2f} ms; load {load()}", flush=True)
    out["load_end"] = load()
    return out


# --------------------------------------------------------------------------- extrapolation

def extrapolate(rep: dict, tile: int = 128) -> dict:
    """The 4096² fit and the 500-material library on 8, 64 and 512 cores, from the measured
    costs (one worker per core, 1 thread).  Returns the rows and the assumptions used."""
    ip = rep["in_process"]
    k_meas, k_half = ip["images"], ip["half_images"]
    b_meas, b_half = ip["per_pixel_s"], ip["per_pixel_half_s"]
    per_image = (b_meas - b_half) / (k_meas - k_half)  # marginal cost per pixel per LED image
    b_full = b_meas + per_image * (FULL_LED_IMAGES - k_meas)
    a = ip["fixed_s"]
    big = next(t for t in rep["tiled"] if "sweep" in t)
    pay = {p["tile"]: p for p in big.get("payload", [])}
    # per-task overhead: the measured round trip of a tile's payload, scaled by bytes to the full
    # light set and this tile side (the largest measured payload's rate), or the no-op round trip
    if pay:
        p = max(pay.values(), key=lambda r: r["in_bytes"])
        rate = p["in_bytes"] / max(p["roundtrip_s"] - big["noop_roundtrip_s"], 1e-9)  # bytes/s through Dask here
    else:
        rate = float("inf")
    in_bytes = FULL_LED_IMAGES * tile * tile * 3 * 4
    o = big["noop_roundtrip_s"] + in_bytes / rate
    sched_rate = 1.0 / big["noop_batch_s_per_task"]  # tasks/s the scheduler sustained here
    px = BIG * BIG
    n_tiles = math.ceil(BIG / tile) ** 2
    t_tile = a + b_full * tile * tile
    exr_half = FULL_LED_IMAGES * px * 3 * 2
    f32 = FULL_LED_IMAGES * px * 3 * 4
    meas_bpp = rep["dataset"]["exr_bytes"] / (rep["dataset"]["exr_files"] * rep["size"] ** 2)  # per pixel & image
    exr_meas = meas_bpp * (FULL_LED_IMAGES + 2) * px
    decode_bps = rep["dataset"]["exr_bytes"] / rep["dataset"]["load_s"]  # one process, decoding + float32
    # issue 25: the workers read their own tiles (a tile's EXR bytes at one worker's decode rate, no
    # shipping), and the survey and the gather are band tasks on the workers, each a read of the
    # dataset plus the survey's per-pixel work (the albedo check's photometric stereo); the driver
    # keeps the selection and writes the maps by rows
    tile_read = meas_bpp * (FULL_LED_IMAGES + 2) * tile * tile / decode_bps
    o = big["noop_roundtrip_s"] + tile_read
    from dualscale.fit.stream import DEFAULT_MEMORY, band_boxes

    n_bands = len(band_boxes((BIG, BIG), FULL_LED_IMAGES, DEFAULT_MEMORY))
    maps_bytes = px * ip["channels"] * 4
    serial = ip["selection_s"] * (FULL_LED_IMAGES / k_meas) + maps_bytes / decode_bps  # selection; the maps' rows
    read = exr_meas / decode_bps  # one pass by one process
    fit_rows = []
    for n in CORES:
        waves = math.ceil(n_tiles / n)
        compute = waves * (t_tile + o)
        sched = (n_tiles + 2 * n_bands) / sched_rate
        passes = 2 * max(read / n, exr_meas / STORAGE_BPS)  # survey + gather on the workers: reads
        storage = exr_meas / STORAGE_BPS  # the tiles' own reads, at the storage's rate
        wall = passes + serial + max(compute, sched, storage)
        fit_rows.append({"cores": n, "tiles": n_tiles, "waves": waves, "compute_s": compute, "scheduler_s": sched,
                         "passes_s": passes, "storage_s": storage, "read_s": read, "serial_s": serial,
                         "wall_s": wall, "storage_bps_to_keep_up": exr_meas / compute,
                         "overhead_fraction": o / (t_tile + o)})
    one_core = n_tiles * (t_tile + o)
    stages = sum(DIGITIZE_STAGES_S)
    lib_rows = []
    for n in CORES:
        small = math.ceil(LIBRARY / n) * (stages + 6 * o) + WORKER_FIRST_TASK_S
        # a full-size sample: its fit as one task chain on one worker (b_full x 4096²) plus the other
        # stages as measured; the library as many tiles as there are cores can take
        full_fit_core_s = px * b_full + n_tiles * a
        work = LIBRARY * (full_fit_core_s + stages - DIGITIZE_STAGES_S[1]) / n + WORKER_FIRST_TASK_S
        reads = LIBRARY * 3 * exr_meas / STORAGE_BPS  # each material's survey, gather and tiles read its dataset
        full = max(work, reads)
        lib_rows.append({"cores": n, "small_s": small, "full_s": full, "work_s": work, "storage_s": reads,
                         "tasks": LIBRARY * 6, "scheduler_s": LIBRARY * 6 / sched_rate,
                         "full_storage_bps": LIBRARY * 3 * exr_meas / work})
    default = [t for t in rep["tiled"] if not t["unset_trim"] and t["worker_trim"] != ["None"]]
    factors = [t["tile_in_worker_s"] / t["tile_here_s"] for t in default]
    return {"tile": tile, "per_pixel_full_s": b_full, "worker_env_factor": statistics.median(factors) if factors else None, "per_image_s": per_image, "fixed_s": a, "task_overhead_s": o,
            "dask_bytes_per_s": rate, "scheduler_tasks_per_s": sched_rate, "tile_in_bytes": in_bytes,
            "tile_out_bytes": tile * tile * ip["channels"] * 4, "t_tile_s": t_tile, "one_core_s": one_core,
            "exr_half_bytes": exr_half, "float32_bytes": f32, "exr_measured_bytes": exr_meas,
            "exr_bytes_per_px_image": meas_bpp, "decode_bps": decode_bps, "serial_s": serial, "read_s": read,
            "bands": n_bands, "tile_read_s": tile_read, "fit": fit_rows, "library": lib_rows, "material_s": stages}


def hms(s: float) -> str:
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    if s < 172800:
        return f"{s / 3600:.1f} h"
    return f"{s / 86400:.1f} d"


# --------------------------------------------------------------------------- tables

def tables(rep: dict) -> str:
    ip = rep["in_process"]
    base = next(iter(ip["whole"].values()))["median_s"]  # the first --threads count
    out = [f"Date {rep['date']}; machine: {rep['machine']}; Python {rep['python']}, dask {rep['dask']}; "
           f"load average (1/5/15 min) at the start {rep['load_start']}, at the end {rep['load_end']}. "
           f"Dataset: `dualscale synth {MATERIAL} --size {rep['size']} --dataset --lights {rep['lights']}` "
           f"({ip['images']} LED images + back light, {rep['dataset']['exr_bytes'] / 1e6:.1f} MB of EXR, "
           f"loaded in {rep['dataset']['load_s']:.2f} s); preset standard (fused kernel), components fixed "
           f"(opaque, anisotropic, tinted), no held-out lights; medians of {rep['repeats']} runs.", "",
           "**Speed-up** (baseline: the single-process fit at 1 thread, same run):", "",
           "| run | cluster start [s] | fit [s] | speed-up | bit-identical to 1 process | runs [s] | load at the end |",
           "|---|---:|---:|---:|---|---|---|"]
    for n, r in ip["whole"].items():
        n = int(n)  # a key read back from --json is text
        out.append(f"| in-process, {n} thread{'s' if n > 1 else ''} | - | {r['median_s']:.2f} | "
                   f"{base / r['median_s']:.2f} | {'yes' if r['equal_to_first'] else 'no (%.2g)' % r['max_diff']} | "
                   f"{', '.join(f'{t:.2f}' for t in r['times_s'])} | {r['load']} |")
    for t in rep["tiled"]:
        out.append(f"| tiled, {t['workers']} worker{'s' if t['workers'] > 1 else ''} x 1 thread, {t['tiles']} tiles "
                   f"of {t['tile']} px{', ' + TRIM + ' unset' if t['unset_trim'] else ''} | {t['start_s']:.2f} | {t['median_s']:.2f} | {base / t['median_s']:.2f} | "
                   f"{'yes' if t['equal'] else 'NO (%.2g)' % t['max_diff']} | "
                   f"{', '.join(f'{x:.2f}' for x in t['times_s'])} | {t['load_end']} |")
    out += ["", "**Cold and warm workers** (an 8x8 tile pinned to each worker right after the cluster started, "
            "then again: wall time of the batch, and inside the slowest task; the cold batch's time outside the "
            "task is the unpickling of the arguments, which imports dualscale and torch in the fresh worker), and "
            f"one tile of the speed-up runs' side fitted inside a worker (median of 5) against the same crop in this "
            "process right after (median of 3) "
            f"(workers' `{TRIM}`: Dask's nannies set it to 65536 by default; the driver's: "
            f"{rep.get('driver_trim')}):", "",
            f"| workers | {TRIM} in the workers | cold [s] | cold fit in task [s] | kernels from numba's cache | "
            "compiled | warm [s] | warm fit in task [s] | tile in a worker [s] | same tile in-process [s] | ratio |",
            "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for t in rep["tiled"]:
        c, w = t["cold"], t["warm"]
        ip_t = t.get("tile_here_s")
        out.append(f"| {t['workers']} | {', '.join(t['worker_trim'])} | {t['cold_s']:.2f} | "
                   f"{max(r['fit_s'] for r in c):.2f} | {c[0]['cache_hits']} | {c[0]['compiled']} | "
                   f"{t['warm_s']:.3f} | {max(r['fit_s'] for r in w):.3f} | {t['tile_in_worker_s']:.3f} | "
                   + (f"{ip_t:.3f} | {t['tile_in_worker_s'] / ip_t:.2f} |" if ip_t else "- | - |"))
    big = next((t for t in rep["tiled"] if "sweep" in t), {})
    if big:
        ex = rep["extrapolation"]
        out += ["", f"**Per-task overhead** ({big['workers']} workers): no-op tasks, and tasks carrying a tile's "
                f"payload ({ip['images']} images x tile² x 3 float32 in, tile² x {ip['channels']} float32 out), "
                "the way fit_tiled submits them (at most 2 per worker in flight):", "",
                "| task | in | out | round trip, 1 at a time [ms] | per task in a stream [ms] | tasks |",
                "|---|---:|---:|---:|---:|---:|",
                f"| no-op | - | - | {1e3 * big['noop_roundtrip_s']:.2f} | {1e3 * big['noop_batch_s_per_task']:.2f} "
                f"(all at once: {1 / big['noop_batch_s_per_task']:.0f} tasks/s) | {rep['noop_tasks']} |"]
        for p in big["payload"]:
            out.append(f"| tile {p['tile']} px | {p['in_bytes'] / 1e6:.2f} MB | {p['out_bytes'] / 1e3:.0f} kB | "
                       f"{1e3 * p['roundtrip_s']:.1f} | {1e3 * p['throughput_s_per_task']:.1f} | {p['tasks']} |")
        a, b = ip["fixed_s"], ip["per_pixel_s"]
        out += ["", f"**Tile side** ({big['workers']} workers x 1 thread, the whole {rep['size']}² map). The "
                f"in-process fit of a tile costs {1e3 * a:.1f} ms per call + {1e3 * b:.3f} ms per pixel "
                f"(least squares over crops of {', '.join(str(c['side']) for c in ip['crops'])} px at 1 thread: "
                + ", ".join(f"{c['side']} px {c['median_s']:.3f} s" for c in ip["crops"]) + "). Efficiency = "
                "1-thread in-process time / (workers x wall); a tile's overhead = the fit's fixed cost per call + "
                "the Dask round trip of its payload (above), as a share of the tile's whole time (fixed + pixels + "
                "round trip):", "",
                "| tile [px] | tiles | wall [s] | speed-up vs 1 thread | efficiency | tile's fit [s] | "
                "Dask round trip [ms] | overhead share | bit-identical | load |",
                "|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"]
        pay = {p["tile"]: p for p in big["payload"]}
        for r in big["sweep"]:
            fit_t = a + b * r["tile"] ** 2
            rt = pay[r["tile"]]["roundtrip_s"] if r["tile"] in pay else float("nan")
            out.append(f"| {r['tile']} | {r['tiles']} | {r['median_s']:.2f} | {base / r['median_s']:.2f} | "
                       f"{base / (big['workers'] * r['median_s']):.2f} | {fit_t:.3f} | {1e3 * rt:.1f} | "
                       f"{100 * (a + rt) / (fit_t + rt):.1f} % | {'yes' if r['equal'] else 'NO'} | {r['load']} |")
        out += ["", f"Driver work on the whole map (1 thread, {rep['size']}²): the albedo check "
                f"{ip['driver_albedo_check_s']:.2f} s, the report's losses {ip['driver_losses_s']:.2f} s; "
                f"component selection (a sample of pixels, not in the timings above) {ip['selection_s']:.1f} s. "
                f"Cost per pixel and LED image {1e6 * ex['per_image_s']:.2f} us "
                f"({1e3 * ip['per_pixel_s']:.3f} ms/pixel at {ip['images']} images, "
                f"{1e3 * ip['per_pixel_half_s']:.3f} at {ip['half_images']}).", ""]
        out += extrapolation_tables(rep)
    return "\n".join(out)


def extrapolation_tables(rep: dict) -> list[str]:
    ex = rep["extrapolation"]
    gb = 1e9
    out = [f"**Extrapolation: a {BIG}² micro map** ({FULL_LED_IMAGES} LED images, tiles of {ex['tile']} px, one "
           "worker per core x 1 thread). Measured here: per-pixel cost "
           f"{1e3 * ex['per_pixel_full_s']:.3f} ms at {FULL_LED_IMAGES} images (linear in the images from the two "
           f"light sets), {1e3 * ex['fixed_s']:.0f} ms per call, so {ex['t_tile_s']:.1f} s per tile; per-task "
           f"overhead {1e3 * ex['task_overhead_s']:.0f} ms (no-op round trip + the worker's read of its tile, "
           f"{ex['tile_read_s']:.2f} s at one process's decode rate); "
           f"scheduler {ex['scheduler_tasks_per_s']:.0f} tasks/s (Dask's docs: 200 us to 1 ms per task). "
           + (f"The tile fits assume workers without Dask's `{TRIM}` (with it they took "
              f"x{ex['worker_env_factor']:.2f} here). " if ex.get("worker_env_factor") else "")
           + f"The design since issue 25: the driver holds no pixel (the float32 dataset would be "
           f"{ex['float32_bytes'] / gb:.0f} GB); the workers read their own tiles from shared storage, and run the "
           f"survey and the gather as {ex['bands']} band tasks each (two reads of the dataset: their sums and "
           "sample pixels cost little beside the decoding); the EXR dataset is "
           f"{ex['exr_measured_bytes'] / gb:.0f} GB at this synthetic dataset's "
           f"{ex['exr_bytes_per_px_image']:.1f} bytes per pixel and image (half float, uncompressed: "
           f"{ex['exr_half_bytes'] / gb:.0f} GB), decoded at the {ex['decode_bps'] / 1e6:.0f} MB/s one process "
           f"reached here (page cache, 1 thread), every pass and the tiles' reads capped by a shared storage of "
           f"{STORAGE_BPS * 8 / 1e9:.0f} Gb/s (assumed); the driver's serial work (selection, the maps written by "
           f"rows at the same rate): {hms(ex['serial_s'])}. One core: {hms(ex['one_core_s'])} of tile fits.", "",
           "| cores | tiles | waves | tile fits | scheduler bound | survey + gather (workers) | tiles' reads at the "
           "storage's rate | driver serial | **wall** | storage to keep up |",
           "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in ex["fit"]:
        out.append(f"| {r['cores']} | {r['tiles']} | {r['waves']} | {hms(r['compute_s'])} | {hms(r['scheduler_s'])} | "
                   f"{hms(r['passes_s'])} | {hms(r['storage_s'])} | {hms(r['serial_s'])} | **{hms(r['wall_s'])}** | "
                   f"{r['storage_bps_to_keep_up'] / 1e6:.0f} MB/s |")
    out += ["", f"**Extrapolation: a library of {LIBRARY} materials** (`dualscale batch`: one material per worker, "
            f"six stage tasks each). Small samples: the stages of a {sum(DIGITIZE_STAGES_S):.0f} s `digitize "
            f"--quality standard` of a 128² twill at 1 thread (docs/DIGITIZE.md: calibrate, fit, flyouts, "
            f"propagate, export, report = {', '.join(f'{s:g}' for s in DIGITIZE_STAGES_S)} s), a worker's first "
            f"task {WORKER_FIRST_TASK_S:g} s of imports (docs/BATCH.md). Full-size samples: the same stages but a "
            f"{BIG}² fit ({hms(ex['one_core_s'])} on one core, above); the library's fits are spread over the "
            "cores (tiled, or one material per core: the same total when materials >= cores).", "",
            f"Full-size samples read their dataset three times each (survey, gather, tiles): at the assumed "
            f"{STORAGE_BPS * 8 / 1e9:.0f} Gb/s that is a floor on the wall.", "",
            "| cores | small samples | full-size samples: work | full-size: storage floor | **full-size wall** | "
            "stage tasks | scheduler time for them | storage read rate to keep up (full-size) |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in ex["library"]:
        out.append(f"| {r['cores']} | {hms(r['small_s'])} | {hms(r['work_s'])} | {hms(r['storage_s'])} | "
                   f"**{hms(r['full_s'])}** | {r['tasks']} | {r['scheduler_s']:.1f} s | "
                   f"{r['full_storage_bps'] / 1e6:.0f} MB/s |")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a 64² map, tiles 16,32,64, 500 no-op tasks (~2 min)")
    ap.add_argument("--size", type=int, default=None, help="map side in texels (default 128; --quick 64)")
    ap.add_argument("--lights", default="mod2", help="the synth light set (default mod2: 64 LEDs x P0/P90)")
    ap.add_argument("--tile", type=int, default=32, help="tile side of the speed-up runs (default 32)")
    ap.add_argument("--tiles", default=None, help="tile sides of the sweep at the largest worker count "
                                                  "(default 16,32,64,128; --quick 16,32,64)")
    ap.add_argument("--workers", default="1,2", help="local worker counts (default 1,2)")
    ap.add_argument("--threads", default="1,2", help="in-process thread counts; the first is the baseline")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--noop-tasks", type=int, default=None, help="no-op tasks in the batch (default 2000; --quick 500)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    size = a.size or (64 if a.quick else 128)
    sweep = [int(s) for s in (a.tiles or ("16,32,64" if a.quick else "16,32,64,128")).split(",")]
    noop_tasks = a.noop_tasks or (500 if a.quick else 2000)
    workers = [int(s) for s in a.workers.split(",")]
    threads = [int(s) for s in a.threads.split(",")]

    import dask

    from dualscale.fit.params import fit_components
    from dualscale.fit.presets import get_preset
    from dualscale.threads import set_threads

    warnings.filterwarnings("ignore", message=r".*Sending large graph.*")
    rep = {"date": datetime.now().strftime("%Y-%m-%d %H:%M"), "machine": machine(), "python": platform.python_version(),
           "dask": dask.__version__, "load_start": load(), "size": size, "lights": a.lights, "repeats": a.repeats,
           "noop_tasks": noop_tasks}
    print(f"bench_scale {rep['date']}, {rep['machine']}, load {rep['load_start']}", flush=True)
    set_threads(1)
    preset, comps = get_preset("standard"), fit_components(True, False, True)
    with tempfile.TemporaryDirectory() as tmp:
        obs, rep["dataset"] = make_dataset(Path(tmp) / MATERIAL, size, a.lights)
        set_threads(1)
        rep["in_process"], ref = in_process(obs, preset, comps, threads, a.repeats,
                                            [c for c in (8, 16, 32, 64) if c <= size])
        ip = rep["in_process"]
        rep["driver_trim"] = os.environ.get(TRIM)
        rep["tiled"] = []
        for n in workers:
            rep["tiled"].append(tiled(obs, preset, comps, ref, n, a.tile, a.repeats,
                                      sweep if n == max(workers) else None, noop_tasks, ip["channels"]))
            if rep["tiled"][-1]["worker_trim"] != ["None"]:  # Dask set it: the same without it
                rep["tiled"].append(tiled(obs, preset, comps, ref, n, a.tile, a.repeats, None, noop_tasks,
                                          ip["channels"], unset_trim=True))
    rep["load_end"] = load()
    rep["extrapolation"] = extrapolate(rep)
    if a.json:
        Path(a.json).write_text(json.dumps(rep, indent=1, default=str))
    print()
    print(tables(rep))


if __name__ == "__main__":
    main()
