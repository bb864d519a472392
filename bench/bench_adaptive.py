"""Adaptive capture against fixed plans on the virtual rig (issue 27 "Measure"; docs/CAPTURE.md,
"Adaptive capture").

The virtual rig: the POSIX firmware simulator (the real C core) and a ``sim:micro`` camera on
its side channel (virtual sensor: metered exposures, shot and read noise, 12 bits), as fast as
it goes (``--sim-speed 0``: device time is the simulator's clock, the physical floor).  A
calibration of every LED (``tests.units.rawrig.calibration_session``, ``led_step=1``).

Per material and seed:

1. **full**: ``capture micro --lights ALL`` (127 LEDs at P0 and P90 and the back light, 256
   shots), calibrated (``to_radiance``) and fitted with ``standard``;
2. **adaptive**: ``capture micro --lights ALL --adaptive`` with the given ``--min-gain`` (its
   stopping rule) up to ``--budget``; its own dataset fitted with ``standard``;
3. **fixed plans with the adaptive capture's LED count**, cut from the full capture (the same
   frames a fixed capture of those LEDs takes): ``MODn`` (the n whose count is nearest),
   ``random`` (that many LEDs, seeded), and ``ROW2+4`` (its own 19 LEDs);
4. **adaptive at equal error** (unless ``--no-equal``): ``capture micro --lights ALL --adaptive`` with the
   default stop rules and no budget (``--target full+5%``: every map's predicted sigma within
   5 % of the whole plan's), so the device time it needs for about the full plan's error.

Errors are :func:`dualscale.fit.metrics.map_errors` against the ground truth; device time is the
physical floor of the shots in capture order (settle, servo moves, exposures, readout gaps;
:func:`dualscale.capture.session.floor_s`), metering apart.  Prints markdown tables with the
machine, its load (``uptime``) and the date.  Usage: ``.venv/bin/python bench/bench_adaptive.py
[--materials twill,satin,denim,leather,plain,sheer] [--seeds 0,1,2] [--size 16] [--budget 0.333x]``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dualscale.calib.apply import to_radiance  # noqa: E402
from dualscale.capture.journal import JOURNAL, Journal  # noqa: E402
from dualscale.capture.plan import make_plan, select_leds  # noqa: E402
from dualscale.capture.session import CaptureOptions, device_steps, floor_s, metered_plans  # noqa: E402
from dualscale.cli import main  # noqa: E402
from dualscale.fit.core import fit_observations  # noqa: E402
from dualscale.fit.metrics import map_errors  # noqa: E402
from dualscale.fit.observations import load_observations  # noqa: E402
from dualscale.fit.presets import get_preset  # noqa: E402
from dualscale.fit.select import select_components  # noqa: E402
from dualscale.protocol import regmap as rm  # noqa: E402
from dualscale.sim.materials import generate  # noqa: E402

ERRS = ("albedo_rmse", "normal_mean_deg", "roughness_mae", "anisotropy_mae", "ior_mae")
TEXEL_UM = 9.0
GAP_US = 1000  # readout_ms=1


def _cam(material: str, size: int, seed: int) -> str:
    return f"sim:micro?material={material}&size={size}&texel_um={TEXEL_UM:g}&seed={seed}&readout_ms=1"


def _capture(out: Path, cam: str, *extra: str) -> None:
    rc = main(["capture", "micro", "-o", str(out), "--port", "sim", "--camera", cam, "--rig-id", "virtual-dome-0",
               "--sim-speed", "0", "--no-progress", "--threads", "1", *extra])
    if rc != 0:
        raise SystemExit(f"capture {extra} failed: exit {rc}")


def _floor(root: Path, leds: list[int]) -> float:
    """The floor of a micro capture of ``leds`` in the plan's order (P0 run, back light, P90 run)
    with the brackets ``root``'s capture metered."""
    plan = make_plan("micro", "ALL")
    keep = set(leds)
    shots = [s for s in plan.shots if s.kind == "backlight" or s.index in keep]
    plans = metered_plans(Journal(root / JOURNAL))
    return floor_s(device_steps(shots, plans, plan, CaptureOptions(), rm.POL_P0_CDEG), GAP_US)


def _fit_errors(obs, gt) -> dict[str, float]:
    comps, _ = select_components(obs, seed=0)
    res = fit_observations(obs, get_preset("standard"), comps, seed=0)
    return map_errors(res.maps, gt)


def run_one(material: str, seed: int, size: int, cal: Path, min_gain: float, budget: str, work: Path,
            equal: bool = False) -> dict:
    gt = generate(material, size, TEXEL_UM / 1000.0, seed).maps
    cam = _cam(material, size, seed)
    full, ad = work / f"{material}-{seed}-full", work / f"{material}-{seed}-adaptive"
    t0 = time.perf_counter()
    _capture(full, cam, "--lights", "ALL")
    to_radiance(full, work / f"{material}-{seed}-full-rad", cal)
    obs = load_observations(work / f"{material}-{seed}-full-rad")
    t1 = time.perf_counter()
    all_leds = sorted(set(obs.led_ids.tolist()))
    full_floor = _floor(full, all_leds)
    if budget.endswith("x"):  # a fraction of the full plan's device time
        budget = f"{float(budget[:-1]) * full_floor:.3f}s"
    _capture(ad, cam, "--lights", "ALL", "--adaptive", "--calibration", str(cal), "--min-gain", str(min_gain),
             "--budget", budget)
    t_ad = time.perf_counter() - t1
    rec = json.loads((ad / "capture.json").read_text())["adaptive"]
    leds = sorted({i for r in rec["rounds"] for i in r["leds"]})
    to_radiance(ad, work / f"{material}-{seed}-ad-rad", cal)
    out: dict = {"material": material, "seed": seed, "stop": rec["stop"], "rounds": len(rec["rounds"]) - 1,
                 "adaptive_wall_s": t_ad}
    out["full"] = {"leds": len(all_leds), "floor_s": full_floor, **_fit_errors(obs, gt)}
    out["adaptive"] = {"leds": len(leds), "floor_s": float(rec["floor_s"]),
                       **_fit_errors(load_observations(work / f"{material}-{seed}-ad-rad"), gt)}
    n = len(leds)
    mod = min(range(1, 64), key=lambda k: abs(len(select_leds(f"MOD{k}")) - n))
    rng = np.random.default_rng(1000 + seed)
    plans = {f"MOD{mod}": select_leds(f"MOD{mod}"), "random": sorted(rng.choice(all_leds, n, replace=False).tolist()),
             "ROW2+4": select_leds("ROW2+4")}
    for name, sub in plans.items():
        out[name] = {"leds": len(sub), "floor_s": _floor(full, sub), **_fit_errors(obs.select_leds(set(sub)), gt)}
    if equal:
        eq = work / f"{material}-{seed}-equal"
        t2 = time.perf_counter()
        _capture(eq, cam, "--lights", "ALL", "--adaptive", "--calibration", str(cal))
        req = json.loads((eq / "capture.json").read_text())["adaptive"]
        to_radiance(eq, work / f"{material}-{seed}-eq-rad", cal)
        out["equal"] = {"leds": len({i for r in req["rounds"] for i in r["leds"]}), "floor_s": float(req["floor_s"]),
                        **_fit_errors(load_observations(work / f"{material}-{seed}-eq-rad"), gt)}
        out["equal_stop"], out["equal_wall_s"] = req["stop"], time.perf_counter() - t2
        last = [r for r in req["rounds"] if r.get("full_plan")]
        out["equal_full_plan"] = last[-1]["full_plan"] if last else None
    out["setup_wall_s"] = time.perf_counter() - t0
    return out


def _machine() -> str:
    load = os.getloadavg()
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"{datetime.datetime.now().strftime('%Y-%m-%d %H:%M')}, load {load[0]:.1f}/{load[1]:.1f}/{load[2]:.1f}")


def tables(results: list[dict]) -> str:
    lines = [f"Machine: {_machine()}", ""]
    plans = ["full", "adaptive"] + [k for k in results[0] if k.startswith("MOD")] + ["random", "ROW2+4"]
    lines.append("| material | seed | plan | LEDs | device s | " + " | ".join(ERRS) + " |")
    lines.append("|---|---:|---|---:|---:|" + "---:|" * len(ERRS))
    for r in results:
        for p in [k for k in r if isinstance(r[k], dict) and "leds" in r[k]]:
            e = r[p]
            lines.append(f"| {r['material']} | {r['seed']} | {p} | {e['leds']} | {e['floor_s']:.1f} | "
                         + " | ".join(f"{e[k]:.4g}" for k in ERRS) + " |")
    lines += ["", "Ratios to the full plan (median over seeds; errors: plan / full; device time: plan / full):", ""]
    lines.append("| material | plan | LEDs | device time | " + " | ".join(ERRS) + " |")
    lines.append("|---|---|---:|---:|" + "---:|" * len(ERRS))
    for mat in dict.fromkeys(r["material"] for r in results):
        rs = [r for r in results if r["material"] == mat]
        for p in ["adaptive", "MOD", "random", "ROW2+4", "equal"]:
            plan_of = lambda r, p=p: [k for k in r if k.startswith(p) and isinstance(r[k], dict) and "leds" in r[k]]  # noqa: E731
            if not all(plan_of(r) for r in rs):
                continue
            keys = [plan_of(r)[0] for r in rs]
            med = lambda f: statistics.median(f(r, k) for r, k in zip(rs, keys))  # noqa: E731
            lines.append(f"| {mat} | {keys[0] if p != 'MOD' else 'MODn'} | {med(lambda r, k: r[k]['leds']):.0f} | "
                         f"{med(lambda r, k: r[k]['floor_s'] / r['full']['floor_s']):.2f} | "
                         + " | ".join(f"{med(lambda r, k, e=e: r[k][e] / max(r['full'][e], 1e-12)):.2f}" for e in ERRS)
                         + " |")
    stops = {}
    for r in results:
        stops[r["stop"]] = stops.get(r["stop"], 0) + 1
    eq = {}
    for r in results:
        if "equal_stop" in r:
            eq[r["equal_stop"]] = eq.get(r["equal_stop"], 0) + 1
    if eq:
        lines += ["", f"Adaptive at equal error (full+5%, no budget) stops: {eq}; wall time median "
                  f"{statistics.median(r['equal_wall_s'] for r in results if 'equal_wall_s' in r):.0f} s"]
    lines += ["", f"Adaptive stops: {stops}; rounds median {statistics.median(r['rounds'] for r in results):.0f}; "
              f"wall time of an adaptive capture median {statistics.median(r['adaptive_wall_s'] for r in results):.0f} s"]
    return "\n".join(lines)


def main_() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--materials", default="twill,satin,denim,leather,plain,sheer")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--size", type=int, default=16)
    ap.add_argument("--min-gain", type=float, default=None, help="default: the product's")
    ap.add_argument("--budget", default="0.333x",
                    help="the adaptive capture's --budget, or Fx: F times the full plan's device time (default 0.333x, "
                         "the issue's goal)")
    ap.add_argument("--calibration", default=None, help="a calibration of every LED (default: made here)")
    ap.add_argument("--json", default=None, help="also write the results here")
    ap.add_argument("--no-equal", dest="equal", action="store_false",
                    help="leave out the adaptive capture at equal error (default target, no budget)")
    a = ap.parse_args()
    import torch

    from dualscale.adaptive.loop import AdaptiveOptions

    torch.set_num_threads(1)
    min_gain = AdaptiveOptions().min_gain if a.min_gain is None else a.min_gain
    with tempfile.TemporaryDirectory(prefix="bench-adaptive-") as td:
        work = Path(td)
        cal = Path(a.calibration) if a.calibration else None
        if cal is None:
            from tests.units.rawrig import calibration_session

            cal = calibration_session(work / "cal", led_step=1)
        results = []
        for mat in a.materials.split(","):
            for seed in [int(s) for s in a.seeds.split(",")]:
                r = run_one(mat, seed, a.size, cal, min_gain, a.budget, work, a.equal)
                results.append(r)
                print(json.dumps(r), flush=True)
        if a.json:
            Path(a.json).write_text(json.dumps(results, indent=1))
    print(f"\n### Adaptive capture (min-gain {min_gain:g}, budget {a.budget}, {a.size} px)\n")
    print(tables(results))


if __name__ == "__main__":
    main_()
