"""The propagation trade as one figure (issue 29 §4): per map, L1 and SSIM against training time
(log axis) on the twill benchmark, the training presets (cold and warm-started) and the classic
baselines as labelled points.

    PYTHONPATH=host python bench/bench_propagate_trade.py [--out docs/figures/propagate_trade.png]
    PYTHONPATH=host python bench/bench_propagate_trade.py --measure [--work /tmp/propbench] [--threads 1]

Without ``--measure`` it draws the figure from the packaged trade data
(``host/dualscale/report/data/propagate_trade.json``, :mod:`dualscale.report.trade`: the layout,
the one reader), so the figure is reproducible without re-training.  With ``--measure`` it first
re-measures them, presets and baselines in one run (about an hour on the 2-core VM):
``bench_propagate.py --stages prep,warm,presets --runs quick,quick+warm,fast,fast+warm,balanced
--json ...`` and ``bench_propagate_baseline.py --json ...``, then rewrites the data file (this
script is its one writer) and draws.  Every output goes through a temp file and a rename
(:mod:`dualscale.formats.atomic`); a failed measurement leaves the previous data as they were.

The ``digitize`` report reads the same file to say where its preset sits on this curve
(:func:`dualscale.report.trade.trade_rows`).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
RUNS = "quick,quick+warm,fast,fast+warm,balanced"
#: the markers and colours of the series (a preset series is joined by a line, in time order)
SERIES = {"preset": ("o", "#1f77b4", "presets, random weights"), "warm": ("s", "#ff7f0e", "presets, warm start"),
          "baseline": ("D", "#2ca02c", "classic baselines")}
SHORT = {"quick + warm start": "quick+w", "fast + warm start": "fast+w"}


def measure(data: Path, work: str, threads: int) -> None:
    """Run the presets and baselines benches with ``--json`` and rewrite ``data`` from their rows."""
    import json

    from dualscale.formats.atomic import write_json
    from dualscale.report.trade import TRADE_FILE

    old = json.loads(TRADE_FILE.read_text(encoding="utf-8"))
    with tempfile.TemporaryDirectory() as tmp:
        pj, bj = Path(tmp) / "presets.json", Path(tmp) / "baselines.json"
        subprocess.run([sys.executable, str(HERE / "bench_propagate.py"), "--work", work, "--threads", str(threads),
                        "--stages", "prep,warm,presets", "--runs", RUNS, "--json", str(pj)], check=True)
        subprocess.run([sys.executable, str(HERE / "bench_propagate_baseline.py"), "--work", work, "--json", str(bj)],
                       check=True)
        doc = assemble(old, json.loads(pj.read_text()), json.loads(bj.read_text()))
    write_json(data, doc)
    print(f"wrote {data}")


def assemble(old: dict, presets: dict, baselines: dict) -> dict:
    """The trade data from the benches' ``--json`` runs (``presets``, ``baselines``), keeping the
    benchmark and metrics texts of ``old``; checked by ``dualscale.report.trade.validate``."""
    from dualscale.report.trade import FORMAT, VERSION, validate

    presets = {**presets, "source": f"bench/bench_propagate.py --stages prep,warm,presets --runs {RUNS} (--measure)"}
    baselines = {**baselines, "source": "bench/bench_propagate_baseline.py (--measure)"}
    doc = {"format": FORMAT, "version": VERSION, "written_by": "bench/bench_propagate_trade.py --measure",
           "benchmark": old["benchmark"], "metrics": old["metrics"], "maps": list(presets["points"][0]["maps"]),
           "runs": [presets, baselines]}
    return validate(doc, "measured trade data")


def from_runs(spec_path: Path) -> dict:
    """The trade data from earlier benches' ``--json`` files, chosen by a spec (JSON):
    ``{"runs": [{"name", "source", "load", "points": [{"file", "label", ...overrides}]}]}``.
    Each point is the row of ``file`` whose label is ``label``, with the spec's other keys
    replacing its own (e.g. ``"preset": "fast"`` for a variant that is today's ``fast``, or
    ``"seconds"`` from a same-run step timing: the spec says why in its run's ``source``)."""
    import json

    from dualscale.report.trade import TRADE_FILE

    spec = json.loads(spec_path.read_text(encoding="utf-8"))
    old = json.loads(TRADE_FILE.read_text(encoding="utf-8"))
    runs = []
    for r in spec["runs"]:
        points, dates, machine = [], [], None
        for want in r["points"]:
            doc = json.loads((spec_path.parent / want["file"]).read_text(encoding="utf-8"))
            row = next((p for p in doc["points"] if p["label"] == want["label"]), None)
            if row is None:
                raise SystemExit(f"{want['file']}: no point labelled {want['label']!r}")
            points.append({**row, **{k: v for k, v in want.items() if k not in ("file", "label")},
                           "label": want.get("as", row["label"])})
            points[-1].pop("as", None)
            dates.append(doc["date"])
            machine = machine or doc["machine"]
        runs.append({"name": r["name"], "date": min(dates)[:10], "machine": machine, "load": r["load"],
                     "source": r["source"], "points": points})
    from dualscale.report.trade import FORMAT, VERSION, validate

    doc = {"format": FORMAT, "version": VERSION, "written_by": f"bench/bench_propagate_trade.py --from-runs {spec_path.name}",
           "benchmark": old["benchmark"], "metrics": old["metrics"], "maps": list(runs[0]["points"][0]["maps"]),
           "runs": runs}
    return validate(doc, f"trade data from {spec_path}")


def _series(p: dict) -> str:
    return "baseline" if p["kind"] == "baseline" else ("warm" if p["warm_start"] else "preset")


def draw(doc: dict, out: Path, dpi: int = 110) -> Path:
    """Draw the figure of ``doc`` (the trade data) into ``out`` (PNG) through a temp file."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dualscale.formats.atomic import atomic_path

    maps = doc["maps"]
    points = [(run, p) for run in doc["runs"] for p in run["points"]]
    fig, axes = plt.subplots(2, len(maps), figsize=(2.6 * len(maps), 6.0), layout="constrained", sharex=True)
    for j, m in enumerate(maps):
        for i, (metric, k) in enumerate((("L1 (lower is better)", 0), ("SSIM (higher is better)", 1))):
            ax = axes[i, j]
            for s, (marker, colour, name) in SERIES.items():
                pts = sorted((p["seconds"], p["maps"][m][k], p["label"]) for _, p in points if _series(p) == s)
                if not pts:
                    continue
                xs, ys, labels = zip(*pts)
                ax.plot(xs, ys, marker=marker, color=colour, ls="-" if s != "baseline" else "none", ms=5,
                        label=name)
                for x, y, lab in pts:
                    ax.annotate(SHORT.get(lab, lab), (x, y), xytext=(3, 3), textcoords="offset points", fontsize=6.5,
                                color=colour)
            ax.set_xscale("log")
            ax.set_xlim(0.05, 6000)  # room for the labels right of the longest run
            ax.grid(True, which="major", alpha=0.3)
            if i == 0:
                ax.set_title(m.replace("_", " "))
            else:
                ax.set_xlabel("training time [s]")
            if j == 0:
                ax.set_ylabel(metric)
    handles, names = axes[0, 0].get_legend_handles_labels()
    runs = "; ".join(f"{r['name']}: {r['date']}, load {min(p['load'] for p in r['points']):g}"
                     f"-{max(p['load'] for p in r['points']):g}" for r in doc["runs"])
    fig.legend(handles, names, loc="outside lower center", ncol=3, fontsize=8)
    fig.suptitle("Propagation on the twill benchmark: accuracy against training time "
                 f"(baselines: fit + run time)\n{runs}; 2-core VM, 1 torch thread, shared (compare rows of one run)",
                 fontsize=9)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(HERE.parent / "docs" / "figures" / "propagate_trade.png"))
    ap.add_argument("--measure", action="store_true", help="re-measure presets and baselines first (~1 h)")
    ap.add_argument("--work", default="/tmp/propbench", help="--measure: the benches' work folder")
    ap.add_argument("--threads", type=int, default=1, help="--measure: torch threads for training")
    ap.add_argument("--from-runs", metavar="SPEC", help="rewrite the data from earlier benches' --json files "
                    "chosen by SPEC (see from_runs)")
    a = ap.parse_args()
    from dualscale.report.trade import TRADE_FILE, load_trade

    if a.measure:
        measure(TRADE_FILE, a.work, a.threads)
    elif a.from_runs:
        from dualscale.formats.atomic import write_json

        write_json(TRADE_FILE, from_runs(Path(a.from_runs)))
    doc = load_trade()
    print(f"wrote {draw(doc, Path(a.out))} from {TRADE_FILE}")
    for run in doc["runs"]:
        print(f"  {run['name']}: {run['date']}, {run['machine']}, load {run['load']}: "
              + ", ".join(f"{p['label']} {p['seconds']:g} s" for p in run["points"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
