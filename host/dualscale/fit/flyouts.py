"""Fly-out fibre detection (supplementary Sec. 4.1), on the micro camera's LED images.

1. Confidence ``C = max over the most grazing ring (grazing capture) - most orthogonal
   capture``, luminance, clipped at 0, in the analyser mode that passes the specular (our P0:
   analyser aligned with the LED polariser; the paper's labels call that mode P90).  The max
   over the grazing ring lights fibres of every azimuth.
2. Probabilities ``p = C / sum(C)``.
3. ``seeds`` positions drawn from ``p``; ``seeds`` is given for a 1-Mpx image and scaled with the
   pixel count (10,000 by default; at least 50).
4. From each seed, trace both ways along the path of minimum gradient: start along the ridge
   (minor eigenvector of the structure tensor of the smoothed map), then repeatedly step to
   the forward 8-neighbour (within 60 deg of the current heading) with the smallest gradient
   magnitude, while the smoothed confidence stays above both ``stop_fraction`` of the seed's
   and the map's mean plus one standard deviation (seeds in the background stop at once).
5. Drop paths shorter than ``min_length_mm`` (0.27 mm) / pixel pitch.
6. With a tangent map, drop paths whose mean axis is within ``yarn_angle_deg`` of the yarn
   axis under them (the axial mean of the tangent in a band 2-5 px around the path).
7. Longest first, drop a path when half of its pixels are already covered (dilated by 1 px).
   (A seed that lands on a long path already traced is skipped: it could only yield a
   duplicate.  This keeps the cost proportional to the number of fibres, not of seeds.)

Scoring against a ground-truth mask uses a tolerance of ``tol_px``: precision is the share of
detected fibre pixels within it of a true fibre, recall the share of true fibre pixels within
it of a detection.

Resolvability (:func:`resolvability`): a fibre of :data:`FIBRE_DIAMETER_MM` is resolved when it
is at least :data:`RESOLVED_TEXELS` texels across.  In production there is no ground truth, so
the record states that criterion and the precision and recall measured on the simulated rig in
the nearest regime (:data:`SIMULATED`, from ``bench/bench_flyouts.py --resolution``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage
from skimage.draw import line

from dualscale.errors import InputError
from dualscale.progress import Progress, iterate

#: The diameter of a fly-out fibre assumed where none is measured [mm]: 12 um, a cotton fibre (textile
#: fibres are 10-20 um across) and the simulator's fibre (``sim.materials.fabrics.add_flyouts``).
FIBRE_DIAMETER_MM = 0.012

#: A fibre is resolved when it is at least this many texels across: the smallest ratio measured
#: at which the median precision is above 0.85 and every simulated row scored at least 0.73
#: (:data:`SIMULATED`); below it, precision falls to 0.4-0.7 and recall to 0.1-0.4.
RESOLVED_TEXELS = 5.0

#: Detection on the simulated rig per regime: ``(fibre diameter / texel, median precision, lowest
#: and highest precision, median recall, rows, rows with a detection)``; precision is the share of
#: the detected polylines' pixels within 2 px of a true fibre (over the rows with a detection),
#: recall the share of the true centre lines within 2 px of a detection.
SIMULATED = (
    (6.67, 0.93, 0.78, 0.94, 0.64, 4, 4),
    (5.00, 0.89, 0.73, 1.00, 0.60, 12, 12),
    (3.33, 0.62, 0.46, 1.00, 0.33, 12, 12),
    (2.50, 0.58, 0.34, 0.88, 0.38, 12, 12),
    (1.67, 0.73, 0.37, 1.00, 0.20, 12, 10),
    (1.25, 0.39, 0.32, 0.55, 0.08, 12, 7),
)
SIMULATED_SOURCE = ("bench/bench_flyouts.py --resolution 1.8,2.4,3.6,4.8,7.2,9.6: twill, plain, satin and denim, "
                    "seeds 0-2 (1.8 um: twill 0-2 and plain 0), a 0.69 mm field, 12 um fibres, the true tangent, "
                    "sensor noise; 2026-12-02 (docs/FITTING.md)")

_DIRS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]  # (drow, dcol)


def confidence_map(obs) -> np.ndarray:
    """Step 1 from :class:`~dualscale.fit.observations.Observations` ``(H, W)``."""
    import torch

    spec = obs.select(torch.nonzero(obs.w_s > 0.5).flatten()) if bool((obs.w_s > 0.5).any()) else obs
    z = spec.dirs[:, 2]
    y = spec.images.mean(-1)
    grazing = y[z <= z.min() + 1e-3].max(0).values
    ortho = y[int(torch.argmax(z))]
    return (grazing - ortho).clamp(min=0).to(torch.float64).numpy()


def confidence_by_bands(origin, boxes: list[tuple[int, int, int, int]], shape: tuple[int, int]) -> np.ndarray:
    """:func:`confidence_map` ``(H, W)`` of a micro capture too large to load (issue 25): the
    lowest ring's and the most vertical LED's images only (of the observations ``origin``, a
    :class:`~dualscale.fit.observations.DatasetOrigin`), read a part of ``boxes`` at a time.  The
    same values as the whole map's: the map is per pixel."""
    from dataclasses import replace

    import torch

    from .observations import read_tile

    head = read_tile(origin, (0, 1, 0, 1))
    spec = head.select(torch.nonzero(head.w_s > 0.5).flatten()) if bool((head.w_s > 0.5).any()) else head
    z = spec.dirs[:, 2]
    ids = set(spec.led_ids[z <= z.min() + 1e-3].tolist()) | {int(spec.led_ids[int(torch.argmax(z))])}
    few = replace(origin, leds=tuple(sorted(ids)))
    conf = np.empty(shape, np.float64)
    for y0, y1, x0, x1 in boxes:
        conf[y0:y1, x0:x1] = confidence_map(read_tile(few, (y0, y1, x0, x1)))
    return conf


def _raster(path: list[tuple[float, float]], shape: tuple[int, int]) -> np.ndarray:
    m = np.zeros(shape, bool)
    for (r0, c0), (r1, c1) in zip(path[:-1], path[1:]):
        rr, cc = line(int(round(r0)), int(round(c0)), int(round(r1)), int(round(c1)))
        ok = (rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])
        m[rr[ok], cc[ok]] = True
    if len(path) == 1:
        m[int(path[0][0]), int(path[0][1])] = True
    return m


def _length(path: list[tuple[float, float]]) -> float:
    p = np.asarray(path, float)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def _trace(start: tuple[int, int], heading: np.ndarray, conf: np.ndarray, grad: np.ndarray, floor: float,
           max_steps: int, max_gap: int = 0) -> list[tuple[int, int]]:
    """Follow the path of minimum gradient from ``start``: step to the forward 8-neighbour
    (within 60 deg of the smoothed heading) with the smallest gradient magnitude among those
    whose confidence is at least ``floor``.  Where none is, cross a gap of up to ``max_gap``
    pixels straight ahead (a fibre's highlight is dashed where its normal turns away); the
    gap is kept only when the fibre resumes after it."""
    h, w = conf.shape
    r, c = start
    d = heading / max(np.linalg.norm(heading), 1e-12)
    out: list[tuple[int, int]] = []
    seen = {start}
    gap: list[tuple[int, int]] = []
    for _ in range(max_steps):
        best, best_g, ahead, ahead_dot = None, math.inf, None, -2.0
        for dr, dc in _DIRS:
            v = np.array([dr, dc], float) / math.hypot(dr, dc)
            dot = float(v @ d)
            if dot < 0.5:  # within 60 deg of the heading
                continue
            q = (r + dr, c + dc)
            if not (0 <= q[0] < h and 0 <= q[1] < w) or q in seen:
                continue
            if dot > ahead_dot:
                ahead, ahead_dot = q, dot
            if conf[q] >= floor and grad[q] < best_g:
                best, best_g = q, grad[q]
        if best is None:
            if ahead is None or len(gap) >= max_gap:
                break
            gap.append(ahead)
            best = ahead
        else:
            out.extend(gap)
            gap = []
            out.append(best)
        step = np.array([best[0] - r, best[1] - c], float)
        d = 0.7 * d + 0.3 * step / np.linalg.norm(step)  # smoothed heading
        d /= np.linalg.norm(d)
        r, c = best
        seen.add(best)
    return out


def yarn_field(tangent: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Local yarn axis as a doubled-angle vector field ``(sin 2a, cos 2a)`` smoothed over
    ``sigma_px``: the fibres' twist about the yarn axis averages out inside a yarn, and where
    warp meets weft the two cancel (a short vector: no clear yarn direction)."""
    a = 2 * np.pi * np.asarray(tangent, float)  # tangent value v is azimuth pi v; doubled for an axial mean
    return (ndimage.gaussian_filter(np.sin(a), sigma_px, mode="wrap"),
            ndimage.gaussian_filter(np.cos(a), sigma_px, mode="wrap"))


def along_yarn(path: list[tuple[int, int]], field: tuple[np.ndarray, np.ndarray], yarn_angle_deg: float,
               reach_px: float) -> np.ndarray:
    """Which points of a path run within ``yarn_angle_deg`` of the yarn beside them (bool).

    The yarn under a fly-out is read beside it, not on it (a fitted tangent map follows the
    fibre's own texels): ``field`` (:func:`yarn_field`) is sampled across the path from just
    outside its footprint out to ``reach_px`` on either side.  A point runs along the yarn
    when either side does: a path on the boundary between warp and weft runs along one."""
    fs, fc = field
    h, w = fs.shape
    own = ndimage.binary_dilation(_raster(path, (h, w)), iterations=2)
    p = np.asarray(path, float)
    if len(p) < 3:
        return np.zeros(len(p), bool)
    d = np.gradient(ndimage.uniform_filter1d(p, 5, axis=0, mode="nearest"), axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    path_ang = np.arctan2(-d[:, 0], d[:, 1])  # y-up azimuth [rad]
    perp = np.stack([d[:, 1], -d[:, 0]], -1)  # (drow, dcol) across the path
    along = np.zeros(len(p), bool)
    for side in (1.0, -1.0):
        s2 = np.zeros(len(p))
        c2 = np.zeros(len(p))
        for k in np.linspace(3.0, max(3.0, reach_px), 4):
            q = np.rint(p + side * k * perp).astype(int)
            ok = (q[:, 0] >= 0) & (q[:, 0] < h) & (q[:, 1] >= 0) & (q[:, 1] < w)
            qr, qc = np.clip(q[:, 0], 0, h - 1), np.clip(q[:, 1], 0, w - 1)
            ok &= ~own[qr, qc]
            s2 += np.where(ok, fs[qr, qc], 0.0)
            c2 += np.where(ok, fc[qr, qc], 0.0)
        clear = np.hypot(s2, c2) > 0.5 * 4  # a clear yarn direction on this side
        yarn = 0.5 * np.arctan2(s2, c2)
        diff = np.abs((np.degrees(path_ang - yarn) + 90.0) % 180.0 - 90.0)
        along |= clear & (diff < yarn_angle_deg)
    return along


def _off_yarn(path: list[tuple[int, int]], along: np.ndarray, min_len: float) -> list[tuple[int, int]] | None:
    """``path`` without the stretches at its ends that run along the yarn (a trace that slid
    off a fly-out onto a yarn edge), or ``None`` when what is left is shorter than
    ``min_len`` or still runs along the yarn for half its points."""
    off = ~ndimage.binary_opening(along, structure=np.ones(5, bool))  # ignore isolated points
    idx = np.nonzero(off)[0]
    if len(idx) == 0:
        return None
    a, b = int(idx[0]), int(idx[-1]) + 1
    if _length(path[a:b]) < min_len or along[a:b].mean() >= 0.5:
        return None
    return path[a:b]


def detect(conf: np.ndarray, pixel_mm: float, seeds: int = 10000, min_length_mm: float = 0.27,
           tangent: np.ndarray | None = None, yarn_angle_deg: float = 15.0, stop_fraction: float = 0.35,
           seed: int = 0, max_gap_mm: float = 0.01, yarn_mm: float = 0.1, smooth_px: float = 1.0,
           orient_px: float = 2.0, progress: Progress = None) -> dict[str, Any]:
    """Steps 2-7 on a confidence map ``(H, W)``: polylines ``[(row, col), ...]``, mask, counts.
    ``progress`` (:mod:`dualscale.progress`): one unit per seed traced."""
    h, w = conf.shape
    conf = np.clip(np.nan_to_num(conf), 0, None)
    min_len = min_length_mm / pixel_mm
    max_gap = int(round(max_gap_mm / pixel_mm))
    n_seeds = max(50, int(round(seeds * h * w / 1e6)))
    out: dict[str, Any] = {"seeds": n_seeds, "min_length_px": min_len, "paths": [], "mask": np.zeros((h, w), bool),
                           "dropped": {"short": 0, "along_yarn": 0, "duplicate": 0}}
    total = conf.sum()
    if total <= 0:
        return out
    rng = np.random.default_rng(seed)
    picks = rng.choice(h * w, size=n_seeds, p=(conf / total).ravel())
    sm = ndimage.gaussian_filter(conf, smooth_px)
    global_floor = float(sm.mean() + sm.std())
    gr, gc = ndimage.sobel(sm, 0), ndimage.sobel(sm, 1)
    grad = np.hypot(gr, gc)
    jrr, jrc, jcc = (ndimage.gaussian_filter(a, orient_px) for a in (gr * gr, gr * gc, gc * gc))
    paths = []
    traced = np.zeros((h, w), bool)  # pixels of long paths already traced
    for k in iterate(progress, picks, "fly-out seeds", unit="seed"):
        r, c = divmod(int(k), w)
        if traced[r, c]:  # would only retrace a fibre already found (a duplicate, step 7)
            continue
        t = np.array([[jrr[r, c], jrc[r, c]], [jrc[r, c], jcc[r, c]]])
        _, vec = np.linalg.eigh(t)
        along = vec[:, 0]  # least change: along the ridge
        floor = max(stop_fraction * sm[r, c], global_floor)
        fwd = _trace((r, c), along, sm, grad, floor, int(4 * min_len) + 8, max_gap)
        bwd = _trace((r, c), -along, sm, grad, floor, int(4 * min_len) + 8, max_gap)
        path = [*reversed(bwd), (r, c), *fwd]
        paths.append(path)
        if _length(path) >= min_len:
            traced |= ndimage.binary_dilation(_raster(path, (h, w)))
    kept = []
    for p in paths:
        if _length(p) < min_len:
            out["dropped"]["short"] += 1
            continue
        kept.append(p)
    if tangent is not None:
        keep2 = []
        reach = yarn_mm / pixel_mm
        field = yarn_field(tangent, reach / 2)
        for p in kept:
            q = _off_yarn(p, along_yarn(p, field, yarn_angle_deg, reach), min_len)
            if q is None:
                out["dropped"]["along_yarn"] += 1
            else:
                keep2.append(q)
        kept = keep2
    covered = np.zeros((h, w), bool)
    final = []
    for p in sorted(kept, key=_length, reverse=True):
        m = _raster(p, (h, w))
        if (covered & m).sum() >= 0.5 * m.sum():
            out["dropped"]["duplicate"] += 1
            continue
        covered |= ndimage.binary_dilation(m)
        out["mask"] |= m
        final.append(p)
    out["paths"] = final
    return out


def score(mask: np.ndarray, gt: np.ndarray, tol_px: int = 2) -> dict[str, float]:
    """Precision and recall of detected fibre pixels with a ``tol_px`` buffer.

    Detections are 1-px polylines, true fibres have a footprint a few pixels wide, so (as for
    the completeness and correctness of extracted road networks) precision is the share of
    detected pixels within ``tol_px`` of a true fibre's footprint, and recall the share of
    the true fibres' centre lines (skeleton of the footprint) within ``tol_px`` of a
    detection."""
    from skimage.morphology import skeletonize

    gt = np.asarray(gt, bool)
    centre = skeletonize(gt) if gt.any() else gt
    gt_d = ndimage.binary_dilation(gt, iterations=tol_px) if tol_px > 0 else gt
    det_d = ndimage.binary_dilation(mask, iterations=tol_px) if tol_px > 0 else mask
    precision = float((mask & gt_d).sum() / mask.sum()) if mask.any() else 0.0
    recall = float((centre & det_d).sum() / centre.sum()) if centre.any() else 1.0
    return {"precision": precision, "recall": recall, "tolerance_px": tol_px}


#: The whole pipeline measured once on the simulated rig (``make demo``: ``digitize --rig sim``, twill,
#: 128 px of 7.2 um, 1.67 texels across, quality standard, the fitted tangent), scored against the
#: simulator's fibres: lower than :data:`SIMULATED`'s detector-only rows, which use the true tangent.
DEMO_PIPELINE = {"texels_across": 1.67, "precision": 0.15, "recall": 0.03, "fibres_true": 8, "fibres_detected": 2,
                 "source": "make demo (digitize --rig sim, twill 128 px of 7.2 um, standard), scored with "
                           "fit.flyouts.score against the simulator's mask; 2026-12-02 (docs/FITTING.md)"}


def resolvability(texel_mm: float, fibre_diameter_mm: float = FIBRE_DIAMETER_MM) -> dict[str, Any]:
    """Whether a texel of ``texel_mm`` (mm) resolves a fly-out fibre of ``fibre_diameter_mm``
    (mm; the default is assumed, not measured), and the precision measured on the simulated rig in
    the nearest regime (:data:`SIMULATED`, by the log of the ratio).  Returns ``{"fibre_diameter_mm",
    "fibre_diameter_source", "texel_mm", "texels_across", "criterion", "resolved",
    "simulated_precision": {"texels_across", "median", "range", "recall", "rows", "rows_detected",
    "tolerance_px", "source"[, "demo_pipeline": DEMO_PIPELINE, when under-resolved]}, "warning"}``;
    ``warning`` is ``None`` when resolved.  Raises ``ValueError`` for a texel or diameter that is
    not a positive number."""
    if not (texel_mm > 0 and fibre_diameter_mm > 0):
        raise ValueError(f"resolvability: texel {texel_mm} mm and fibre diameter {fibre_diameter_mm} mm must be > 0")
    across = fibre_diameter_mm / texel_mm
    row = min(SIMULATED, key=lambda r: abs(math.log(r[0] / across)))
    resolved = across >= RESOLVED_TEXELS
    sim = {"texels_across": row[0], "median": row[1], "range": [row[2], row[3]], "recall": row[4], "rows": row[5],
           "rows_detected": row[6], "tolerance_px": 2, "source": SIMULATED_SOURCE}
    if not resolved:
        sim["demo_pipeline"] = DEMO_PIPELINE
    warning = None
    if not resolved:
        warning = (f"the texel ({texel_mm * 1000:.3g} um) under-resolves the fly-out fibres: a fibre of "
                   f"{fibre_diameter_mm * 1000:.3g} um is {across:.2g} texels across, fewer than the {RESOLVED_TEXELS:g} "
                   f"they need; on the simulated rig at {row[0]:g} texels across, {row[1]:.0%} of the detected length "
                   f"lay within 2 px of a true fibre (from {row[2]:.0%} to {row[3]:.0%}) and a detection passed within "
                   f"2 px of {row[4]:.0%} of the true fibres' length (median recall), with the true tangent; the "
                   f"whole demo pipeline at {DEMO_PIPELINE['texels_across']:g} texels across found "
                   f"{DEMO_PIPELINE['fibres_detected']} of {DEMO_PIPELINE['fibres_true']} fibres at "
                   f"{DEMO_PIPELINE['precision']:.0%} precision. Read the count and the polylines as indicative, and capture "
                   f"at {fibre_diameter_mm / RESOLVED_TEXELS * 1000:.2g} um per texel or finer to resolve them")
    return {"fibre_diameter_mm": fibre_diameter_mm,
            "fibre_diameter_source": ("assumed: a cotton fibre, the simulator's (textile fibres are 10-20 um); "
                                      "not measured on this sample") if fibre_diameter_mm == FIBRE_DIAMETER_MM
            else "given",
            "texel_mm": texel_mm, "texels_across": across,
            "criterion": f"resolved when the fibre is at least {RESOLVED_TEXELS:g} texels across",
            "resolved": resolved, "simulated_precision": sim, "warning": warning}


def detect_dataset(dataset: str | Path, out: str | Path, tangent_maps: str | Path | None = None, seeds: int = 10000,
                   min_length_mm: float = 0.27, gt_dir: str | Path | None = None, seed: int = 0,
                   obs=None, progress: Progress = None, conf: np.ndarray | None = None) -> dict[str, Any]:
    """Run :func:`detect` on a dataset; write the fibres (:mod:`dualscale.formats.flyouts`) and
    ``confidence.exr`` to ``out``; score against the ground truth in ``gt_dir`` (a folder with
    ``flyout_mask.exr``) only when it is given.  ``obs``: observations already loaded (then
    ``dataset`` is only recorded); ``conf``: their :func:`confidence_map`, computed already (a
    capture too large to load: :func:`confidence_by_bands`; ``obs`` then needs only the lights
    and the texel size).  The report (and ``flyouts.json``) carries
    ``resolvability``: :func:`resolvability` of the dataset's texel."""
    from dualscale.formats.exr import read_exr, write_exr
    from dualscale.formats.flyouts import read_flyouts, write_flyouts

    from .observations import load_observations

    obs = load_observations(dataset) if obs is None else obs
    conf = confidence_map(obs) if conf is None else conf
    tan = None
    if tangent_maps is not None:
        tpath = Path(tangent_maps) / "tangent.exr"
        if not tpath.is_file():
            raise FileNotFoundError(f"no tangent.exr in {tangent_maps}")
        tan = read_exr(tpath, ("Y",))[..., 0].astype(np.float64)
        if tan.shape != conf.shape:
            raise ValueError(f"tangent map is {tan.shape}, images are {conf.shape}")
    if obs.pixel_mm is None:
        raise InputError(f"{dataset}: fly-out detection needs the texel size in mm (fibre lengths and gaps are in mm); "
                         "import the photographs with --texel-mm")
    res = detect(conf, obs.pixel_mm, seeds, min_length_mm, tan, seed=seed, progress=progress)
    out = Path(out)
    rep: dict[str, Any] = {"seeds": res["seeds"], "min_length_px": res["min_length_px"], "pixel_mm": obs.pixel_mm,
                           "dropped": res["dropped"], "tangent_filter": tan is not None,
                           "resolvability": resolvability(obs.pixel_mm)}
    if gt_dir is not None:
        _, gt = read_flyouts(gt_dir)
        rep["score"] = score(res["mask"], gt)
    write_exr(out / "confidence.exr", conf.astype(np.float32), ("Y",))
    write_flyouts(out, [[(c, r) for r, c in p] for p in res["paths"]], res["mask"], obs.pixel_mm, rep)
    return {"count": len(res["paths"]), **rep}
