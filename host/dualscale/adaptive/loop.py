"""Adaptive micro capture (issue 27): capture a round of lights, fit, choose the next, stop when
the maps are determined.  ``dualscale capture micro --adaptive`` and ``digitize --rig ... --adaptive``.

The candidates are the micro plan's LEDs (``--lights``), each taken at P0 and P90 (two shots);
the back light is always taken, in the first round (both modes: how an opaque sample shows it).

1. **Round 0**: :attr:`AdaptiveOptions.initial` LEDs spread over the dome by farthest-point
   sampling of their directions from the one nearest the zenith (deterministic), and the back light.
2. **After each round**: its own shots are merged and calibrated (the capture's own HDR merge,
   then :func:`dualscale.calib.apply.to_radiance` with the rig's calibration) into a temporary
   dataset and read at a regular grid of at most :attr:`AdaptiveOptions.sample_pixels` pixels
   (each image once, whatever the rounds: :func:`concat_images` joins the rounds' samples); the
   sample of every round so far is fitted
   with the ``standard`` preset (components chosen on the sample; from round 1 a warm start: the
   joint step only, from the last round's maps, while the components stay the same), with its
   per-pixel uncertainty (:mod:`dualscale.fit.uncertainty`).
3. **Stop**, first of: every map's median sigma at or under its target (:attr:`AdaptiveOptions.targets`,
   map units as ``fit.json``'s) and, with :attr:`AdaptiveOptions.full_target` (default ``full+5%``),
   every other map's predicted median sigma within that fraction of what the whole candidate
   plan would give (:func:`.design.predicted_sigmas`: the fit's posterior with every remaining
   candidate's information added, at the current maps; each decision records it with the whole
   plan's estimated device time, ``full_plan``); the best candidate's D-gain under
   :attr:`AdaptiveOptions.min_gain` nats per sample pixel (no light improves the criterion enough);
   the shot budget or the device-time budget (the next batch would exceed it); no candidate left.
4. **Else choose** the next batch (:func:`.design.choose_batch`: greedy D- or A-optimal gain per
   second of device time over the sample's pixels) and take it: its P0 shots, then its P90
   shots (one servo move each way per round; the batch size, unless given, makes the two moves
   at most 10 % of the batch's device time: :func:`auto_batch`).

**Device time** is the physical floor of the shots in the order taken (settle, servo moves,
exposures, readout gaps: :meth:`dualscale.capture.session.CaptureSession.floor_s`), metering
not included; a candidate's cost is the median floor of the LED pairs taken in its dome ring
(else of all taken pairs).

**Recorded and resumable.**  The capture's journal holds an ``adaptive`` entry (the options;
a resume with others is refused), one ``round`` entry per decision written *before* its shots
are taken (the LEDs, why, every candidate's score and cost, the picks' gains), and one ``fit``
entry per round (shots, device time, the median sigma per map, the components).  ``--resume``
after a kill reuses every journaled decision and recomputes the fit of a round whose next
decision is not journaled yet; the fits are deterministic (fixed seed, the same data), so the
decisions are those of an uninterrupted capture.  ``capture.json`` gets the ``adaptive`` record
(options, rounds, stop reason).  The dataset is a normal photometric dataset of the shots
taken: ``fit`` and ``propagate`` read it like any other.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from dualscale.errors import InputError
from dualscale.geometry.dome import DomeGeometry, ring_layout
from dualscale.protocol import regmap as rm

from .options import AdaptiveOptions, _jsonable, option_differences  # noqa: F401  (AdaptiveOptions re-exported)

ROUND_DIR = "adaptive"


def spread_leds(candidates: list[int], n: int, dirs: np.ndarray) -> list[int]:
    """``n`` of ``candidates`` spread over the dome: farthest-point sampling of their directions
    (``dirs`` indexed by LED id), from the candidate nearest the zenith; ties to the lower id."""
    cand = sorted(candidates)
    if n >= len(cand):
        return cand
    d = np.asarray(dirs, np.float64)[cand]
    picked = [int(np.argmax(d[:, 2]))]
    dist = np.arccos(np.clip(d @ d[picked[0]], -1, 1))
    while len(picked) < n:
        j = int(np.argmax(dist))
        picked.append(j)
        dist = np.minimum(dist, np.arccos(np.clip(d @ d[j], -1, 1)))
    return sorted(cand[j] for j in picked)


#: the fewest LEDs a round takes by default: each round costs the host a merge, a calibration
#: and a fit of the sample (seconds), which a round of a few seconds of device time would not pay for
MIN_BATCH = 4


def auto_batch(pair_s: float, servo_s: float) -> int:
    """LEDs per round so that the round's two servo moves (``servo_s`` each) are at most 10 % of
    its device time (``pair_s`` per LED, both modes), between :data:`MIN_BATCH` and 16."""
    return int(min(16, max(MIN_BATCH, math.ceil(2 * servo_s / (0.1 * max(pair_s, 1e-9))))))


def ring_of() -> dict[int, int]:
    """LED id -> its dome ring (0 = zenith; the regmap ring layout)."""
    return {k: int(row) for k, (row, _theta, _phi) in enumerate(ring_layout())}


class AdaptiveCapture:
    """The rounds of one adaptive capture (module doc) on an opened
    :class:`~dualscale.capture.session.CaptureSession` of the micro plan (its candidates).
    ``calibration``: the rig's calibration file (each round is calibrated with it); ``log``:
    called with one line per round."""

    def __init__(self, session, calibration: str | Path, opts: AdaptiveOptions,
                 log: Callable[[str], None] | None = None) -> None:
        if session.plan.name != "micro":
            raise InputError("--adaptive captures the micro plan only")
        self.s, self.cal, self.opts = session, Path(calibration), opts
        self.log = log or (lambda _line: None)
        self.dirs = DomeGeometry.from_regmap().led_dirs.numpy()
        self.ring = ring_of()
        self.leds = sorted({sh.index for sh in session.plan.shots if sh.kind == "led"})
        if len(self.leds) < opts.initial:
            raise InputError(f"--adaptive: --lights gives {len(self.leds)} LEDs, fewer than --initial-leds {opts.initial}")
        check_calibration(self.cal, self.leds, session.rig_record())
        ident = {k: v for k, v in asdict(opts).items()}
        starts = session.journal.of("adaptive")
        if starts and starts[0]["options"] != _jsonable(ident):
            diff = option_differences(starts[0]["options"], _jsonable(ident))
            raise InputError(f"{session.work}: --resume with other adaptive options than the capture there: "
                             f"{'; '.join(diff)}; use the same options or another folder")
        if not starts:
            session.journal.append("adaptive", options=_jsonable(ident))
        self._fit_cache: dict[int, tuple] = {}
        self._sample_cache: dict[int, Any] = {}

    # ------------------------------------------------------------------ shots
    def _shots(self, leds: list[int], back: bool) -> list:
        keep = set(leds)
        return [sh for sh in self.s.plan.shots if (sh.kind == "led" and sh.index in keep) or (back and sh.kind == "backlight")]

    def _taken(self, rounds: list[dict]) -> list:
        out = []
        for r in rounds:
            out += self._shots(r["leds"], r["round"] == 0)
        return out

    # ------------------------------------------------------------------ fit of the rounds so far
    def _fit(self, r: int, rounds: list[dict]) -> tuple:
        """The fit after round ``r`` (rounds[: r + 1] taken): ``(params, comps, sample, preset,
        sigma medians, fit record)``; cached."""
        if r in self._fit_cache:
            return self._fit_cache[r]
        from dualscale.fit.core import fit_observations
        from dualscale.fit.params import params_from_maps
        from dualscale.fit.presets import get_preset
        from dualscale.fit.select import select_components
        from dualscale.fit.uncertainty import median_sigmas

        taken = self._taken(rounds[:r + 1])
        sample = concat_images([self._round_sample(k, rounds[k]) for k in range(r + 1)])
        comps, _ = select_components(sample, seed=self.opts.seed)
        preset = get_preset("standard")
        init = None
        prev = self._fit(r - 1, rounds) if r > 0 else None  # the same chain of warm starts after a resume
        if prev is not None and prev[1] == comps:
            init = prev[0]
            preset = replace(preset, name="standard-warm", iterations=(0, 0, preset.iterations[2]), grid_init=False)
        res = fit_observations(sample, preset, comps, seed=self.opts.seed, init=init, uncertainty=True)
        params = params_from_maps(res.maps, comps)
        sig = {k: v for k, v in median_sigmas(res.uncertainty).items() if v is not None}
        rec = {"round": r, "shots": len(taken), "floor_s": round(self.s.floor_s(taken), 6),
               "sigma": {k: float(v) for k, v in sig.items()}, "components": comps.__dict__,
               "sample_pixels": int(sample.images.shape[2]), "warm": init is not None}
        self._fit_cache[r] = (params, comps, sample, get_preset("standard"), sig, rec)
        return self._fit_cache[r]

    def _round_sample(self, r: int, rnd: dict) -> Any:
        """Round ``r``'s shots alone, merged and calibrated into a temporary dataset and read at
        the sample pixels only (a regular grid of at most ``sample_pixels``): each round's images
        are read once, at their own size, not every shot taken so far at every round; cached."""
        if r in self._sample_cache:
            return self._sample_cache[r]
        import torch

        from dualscale.calib.apply import to_radiance
        from dualscale.fit.observations import load_observations

        tmp = Path(tempfile.mkdtemp(prefix=f"round{r:02d}-", dir=self._round_root()))
        try:
            self.s.merge(self._shots(rnd["leds"], r == 0), tmp / "raw")
            to_radiance(tmp / "raw", tmp / "radiance", self.cal)
            obs = load_observations(tmp / "radiance")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        h, w = obs.shape
        step = max(1, math.ceil(math.sqrt(h * w / self.opts.sample_pixels)))
        ys, xs = torch.meshgrid(torch.arange(step // 2, h, step), torch.arange(step // 2, w, step), indexing="ij")
        self._sample_cache[r] = obs.pixels((ys * w + xs).reshape(-1))
        return self._sample_cache[r]

    def _round_root(self) -> Path:
        root = self.s.work / ROUND_DIR
        root.mkdir(parents=True, exist_ok=True)
        return root

    # ------------------------------------------------------------------ decisions
    def _costs(self, taken_leds: list[int], cands: list[int]) -> np.ndarray:
        """Each candidate's device time [s] (module doc, "Device time")."""
        pairs: dict[int, float] = {}
        for led in taken_leds:
            sh = self._shots([led], False)
            pairs[led] = sum(self.s.floor_s([x], start_cdeg=x.analyzer_cdeg) for x in sh)
        allp = float(np.median(list(pairs.values())))
        out = []
        for c in cands:
            same = [v for k, v in pairs.items() if self.ring[k] == self.ring[c]]
            out.append(float(np.median(same)) if same else allp)
        return np.asarray(out)

    def _servo_s(self) -> float:
        from dualscale.rig.sequence import servo_travel_us

        return (servo_travel_us(rm.POL_P0_CDEG, rm.POL_P90_CDEG) + self.s.opts.servo_margin_us) / 1e6

    def _decide(self, r: int, rounds: list[dict]) -> dict:
        """The decision after round ``r - 1``: the journal's ``round`` entry for round ``r`` (a
        ``stop`` entry has ``leds`` empty and the ``reason``)."""
        from .design import (candidate_information, candidate_observations, choose_batch, design_state,
                             predicted_sigmas)

        params, comps, sample, preset, sig, rec = self._fit(r - 1, rounds)
        taken_leds = sorted({i for x in rounds for i in x["leds"]})
        shots = rec["shots"]
        given = self.opts.targets
        met = all(k in sig and sig[k] <= t for k, t in given.items())
        if given and met and self.opts.full_target is None:
            return {"round": r, "leds": [], "stop": "targets", "reason": f"every named map ({', '.join(given)}) reached "
                    "its target sigma"}
        cands = [i for i in self.leds if i not in set(taken_leds)]
        if not cands:
            return {"round": r, "leds": [], "stop": "candidates", "reason": "every candidate LED is taken"}
        if r >= self.opts.max_rounds:
            return {"round": r, "leds": [], "stop": "rounds", "reason": f"{self.opts.max_rounds} rounds"}
        costs = self._costs(taken_leds, cands)
        st = design_state(params, comps, sample, preset)
        info = candidate_information(st, params, comps,
                                     candidate_observations(sample, self.dirs[cands], cands))
        # what the whole candidate plan would give and cost, predicted at the current maps
        now, full = predicted_sigmas(st, params, comps), predicted_sigmas(st, params, comps, info.sum(1))
        size = self.opts.batch or auto_batch(float(np.median(costs)), self._servo_s())
        rounds_left = math.ceil(len(cands) / size)  # each round turns the analyser there and back
        plan = {"sigma": {k: round(v, 6) for k, v in full.items()}, "sigma_now": {k: round(v, 6) for k, v in now.items()},
                "cost_s": round(rec["floor_s"] + float(costs.sum()) + 2 * rounds_left * self._servo_s(), 6),
                "shots": shots + 2 * len(cands)}
        if self.opts.full_target is not None and met:
            slack = 1.0 + self.opts.full_target
            # a map the whole plan would determine and the lights taken do not is not within any slack
            rel = {k: now[k] / full[k] if k in now else math.inf for k in full if k not in given and full[k] > 0}
            if all(v <= slack for v in rel.values()):
                worst = max(rel, key=rel.get) if rel else None
                why = (f"every map's predicted sigma within {100 * self.opts.full_target:g} % of the whole plan's"
                       + (f" (worst {worst}: {100 * (rel[worst] - 1):.1f} %)" if worst else ""))
                if given:
                    why = why.replace("every map's", "every other map's") + (f"; the named ({', '.join(given)}) "
                                                                             "reached their target sigma")
                return {"round": r, "leds": [], "stop": "targets", "reason": why, "full_plan": plan}
        if self.opts.budget_shots is not None:
            size = min(size, (self.opts.budget_shots - shots) // 2)
        if self.opts.budget_s is not None:
            left = self.opts.budget_s - rec["floor_s"] - 2 * self._servo_s()
            size = min(size, int(left // max(float(np.median(costs)), 1e-9)))
        if size < 1:
            why = "the budget leaves no room for another LED"
            if self.opts.budget_s is not None and rec["floor_s"] > self.opts.budget_s:
                why += (f" (the first {r} round(s) alone took {rec['floor_s']:.1f} s of device time, over the "
                        f"{self.opts.budget_s:g} s budget: round 0's spread is taken whole)")
            return {"round": r, "leds": [], "stop": "budget", "reason": why, "full_plan": plan}
        picked, got, first = choose_batch(st, info, costs, size, self.opts.criterion)
        npx = st.x.shape[0]
        best = float(first.max()) / npx
        scores = {str(c): {"gain": round(float(first[j]) / npx, 6), "cost_s": round(float(costs[j]), 6)}
                  for j, c in enumerate(cands)}
        if best < self.opts.min_gain:
            return {"round": r, "leds": [], "stop": "gain", "scores": scores, "full_plan": plan,
                    "reason": f"the best candidate's gain {best:.3g} nats per pixel is under {self.opts.min_gain:g}"}
        return {"round": r, "leds": sorted(cands[j] for j in picked), "why": f"best {self.opts.criterion}-gain per second",
                "picks": [[cands[j], round(g / npx, 6)] for j, g in zip(picked, got)], "scores": scores,
                "full_plan": plan}

    # ------------------------------------------------------------------ the capture
    def run(self):
        """Capture round by round until a stop rule holds (module doc); merge the dataset of every
        shot taken and write ``capture.json`` with the ``adaptive`` record.  Returns the session's
        :class:`~dualscale.capture.session.CaptureSummary`."""
        journal = self.s.journal
        rounds = [e for e in journal.of("round")]
        fits = {e["round"]: e for e in journal.of("fit")}
        if not rounds:
            first = spread_leds(self.leds, self.opts.initial, self.dirs)
            journal.append("round", round=0, leds=first, why=f"{self.opts.initial} LEDs spread over the dome")
            rounds = journal.of("round")
        for x in rounds[:-1]:  # a resume: the rounds before the last are in the journal whole; take()
            if not x.get("stop"):  # finds them there and counts them in the capture's summary
                self.s.take(self._shots(x["leds"], x["round"] == 0))
        stop = None
        while True:
            cur = rounds[-1]
            if cur.get("stop"):
                stop = cur
                break
            self.s.take(self._shots(cur["leds"], cur["round"] == 0))
            nxt = cur["round"] + 1
            if cur["round"] not in fits:
                rec = self._fit(cur["round"], rounds)[5]
                journal.append("fit", **rec)
                fits[cur["round"]] = rec
            f = fits[cur["round"]]
            absent = sorted(k for k in self.opts.targets if k not in f["sigma"])
            if absent and cur["round"] == 0:
                self.log(f"warning: the fit of this sample has no sigma of {', '.join(absent)} (not among its "
                         "components, or undetermined everywhere): the target cannot stop the capture; the gain "
                         "and budget rules still do")
            self.log(f"round {cur['round']}: {len(cur['leds'])} LEDs, {f['shots']} shots, device {f['floor_s']:.1f} s; "
                     "median sigma " + ", ".join(f"{k} {v:.3g}" for k, v in sorted(f["sigma"].items())))
            decision = self._decide(nxt, rounds)
            if decision["leds"]:
                self.log(f"round {nxt}: LEDs {decision['leds']} (gain {decision['picks'][0][1]:.3g} nats per pixel "
                         f"for the first pick)")
            journal.append("round", **decision)
            rounds = journal.of("round")
        taken = self._taken([x for x in rounds if not x.get("stop")])
        record = {"options": _jsonable(asdict(self.opts)), "stop": stop["stop"], "reason": stop["reason"],
                  "rounds": [{**{k: v for k, v in x.items() if k != "kind"},
                              **({"fit": fits.get(x["round"])} if x["round"] in fits else {})} for x in rounds],
                  "shots": len(taken), "floor_s": round(self.s.floor_s(taken), 6)}
        self.log(f"stopped: {stop['reason']} ({record['shots']} shots, device time {record['floor_s']:.1f} s)")
        shutil.rmtree(self.s.work / ROUND_DIR, ignore_errors=True)
        return self.s.finish(taken=taken, adaptive=record)


def concat_images(parts: list) -> Any:
    """The :class:`~dualscale.fit.observations.Observations` of ``parts`` (the rounds' samples,
    the same pixels) one after the other along the image axis; the back light, its weights and
    the view are the first part's (round 0 takes the back light)."""
    import torch

    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    cat = lambda name: torch.cat([getattr(o, name) for o in parts])  # noqa: E731
    valid = None
    if any(o.valid is not None for o in parts):
        valid = torch.cat([o.valid if o.valid is not None else torch.ones(o.images.shape[:3], dtype=torch.bool)
                           for o in parts])
    scale = None
    if all(o.signal_scale is not None for o in parts):
        scale = cat("signal_scale")
    return replace(first, images=cat("images"), dirs=cat("dirs"), w_s=cat("w_s"), w_p=cat("w_p"), w_d=cat("w_d"),
                      led_ids=cat("led_ids"), valid=valid, signal_scale=scale, origin=None)


def check_calibration(path: Path, leds: list[int], rig: dict[str, str] | None = None) -> None:
    """Before the first shot: the calibration covers every candidate LED (each round is calibrated
    with it), else :class:`~dualscale.errors.CalibrationError` naming the LEDs it lacks; and,
    with ``rig`` (``{"id", "layout"}``, :meth:`~dualscale.capture.session.CaptureSession.rig_record`),
    it is this rig's, else :class:`~dualscale.errors.RigMismatchError` naming ``--rig-id``."""
    from dualscale.capture.stage import calibrated_leds
    from dualscale.errors import CalibrationError, RigMismatchError
    from dualscale.formats.calibration import read_calibration

    try:
        cal = read_calibration(path, rig_id=None if rig is None else rig["id"],
                               layout=None if rig is None else rig["layout"])
    except RigMismatchError as e:
        raise RigMismatchError(f"{e}: every round is calibrated with it, so it is refused before the first shot; "
                               "give the rig's --rig-id as it was at calibration, or calibrate this rig") from None
    have = calibrated_leds(cal)
    missing = sorted(set(leds) - have) if have is not None else []
    if missing:
        raise CalibrationError(f"{path}: no white-sheet capture for LED(s) {missing[:8]}{' ...' if len(missing) > 8 else ''} "
                               "of the adaptive capture's candidates (--lights): calibrate those lights, or choose "
                               "--lights the calibration covers")
