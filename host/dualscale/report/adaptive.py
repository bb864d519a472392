"""The run report's "Adaptive capture" section (issue 27): the rounds of a ``digitize --rig ...
--adaptive`` micro capture, from the ``"adaptive"`` record of ``RUN/capture/micro/capture.json``
(written by :meth:`dualscale.adaptive.loop.AdaptiveCapture.run`; its shape is in
:mod:`dualscale.adaptive.loop`'s doc).

* :func:`section` -> ``None`` when the run has no such record (no rig capture, or a fixed plan);
  else the figures and the table of the section.
* :func:`sigma_rounds_figure`: each map's median 1σ over the round's sample pixels (log axis,
  each map in its own unit, :func:`dualscale.report.plots.sigma_unit`) against the shots taken
  and against the device time (the physical floor, ``floor_s``), one marker per round; with the
  whole candidate plan's prediction (the last decision's ``full_plan``) as each map's dashed
  level and its estimated device time as a dotted vertical line.
* :func:`dome_figure`: the dome seen from above (the x-y projection of the unit LED directions
  of :meth:`dualscale.geometry.dome.DomeGeometry.from_regmap`, +z the zenith at the centre),
  every LED a small grey dot, the candidates (the plan's LEDs) outlined, the chosen LEDs filled
  in the colour of the round that took them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

import numpy as np

from . import format as fmt
from . import plots

RECORD = "capture/micro/capture.json"  # relative to the run folder (pipeline.capture_stage)
#: the maps of the table's sigma columns (every map fitted in a round is in the figure)
TABLE_MAPS = ("normal", "roughness", "albedo")
ROUNDS_CMAP = "plasma"


def read_record(run: Path, note: Callable[[str], None]) -> dict[str, Any] | None:
    """The ``"adaptive"`` record of ``run``'s micro capture, or ``None`` when there is none (no
    ``capture.json``, or a capture without ``"adaptive"``).  An unreadable file or a record
    without rounds is one ``note`` (a report warning) and ``None``: the page is still written."""
    path = run / RECORD
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        note(f"{RECORD} is not readable ({e}); the adaptive capture's rounds are not shown")
        return None
    rec = doc.get("adaptive") if isinstance(doc, dict) else None
    if rec is None:
        return None
    if not isinstance(rec, dict) or not isinstance(rec.get("rounds"), list) or not any(
            isinstance(r, dict) and isinstance(r.get("fit"), dict) for r in rec["rounds"]):
        note(f"{RECORD} has an adaptive record without fitted rounds; the adaptive capture is not shown")
        return None
    rec = dict(rec, candidates=_candidates(doc.get("plan")))
    return rec


def _candidates(plan: Any) -> list[int]:
    """The plan's LED indices (the adaptive capture's candidates), in order, each once."""
    out: list[int] = []
    for s in (plan or {}).get("shots") or [] if isinstance(plan, dict) else []:
        if isinstance(s, dict) and s.get("kind") == "led" and isinstance(s.get("index"), int) and s["index"] not in out:
            out.append(s["index"])
    return out


def fitted_rounds(rec: dict[str, Any]) -> list[dict[str, Any]]:
    """The rounds with a fit (every round but the stop decision), in order."""
    return [r for r in rec["rounds"] if isinstance(r, dict) and isinstance(r.get("fit"), dict)]


def _map_names(rounds: list[dict[str, Any]]) -> list[str]:
    seen = {n for r in rounds for n in (r["fit"].get("sigma") or {})}
    return [n for n in plots.MAP_TITLES if n in seen] + sorted(seen - set(plots.MAP_TITLES))


def last_full_plan(rec: dict[str, Any]) -> dict[str, Any] | None:
    """The last decision's prediction of the whole candidate plan (``full_plan``: ``sigma`` and
    ``sigma_now`` per map, ``cost_s`` its estimated device time, ``shots``), or ``None`` (a
    record written before the prediction existed, or a capture that stopped for want of
    candidates)."""
    plans = [r["full_plan"] for r in rec["rounds"] if isinstance(r, dict) and isinstance(r.get("full_plan"), dict)]
    return plans[-1] if plans else None


def sigma_rounds_figure(rounds: list[dict[str, Any]], full: dict[str, Any] | None = None):
    """Median 1σ per map after each round (log y, one line and marker per map and round) against
    the shots taken (left) and the device time [s] (right).  ``rounds``: :func:`fitted_rounds`;
    ``full``: :func:`last_full_plan` (its predicted σ dashed, its shots and device time dotted).
    Returns ``(fig, caption)``."""
    names = _map_names(rounds)
    shots = np.array([float(r["fit"].get("shots", np.nan)) for r in rounds])
    secs = np.array([float(r["fit"].get("floor_s", np.nan)) for r in rounds])
    fig = plots.figure(8.6, 3.4)
    axes = fig.subplots(1, 2, sharey=True)
    colours = plots._plt().rcParams["axes.prop_cycle"].by_key()["color"]
    missing = []
    for i, n in enumerate(names):
        y = np.array([float((r["fit"].get("sigma") or {}).get(n, np.nan)) for r in rounds])
        y[~(y > 0)] = np.nan  # a log axis: a zero or absent median is a gap
        if np.isnan(y).any():
            missing.append(plots.MAP_TITLES.get(n, n))
        label = f"{'IOR' if n == 'ior' else plots.MAP_TITLES.get(n, n)} [{plots.sigma_unit(n)}]"
        for ax, x in zip(axes, (shots, secs)):
            ax.plot(x, y, marker="o", ms=4, lw=1.2, color=colours[i % len(colours)], label=label)
            v = (full or {}).get("sigma", {}).get(n)
            if isinstance(v, (int, float)) and v > 0:
                ax.axhline(v, color=colours[i % len(colours)], lw=0.8, ls="--")
    if full:
        for ax, k in zip(axes, ("shots", "cost_s")):
            if isinstance(full.get(k), (int, float)):
                ax.axvline(float(full[k]), color="0.4", lw=0.8, ls=":")
    for ax, xl in zip(axes, ("shots taken", "device time (physical floor) [s]")):
        ax.set_yscale("log")
        ax.set_xlabel(xl)
        ax.spines[["top", "right"]].set_visible(False)
        ax.grid(True, which="major", color="0.9", lw=0.6)
    axes[0].set_ylabel("median 1σ [each map's unit]")
    axes[0].set_title("σ against the shots")
    axes[1].set_title("σ against the device time")
    axes[1].legend(loc="center left", bbox_to_anchor=(1.02, 0.5), fontsize=7, frameon=False)
    cap = (f"The median 1σ of each map over the round's sample pixels after each of the {len(rounds)} rounds "
           "(one marker per round), on a log axis, each map in its own unit (the legend: degrees for the normal "
           "and the tangent, η for the IOR, the map's own value for the others), against the shots taken (left) "
           "and the device time spent so far (right: the shots' physical floor, settle, servo moves, exposures "
           "and readout, without metering).")
    if full:
        cap += (" Dashed: each map's median 1σ that the whole candidate plan would give, predicted at the last "
                "decision from the maps then (the fit's posterior with every remaining candidate's information "
                f"added); dotted: the whole plan's {fmt.value(full.get('shots'))} shots and its estimated "
                f"{fmt.quantity(full.get('cost_s'), 's')} of device time.")
    if missing:
        cap += (f" A gap: the map was not fitted in that round ({', '.join(missing)}: the round's component "
                "choice left it out).")
    return fig, cap


def dome_figure(dirs, candidates: list[int], chosen: dict[int, int], n_rounds: int):
    """The dome from above: ``dirs`` ``(N, 3)`` unit LED directions (x right, y up, the zenith at
    the centre), every LED a small grey dot, the ``candidates`` outlined, ``chosen`` (LED ->
    the round that took it) filled in :data:`ROUNDS_CMAP` with a colour bar of the rounds
    0..``n_rounds - 1``.  Returns ``(fig, caption)``."""
    plt = plots._plt()
    d = np.asarray(dirs, dtype=np.float64)
    fig = plots.figure(4.6, 3.9)
    ax = fig.subplots()
    ax.add_patch(plt.Circle((0, 0), 1.0, fill=False, color="0.75", lw=0.8))
    ax.scatter(d[:, 0], d[:, 1], s=5, c="0.7", lw=0, label=f"LED ({len(d)})", zorder=1)
    cand = [c for c in candidates if 0 <= c < len(d)]
    ax.scatter(d[cand, 0], d[cand, 1], s=46, facecolors="none", edgecolors="0.25", lw=0.9,
               label=f"candidate ({len(cand)})", zorder=2)
    leds = [c for c in chosen if 0 <= c < len(d)]
    norm = plt.Normalize(-0.5, max(n_rounds, 1) - 0.5)
    cmap = plt.get_cmap(ROUNDS_CMAP, max(n_rounds, 1))
    sc = ax.scatter(d[leds, 0], d[leds, 1], s=34, c=[chosen[c] for c in leds], cmap=cmap, norm=norm,
                    edgecolors="0.25", lw=0.5, label=f"chosen ({len(leds)})", zorder=3)
    cb = fig.colorbar(sc, ax=ax, shrink=0.9, pad=0.02, ticks=range(max(n_rounds, 1)))
    cb.set_label("round that took the LED")
    ax.set_aspect("equal")
    ax.set_xlim(-1.08, 1.08)
    ax.set_ylim(-1.08, 1.08)
    ax.set_xlabel("x (direction cosine)")
    ax.set_ylabel("y (direction cosine)")
    ax.set_title("LEDs chosen, dome from above")
    ax.legend(loc="upper left", bbox_to_anchor=(0.0, -0.16), ncol=3, fontsize=7, frameon=False)
    cap = (f"The dome seen from above: the x-y projection of the {len(d)} LEDs' unit directions (the zenith at the "
           f"centre, the horizon on the grey circle), each a small grey dot; the {len(cand)} candidates (the plan's "
           f"LEDs) outlined; the {len(leds)} LEDs taken filled in the colour of the round that took them (round 0 "
           "is the initial spread). The back light, taken in round 0, is under the sample and not drawn.")
    return fig, cap


def section(run: Path, fig: Callable[..., Any], note: Callable[[str], None]) -> dict[str, Any] | None:
    """The section's content: ``{"info": rows, "table": {"header", "rows", "numeric"}, "stop":
    text, "figs": [...]}``, or ``None`` without an adaptive record (:func:`read_record`).
    ``fig((figure, caption), stem, title)`` saves a figure and returns what the page shows
    (the run report's helper around ``Assets.figure``)."""
    from dualscale.geometry.dome import DomeGeometry

    rec = read_record(run, note)
    if rec is None:
        return None
    rounds = fitted_rounds(rec)
    chosen = {int(led): int(r.get("round", i)) for i, r in enumerate(rounds) for led in (r.get("leds") or [])}
    dirs = DomeGeometry.from_regmap().led_dirs.numpy()
    full = last_full_plan(rec)
    figs = [fig(sigma_rounds_figure(rounds, full), "adaptive_sigma", "Median σ per round"),
            fig(dome_figure(dirs, rec["candidates"], chosen, len(rounds)), "adaptive_dome", "LEDs chosen per round")]
    header = ["round", "LEDs taken", "shots", "device time"] + [
        f"median σ {plots.MAP_TITLES.get(n, n)}" + (f" [{plots.sigma_unit(n)}]" if n in plots.SIGMA_SHORT_UNITS else "")
        for n in TABLE_MAPS]
    rows = []
    for r in rounds:
        fit = r["fit"]
        sig = fit.get("sigma") or {}
        leds = r.get("leds") or []
        rows.append([fmt.value(r.get("round")), ", ".join(str(x) for x in leds) + (" + back light" if r.get("round") == 0 else ""),
                     fmt.value(fit.get("shots")), fmt.quantity(fit.get("floor_s"), "s")]
                    + [fmt.number(sig[n]) if isinstance(sig.get(n), (int, float)) else "not fitted" for n in TABLE_MAPS])
    opts = rec.get("options") if isinstance(rec.get("options"), dict) else {}
    budget = [f"{opts['budget_shots']} shots" if opts.get("budget_shots") else "",
              fmt.duration(opts["budget_s"]) if opts.get("budget_s") else ""]
    targets = opts.get("targets") or {}
    info = [("rounds", fmt.number(len(rounds))),
            ("candidates (the plan's LEDs)", fmt.number(len(rec["candidates"]))),
            ("shots taken", fmt.value(rec.get("shots"))),
            ("device time (physical floor)", fmt.quantity(rec.get("floor_s"), "s")),
            ("criterion", f"{opts.get('criterion', fmt.DASH)}-optimal gain per second of device time"),
            ("budget", " and ".join(b for b in budget if b) or "none"),
            ("targets (median σ)", ", ".join(
                [f"{plots.MAP_TITLES.get(k, k)} {fmt.number(v)}" for k, v in targets.items()]
                + ([f"every {'other ' if targets else ''}map within {fmt.number(100 * opts['full_target'])} % of the "
                    "whole plan's predicted σ"]
                   if isinstance(opts.get("full_target"), (int, float)) else [])) or "none")]
    if full:
        ratio = {k: full["sigma_now"][k] / v for k, v in (full.get("sigma") or {}).items()
                 if isinstance(v, (int, float)) and v > 0 and isinstance((full.get("sigma_now") or {}).get(k), (int, float))}
        worst = max(ratio, key=ratio.get) if ratio else None
        info.append(("the whole candidate plan (predicted)",
                     f"{fmt.value(full.get('shots'))} shots, about {fmt.quantity(full.get('cost_s'), 's')} of device time"
                     + (f"; at the last decision the worst map, {plots.MAP_TITLES.get(worst, worst)}, had "
                        f"{fmt.number(ratio[worst])} times its predicted σ" if worst else "")))
    stop = f"Stopped ({rec.get('stop', fmt.DASH)}): {rec.get('reason', 'no reason recorded')}."
    return {"info": info, "table": {"header": header, "rows": rows, "numeric": set(range(2, len(header)))},
            "stop": stop, "figs": figs}
