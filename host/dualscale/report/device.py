"""The device-evaluation report (``dualscale evaluate-device``): ``report.html`` plus PNG and SVG
figures in the report folder, in the style of the run report (``dualscale.report``: shared
templates, plots and number formatting).

Goals shown beside the values come from the paper (Garces et al. 2023, Sec. 3):

* mean CIEDE2000 < 3 ("below perception"; stated for the micro camera);
* polarisation: the largest |max-angle error| < 12° (the paper's average is 4.43°);
* collimation: std of the normalised white-sheet luminance < 0.15 for every LED.

Hemisphere plots use one colour scale per figure whose maximum is the data's maximum, so the
"before CCM" points are never capped; the goal is drawn on the colorbar.
"""

from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from dualscale.calib import colourref as cr
from dualscale.report import format as fmt
from dualscale.report import plots
from dualscale.report.html import Assets, write_page

DE_GOAL = 3.0
POL_MAX_ERROR_GOAL_DEG = 12.0
COLLIMATION_STD_GOAL = 0.15
CCM_METHODS = (("before", "before (white balance only)"), ("least_squares", "least squares"),
               ("ciede2000", "Nelder–Mead on CIEDE2000"))


def _hemi_panels(values_by_light: dict[str, float], title: str):
    """``(title, theta, phi, values, centre)`` for :func:`plots.hemisphere_figure`."""
    from dualscale.calib.evaluate import hemisphere_coords

    coords = hemisphere_coords(list(values_by_light))
    leds = [k for k in values_by_light if k.startswith("led") and k in coords]
    return (title, [coords[k][0] for k in leds], [coords[k][1] for k in leds],
            [float(values_by_light[k]) for k in leds], values_by_light.get("diffuse"))


def _summary_rows(summary: dict[str, Any]) -> list[tuple[str, Any]]:
    """The evaluate-device summary as (quantity, value-with-goal) rows; unknown keys are shown
    plainly (never as JSON)."""
    rows: list[tuple[str, Any]] = []
    rest = dict(summary)
    for key in sorted(k for k in summary if k.endswith("_mean_dE00")):
        cam = key[: -len("_mean_dE00")]
        d = rest.pop(key) or {}
        if isinstance(d, dict):
            if "before" in d:
                rows.append((f"{cam}: mean ΔE00 before the CCM", fmt.quantity(d["before"])))
            if "after" in d:
                rows.append((f"{cam}: mean ΔE00 after the CCM", fmt.check(d["after"], "<", DE_GOAL)))
        else:
            rows.append((f"{cam}: mean ΔE00", fmt.value(d)))
    if "sharpness_mean" in rest:
        rows.append(("sharpness, mean over the dots (1 = ideal)", fmt.value(rest.pop("sharpness_mean"))))
    pol = rest.pop("polarization_error_deg", None)
    if isinstance(pol, dict):
        if "mean_abs" in pol:
            rows.append(("polarisation: mean |max-angle error|", fmt.quantity(pol["mean_abs"], "°")))
        if "max_abs" in pol:
            rows.append(("polarisation: largest |max-angle error|", fmt.check(pol["max_abs"], "<",
                                                                              POL_MAX_ERROR_GOAL_DEG, "°")))
        if "analyzer_misalignment" in pol:
            rows.append(("analyser misalignment (estimated)", fmt.quantity(pol["analyzer_misalignment"], "°")))
    if "collimation_std_max" in rest:
        rows.append(("collimation: largest std of normalised luminance",
                     fmt.check(rest.pop("collimation_std_max"), "<", COLLIMATION_STD_GOAL)))
    rows += fmt.rows(rest)
    return rows


def write_report(out: str | Path, results: dict[str, Any], calib: dict[str, Any]) -> Path:
    """Figures (PNG + SVG) and ``report.html`` in ``out``; ``results`` from the ``evaluate-device``
    command, ``calib`` the calibration file's content. Returns the page's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    assets = Assets(out, folder=None, svg=True)
    sections: dict[str, dict[str, Any]] = {}

    def add(section: str, f, stem: str, caption: str, title: str, wide: bool = False):
        sections.setdefault(section, {"figs": []})["figs"].append(
            {"src": assets.figure(f, stem), "caption": caption, "title": title, "alt": title, "wide": wide})

    colour = results.get("colour") or {}
    if colour:
        cams = sorted(colour)
        panels = []
        for cam in cams:
            for stage, name in (("before", "before CCM"), ("after", "after CCM")):
                vals = {l: float(np.mean(d[stage])) for l, d in colour[cam].items() if stage in d}
                panels.append(_hemi_panels(vals, f"{cam}: {name}"))
        f, cap, _ = plots.hemisphere_figure(panels, label="mean ΔE00 over the 24 patches", goal=DE_GOAL,
                                            goal_text="goal ΔE00 <", ncols=2)
        add("colour", f, "colour_hemisphere", cap, "Colour accuracy on the hemisphere", wide=True)
        f = plots.figure(10.5, 1.0 + 2.3 * len(cams))
        axes = f.subplots(len(cams), 1, squeeze=False)[:, 0]
        for ax, cam in zip(axes, cams):
            leds = [d["after"] for l, d in colour[cam].items() if l.startswith("led") and "after" in d]
            if leds:
                data = np.asarray(leds, float)
                ax.boxplot([data[:, k] for k in range(data.shape[1])], widths=0.6, flierprops={"markersize": 2})
            ax.axhline(DE_GOAL, color="crimson", lw=1, ls="--", label=f"goal ΔE00 < {fmt.number(DE_GOAL)}")
            ax.set_ylabel("ΔE00")
            ax.set_title(f"{cam}: {len(leds)} directional LEDs, after the CCM", loc="left")
            ax.set_xticks(range(1, cr.N_PATCHES + 1), [] if ax is not axes[-1] else cr.patch_names(),
                          rotation=90, fontsize=7)
            ax.legend(loc="upper right", fontsize=7)
        axes[-1].set_xlabel("ColorChecker patch")
        add("colour", f, "colour_boxplots",
            "CIEDE2000 per patch over the directional LEDs, after the CCM (box: quartiles, whiskers: 1.5 IQR).",
            "ΔE00 per patch", wide=True)

    sh = results.get("sharpness")
    if sh and len(sh.get("values") or []):
        xy = np.asarray(sh["centres"], float).reshape(-1, 2)
        v = np.asarray(sh["values"], float)
        f = plots.figure(4.8, 4.0)
        ax = f.add_subplot()
        fin = v[np.isfinite(v)]
        s = ax.scatter(xy[:, 0], xy[:, 1], c=v, cmap="viridis", s=150, marker="s",
                       vmin=float(fin.min()) if fin.size else 0, vmax=float(fin.max()) if fin.size else 1)
        ax.invert_yaxis()
        ax.set_aspect("equal")
        ax.set_xlabel("column [px]")
        ax.set_ylabel("row [px]")
        ax.set_title("sharpness per dot (dot grid, diffuse light)")
        f.colorbar(s, ax=ax, label="sharpness (1 = ideal, unitless)", shrink=0.9)
        cap = (f"{len(v)} dots; colour scale = the data's full range, {fmt.number(fin.min())} to "
               f"{fmt.number(fin.max())}." if fin.size else "No dot could be measured.")
        add("sharpness", f, "sharpness_map", cap, "Sharpness map")

    pol = results.get("polarization")
    if pol and pol.get("leds"):
        leds = pol["leds"]
        f = plots.figure(10.5, 3.8)
        gs = f.add_gridspec(1, 2, width_ratios=[1.25, 1])
        ax = f.add_subplot(gs[0])
        shown = leds[:6]
        for p in shown:
            ax.plot(p["angles_deg"], p["intensity"], "o-", ms=3, label=f"LED {p['led']}")
        ax.set_xlabel("analyser angle [°]")
        ax.set_ylabel("mean luminance [relative radiance]")
        ax.set_title(f"intensity against analyser angle ({len(shown)} of {len(leds)} LEDs)")
        ax.legend(fontsize=7, ncols=2)
        err = {f"led{p['led']:03d}": abs(float(p["error_deg"])) for p in leds}
        th_ph = _hemi_panels(err, "|max-angle error| per LED")
        ax2 = f.add_subplot(gs[1], projection="polar")
        norm, is_log = plots.hemisphere_norm(list(err.values()))
        sc = plots.hemisphere(ax2, th_ph[1], th_ph[2], th_ph[3], norm=norm)
        ax2.set_title(th_ph[0], pad=12)
        cb = f.colorbar(sc, ax=ax2, shrink=0.85, pad=0.08)
        cb.set_label("|max-angle error| [°]" + (" (log scale)" if is_log else ""))
        if norm.vmin <= POL_MAX_ERROR_GOAL_DEG <= norm.vmax:
            cb.ax.axhline(POL_MAX_ERROR_GOAL_DEG, color="crimson", lw=1.2)
        e = np.asarray(list(err.values()))
        cap = (f"Left: mean luminance of the micro field while the analyser turns. Right: |measured − theoretical| "
               f"angle of the intensity maximum per LED (radius: angle from the zenith [°]); colour scale 0 to the "
               f"data max {fmt.quantity(norm.vmax, '°')}. Mean {fmt.quantity(e.mean(), '°')}, largest "
               f"{fmt.check(e.max(), '<', POL_MAX_ERROR_GOAL_DEG, '°')}.")
        add("polarization", f, "polarization", cap, "Polarisation", wide=True)

    colm = results.get("collimation")
    if colm:
        f, cap, _ = plots.hemisphere_figure([_hemi_panels(colm, "white-sheet luminance std per LED")],
                                            label="luminance std / mean (unitless)",
                                            goal=COLLIMATION_STD_GOAL, goal_text="goal <", size=(5.0, 3.8))
        add("collimation", f, "collimation", cap, "Collimation")

    ccm_rows = []
    for cam, kinds in (calib.get("ccm") or {}).items():
        for kind, fit in (kinds or {}).items():
            d = (fit or {}).get("mean_delta_e2000") or {}
            row = [cam, kind]
            for m, _ in CCM_METHODS:
                e = d.get(m) or {}
                row.append(f"{fmt.number(e.get('fit'))} / {fmt.number(e.get('held_out'))}")
            held = (d.get("ciede2000") or {}).get("held_out")
            row.append(fmt.check(held, "<", DE_GOAL) if held is not None else fmt.DASH)
            ccm_rows.append(row)

    rig = calib.get("rig") or {}
    summary_rows = _summary_rows(results.get("summary") or {})
    cards = [(k, v) for k, v in summary_rows if isinstance(v, fmt.Checked)]
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    from dualscale import __version__

    notes = {"colour": "No ColorChecker captures in this session: colour accuracy not evaluated.",
             "sharpness": "No dot-grid capture in this session: sharpness not evaluated.",
             "polarization": "No polarisation sweep in this session: polarisation not evaluated.",
             "collimation": "No white-sheet captures under directional LEDs: collimation not evaluated."}
    return write_page(
        out / "report.html", "device.html",
        title="dualscale device evaluation",
        subtitle=(f"rig {rig.get('id', fmt.DASH)} · layout {fmt.value(rig.get('layout'))} · calibration created "
                  f"{fmt.timestamp(calib.get('created'))}"),
        toc=[("summary", "Summary"), ("ccm", "Colour correction"), ("colour", "Colour accuracy"),
             ("sharpness", "Sharpness"), ("polarization", "Polarisation"), ("collimation", "Collimation")],
        footer=f"dualscale {__version__} · written {now} · figures beside this page as PNG and SVG",
        cards=cards, summary_rows=summary_rows,
        ccm={"header": ["camera", "lights"] + [n + " (fit / held-out)" for _, n in CCM_METHODS]
             + ["held-out, Nelder–Mead"], "rows": ccm_rows, "numeric": []} if ccm_rows else None,
        sections=sections, notes=notes, de_goal=fmt.number(DE_GOAL),
    )


__all__ = ["write_report", "DE_GOAL", "POL_MAX_ERROR_GOAL_DEG", "COLLIMATION_STD_GOAL"]
