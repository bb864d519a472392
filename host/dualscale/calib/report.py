"""Plots (matplotlib, PNG + SVG) and one HTML report of a device evaluation."""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

import numpy as np

from . import colourref as cr
from .evaluate import hemisphere_coords


def _save(fig, out: Path, name: str) -> str:
    for ext in ("png", "svg"):
        fig.savefig(out / f"{name}.{ext}", dpi=110, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return f"{name}.png"


def _hemisphere(ax, values: dict[str, float], title: str, vmax: float, cmap: str = "magma"):
    """Polar scatter: radius = theta, angle = phi; the diffuse value fills the centre."""
    coords = hemisphere_coords(list(values))
    leds = [k for k in values if k.startswith("led") and k in coords]
    th = np.array([coords[k][0] for k in leds])
    ph = np.radians([coords[k][1] for k in leds])
    sc = ax.scatter(ph, th, c=[values[k] for k in leds], cmap=cmap, vmin=0, vmax=vmax, s=60)
    if "diffuse" in values:
        ax.scatter([0], [0], c=[values["diffuse"]], cmap=cmap, vmin=0, vmax=vmax, s=400, marker="o", edgecolors="w")
    ax.set_ylim(0, 80)
    ax.set_title(title, fontsize=9)
    return sc


def write_report(out: str | Path, results: dict[str, Any], calib: dict[str, Any]) -> Path:
    """Figures and ``report.html`` in ``out``; ``results`` from the ``evaluate-device`` command."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figs: list[tuple[str, str]] = []
    colour = results.get("colour", {})
    if colour:
        cams = sorted(colour)
        fig, axes = plt.subplots(2, len(cams), subplot_kw={"projection": "polar"}, figsize=(3.2 * len(cams), 6.4),
                                 squeeze=False)
        for j, cam in enumerate(cams):
            for i, stage in enumerate(("before", "after")):
                vals = {l: float(np.mean(d[stage])) for l, d in colour[cam].items()}
                sc = _hemisphere(axes[i, j], vals, f"{cam}: mean dE00 {stage} CCM", 10.0)
        fig.colorbar(sc, ax=axes.ravel().tolist(), shrink=0.6, label="mean CIEDE2000")
        figs.append(("Colour accuracy on the hemisphere (centre: diffuse)", _save(fig, out, "colour_hemisphere")))
        fig, axes = plt.subplots(len(cams), 1, figsize=(11, 2.6 * len(cams)), squeeze=False)
        for j, cam in enumerate(cams):
            leds = [d for l, d in colour[cam].items() if l.startswith("led")]
            if leds:
                data = np.array([d["after"] for d in leds])
                axes[j, 0].boxplot([data[:, k] for k in range(cr.N_PATCHES)])
            axes[j, 0].set_ylabel(f"{cam} dE00")
        axes[-1, 0].set_xticks(range(1, 25), cr.patch_names(), rotation=60, ha="right", fontsize=7)
        figs.append(("CIEDE2000 per patch over directional LEDs, after CCM", _save(fig, out, "colour_boxplots")))
    sh = results.get("sharpness")
    if sh:
        xy = np.asarray(sh["centres"])
        fig, ax = plt.subplots(figsize=(4.5, 4))
        s = ax.scatter(xy[:, 0], xy[:, 1], c=sh["values"], cmap="viridis", s=160, marker="s")
        ax.invert_yaxis()
        ax.set_aspect("equal")
        fig.colorbar(s, label="sharpness (1 = ideal)")
        ax.set_title("Sharpness map (dot grid)")
        figs.append(("Sharpness", _save(fig, out, "sharpness_map")))
    pol = results.get("polarization")
    if pol:
        fig = plt.figure(figsize=(10, 4))
        ax = fig.add_subplot(1, 2, 1)
        for p in pol["leds"][:6]:
            ax.plot(p["angles_deg"], p["intensity"], "o-", ms=3, label=f"LED {p['led']}")
        ax.set_xlabel("analyser angle [deg]")
        ax.set_ylabel("mean luminance")
        ax.legend(fontsize=7)
        ax2 = fig.add_subplot(1, 2, 2, projection="polar")
        sc = _hemisphere(ax2, {f"led{p['led']:03d}": abs(p["error_deg"]) for p in pol["leds"]}, "|max-angle error| [deg]",
                         max(1.0, max(abs(p["error_deg"]) for p in pol["leds"])), "viridis")
        fig.colorbar(sc, ax=ax2, shrink=0.7)
        figs.append(("Polarisation", _save(fig, out, "polarization")))
    colm = results.get("collimation")
    if colm:
        fig, ax = plt.subplots(subplot_kw={"projection": "polar"}, figsize=(4.5, 4))
        sc = _hemisphere(ax, colm, "std of normalised luminance", max(0.05, max(colm.values())), "viridis")
        fig.colorbar(sc, ax=ax, shrink=0.7)
        figs.append(("Collimation", _save(fig, out, "collimation")))
    rows = []
    for cam, kinds in calib.get("ccm", {}).items():
        for kind, f in kinds.items():
            d = f["mean_delta_e2000"]
            rows.append(f"<tr><td>{cam}</td><td>{kind}</td>" + "".join(
                f"<td>{d[m]['fit']:.2f} / {d[m]['held_out']:.2f}</td>" for m in ("before", "least_squares", "ciede2000"))
                + "</tr>")
    summ = html.escape(json.dumps(results.get("summary", {}), indent=1))
    body = [f"<h1>dualscale device evaluation</h1><p>rig {html.escape(str(calib.get('rig', {})))}; calibration "
            f"created {html.escape(str(calib.get('created')))}</p>",
            "<h2>CCM: mean CIEDE2000 (fit / held-out patches)</h2><table border=1 cellpadding=3>"
            "<tr><th>camera</th><th>lights</th><th>before</th><th>least squares</th><th>Nelder-Mead dE00</th></tr>"
            + "".join(rows) + "</table>", f"<h2>Summary</h2><pre>{summ}</pre>"]
    for title, png in figs:
        body.append(f"<h2>{html.escape(title)}</h2><img src='{png}' style='max-width:100%'>")
    path = out / "report.html"
    path.write_text("<!doctype html><html><head><meta charset='utf-8'><title>dualscale device evaluation</title>"
                    "</head><body>" + "\n".join(body) + "</body></html>")
    return path
