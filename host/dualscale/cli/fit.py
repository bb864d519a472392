"""``dualscale fit``, ``dualscale study lights`` and ``dualscale flyouts``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .choices import FIT_KERNELS, FIT_PRESETS
from .common import add_engine_options, add_output, add_work_options, apply_threads, engine_spec, output_folder, want_progress

_SWITCH = {"auto": None, "on": True, "off": False}
#: ``--cv-pixels`` default: :data:`dualscale.fit.holdout.CV_PIXELS` (a literal here, so that
#: building the parser imports no torch; tests/fit/test_crossval.py checks they agree)
CV_PIXELS = 2000
#: ``--memory`` default: :data:`dualscale.fit.stream.DEFAULT_MEMORY` (2 GiB, a literal here for the
#: same reason; tests/fit/test_stream.py checks they agree)
DEFAULT_MEMORY = "2G"


def cmd_fit(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from dualscale.fit.api import fit_dataset
    from dualscale.fit.holdout import describe, parse_folds
    from dualscale.fit.presets import PRESETS, get_preset

    from dualscale.errors import InputError

    # the values a user types, checked before any work (and named as typed, not as the preset's fields)
    if args.checkpoint_every < 1:
        raise InputError(f"--checkpoint-every {args.checkpoint_every}: give a number of iterations >= 1")
    if args.tile_px < 1:
        raise InputError(f"--tile-px {args.tile_px}: give a tile side in pixels >= 1")
    if args.ior_prior is not None and not args.ior_prior >= 0:
        raise InputError(f"--ior-prior {args.ior_prior:g}: give a standard deviation >= 0 (0 = no prior)")
    if args.shadow_ratio is not None and not 0 <= args.shadow_ratio < 1:
        raise InputError(f"--shadow-ratio {args.shadow_ratio:g}: give a ratio in [0, 1) (0 = fit every capture)")
    from dualscale.fit.stream import parse_memory

    memory = parse_memory(args.memory)
    preset = get_preset(args.preset)
    for option, field, value in (("--ior-prior", "ior_prior_sd", args.ior_prior),
                                 ("--shadow-ratio", "shadow_ratio", args.shadow_ratio)):
        if value is None:
            continue
        try:
            preset = replace(preset, **{field: value})
        except ValueError:  # the preset's check names its field; the user typed the option
            lm = ", ".join(n for n, p in PRESETS.items() if p.optimizer == "lm")
            raise InputError(f"{option} {value:g}: the {args.preset} preset's {preset.optimizer} optimiser has "
                             f"no such term (implemented for the LM optimiser only: presets {lm})") from None
    apply_threads(args)
    engine = engine_spec(args)
    if args.compile and args.kernel not in (None, "compiled"):
        raise InputError(f"--compile is --kernel compiled; it contradicts --kernel {args.kernel}")
    if args.kernel is not None and args.preset == "standard-compiled" and args.kernel != "compiled":
        raise InputError(f"--preset standard-compiled is `standard` with the compiled kernel; for --kernel "
                         f"{args.kernel} use --preset standard")
    if args.compile:
        preset = replace(preset, kernel="compiled")
    if args.kernel is not None:
        preset = replace(preset, kernel=args.kernel)
    try:
        folds = parse_folds(args.cv_folds)
    except ValueError as e:
        raise InputError(f"--cv-folds: {e}") from None
    if args.cv_pixels < 0:
        raise InputError(f"--cv-pixels {args.cv_pixels}: give a count >= 0 (0 = no cross-validation pass)")
    overrides = {"transmittance": _SWITCH[args.transmittance], "anisotropy": _SWITCH[args.anisotropy],
                 "tint": _SWITCH[args.tint]}
    had_sigma = (Path(args.output) / "uncertainty" / "uncertainty.json").is_file()
    with output_folder(args, "fit", [args.dataset]):
        res, extra = fit_dataset(args.dataset, args.output, preset, overrides, cv_pixels=args.cv_pixels, cv_folds=folds,
                                 progress=want_progress(args), checkpoint_every=args.checkpoint_every,
                                 restart=args.restart, stop_after=args.stop_after, seed=args.seed,
                                 previews=not args.no_previews, gt=args.gt, engine=engine, tile_px=args.tile_px,
                                 memory=memory, uncertainty=not args.no_uncertainty)
    c = res.comps
    where = (f"tiled on {extra['tiled']['engine']}" if "tiled" in extra else
             f"{extra['threads']} thread{'' if extra['threads'] == 1 else 's'}")
    print(f"preset {res.preset.name} (kernel {res.preset.kernel}, {where}): {res.iterations} iterations in "
          f"{res.seconds:.1f} s; components: "
          f"{'translucent' if not c.opaque else 'opaque'}, {'isotropic' if c.isotropic else 'anisotropic'}, "
          f"{'tinted' if c.tinted else 'untinted'}")
    if "tiled" in extra:
        t = extra["tiled"]
        parts = f"tiles: {t['tiles']} of {t['tile_px']} px" if t.get("tile_px") else f"bands: {t['tiles']} of full rows"
        print(f"{parts} on {t['workers']} worker{'' if t['workers'] == 1 else 's'}"
              + (f" ({t['resumed_tiles']} done before)" if t["resumed_tiles"] else ""))
    print(_memory_line(extra))
    lights = extra["lights"]
    print(f"fitted on {lights['fitted_images']} of {lights['images']} images ({lights['fitted_leds']} of "
          f"{lights['leds']} lights)" + ("" if lights["fitted_leds"] == lights["leds"] else
                                         f"; the {res.preset.name} preset's led_stride thins the lights"))
    print("losses on the fitted images: " + ", ".join(f"{k}={v:.4g}" for k, v in res.losses.items()))
    print(describe(extra.get("cross_validation")))
    if extra.get("radiometry"):
        r = extra["radiometry"]
        print(f"camera response: {r.get('response', r.get('transfer'))}; lights' intensities: {r.get('intensities')}")
    if "ground_truth" in extra:
        print("vs ground truth: " + ", ".join(f"{k}={v:.4g}" for k, v in extra["ground_truth"]["errors"].items()))
    line = _uncertainty_line(Path(args.output))
    if line:
        print(line)
    elif args.no_uncertainty and had_sigma:
        print(f"uncertainty: none (--no-uncertainty); the earlier fit's {Path(args.output) / 'uncertainty'}/ was "
              "removed with its maps")
    print(f"wrote {Path(args.output) / 'fit.json'}")
    return 0


def _uncertainty_line(out: Path) -> str | None:
    """What the fit's uncertainty says, from ``fit.json``'s record: the median 1-sigma per map
    (every channel's median, the largest shown), the undetermined shares over 1 %, its time."""
    from dualscale.formats.versioned import read_json

    try:
        rec = read_json(out / "fit.json").get("uncertainty")
    except (OSError, ValueError):
        return None
    if not isinstance(rec, dict) or not rec.get("maps"):
        return None
    unit = {"normal": "°", "tangent": "°", "ior": " (eta)"}
    meds, und = [], []
    for name, m in rec["maps"].items():
        vals = [v for v in m.get("median") or [] if v is not None]
        meds.append(f"{name} {max(vals):.2g}{unit.get(name, '')}" if vals else f"{name} undetermined")
        frac = max(m.get("undetermined_fraction") or [0.0])
        if frac > 0.01:
            und.append(f"{name} {100 * frac:.0f} %")
    return (f"uncertainty ({out / 'uncertainty'}/, {rec.get('seconds', 0):.2f} s): median 1-sigma "
            + ", ".join(meds) + ("; undetermined: " + ", ".join(und) if und else "")
            + " (covers the noise and the fit's convergence, not the calibration; docs/FITTING.md)")


def _memory_line(extra: dict) -> str:
    """The fit's memory, as the user reads it: in memory or out of core, against the budget."""
    from dualscale.fit.stream import memory_text as _size

    mem = extra.get("memory") or {}
    budget = "no budget" if mem.get("memory_bytes") is None else f"the {_size(mem['memory_bytes'])} budget"
    need = f"estimated {_size(mem['estimate_bytes'])}" if mem.get("estimate_bytes") else "given in memory"
    if "out_of_core" not in extra:
        return f"memory: in memory ({need}, within {budget})"
    m = extra["out_of_core"]
    parts = (f"{m['parts']} band{'s' if m['parts'] != 1 else ''} of {m['part_rows']} row{'s' if m['part_rows'] != 1 else ''}"
             f" x {m['part_columns']} columns" if m["part_kind"] == "bands" else
             f"{m['parts']} tiles read by the workers")
    return (f"memory: out of core ({need}, over {budget}): {parts}; peak {m['peak_rss_mib']:.0f} MiB"
            + (" in this process (the driver)" if m["part_kind"] == "tiles" else "")
            + (f"; {m['resumed_parts']} done before" if m["resumed_parts"] else ""))


def _max_sigma(text: str) -> dict[str, float]:
    """``MAP=SIGMA[,MAP=SIGMA]`` of ``study lights --max-sigma``."""
    from dualscale.formats.maps import SIGMA_UNITS

    out: dict[str, float] = {}
    for part in text.split(","):
        name, sep, value = part.partition("=")
        name = name.strip()
        if name in out:
            raise argparse.ArgumentTypeError(f"{name!r} is given twice; give each map one limit")
        try:
            v = float(value)
        except ValueError:
            v = float("nan")
        if not sep or name not in SIGMA_UNITS or not (v > 0 and v < float("inf")):
            raise argparse.ArgumentTypeError(f"{part!r}: give MAP=SIGMA with MAP one of {sorted(SIGMA_UNITS)} and "
                                             "SIGMA a positive number")
        out[name] = v
    return out


def cmd_study_lights(args: argparse.Namespace) -> int:
    from dualscale.fit.study import parse_subset, run_study

    apply_threads(args)
    custom = dict(parse_subset(s) for s in args.subset or [])
    with output_folder(args, "study lights", [args.dataset]):
        rep = run_study(args.dataset, args.output, preset=args.preset, custom=custom, names=args.only,
                        gt_dir=args.gt, progress=want_progress(args), max_sigma=args.max_sigma)
    print(rep["table_markdown"])
    cls = f" ({rep['material_class']})" if rep.get("material_class") not in (None, "unknown") else ""
    print(f"recommendation{cls}: {rep['recommendation']['subset'] or 'none'} -- {rep['recommendation']['reason']}")
    print(f"wrote {Path(args.output) / 'study.json'} and {Path(args.output) / 'study.png'}")
    return 0


def cmd_flyouts(args: argparse.Namespace) -> int:
    from dualscale.fit.flyouts import detect_dataset

    apply_threads(args)
    with output_folder(args, "flyouts", [args.dataset]):
        rep = detect_dataset(args.dataset, args.output, tangent_maps=args.tangent, seeds=args.seeds,
                             min_length_mm=args.min_length_mm, gt_dir=args.gt, seed=args.seed,
                             progress=want_progress(args))
    print(f"{rep['count']} fly-outs (from {rep['seeds']} seeds, min length {rep['min_length_px']:.1f} px)")
    if "score" in rep:
        print("vs ground truth: " + json.dumps(rep["score"]))
    print(f"wrote {Path(args.output) / 'flyouts.json'}, flyouts.svg, flyout_mask.exr")
    return 0


def register(subparsers) -> None:
    """Add ``fit``, ``study`` (``study lights``) and ``flyouts`` to an argparse subparsers object."""
    f = subparsers.add_parser("fit", help="fit SVBSDF maps to a micro photometric dataset")
    f.add_argument("dataset", help="dataset directory (manifest.json), or a `synth` output with micro/")
    add_output(f, "output directory for the maps")
    f.add_argument("--preset", choices=sorted(FIT_PRESETS), default="standard",
                   help="fit preset: draft (fast), standard or paper (docs/FITTING.md; default: standard)")
    for comp in ("transmittance", "anisotropy", "tint"):
        f.add_argument(f"--{comp}", choices=sorted(_SWITCH), default="auto",
                       help=f"force the {comp} component on/off (default: decided from the data)")
    f.add_argument("--ior-prior", type=float, default=None, metavar="SD",
                   help="sd of the Gaussian prior on the normalised IOR map (eta = 1 + 2 v), centred on eta 1.5; "
                        "0 = none (LM presets only; default: the preset's, 0.05 for standard)")
    f.add_argument("--shadow-ratio", type=float, default=None, metavar="R",
                   help="set aside an LED's captures where its diffuse capture is below R x the render (a cast "
                        "shadow); 0 = fit every capture (LM presets only; default: the preset's, 0.5 for standard)")
    f.add_argument("--kernel", choices=FIT_KERNELS, default=None,
                   help="'fused' (the presets' default: numba, analytic derivatives), 'eager' (the reference: torch; "
                        "forward differences for LM presets, autograd for Adam ones) or 'compiled' (LM presets only: "
                        "the reference through torch.compile) (docs/FITTING.md)")
    f.add_argument("--compile", action="store_true", help="the same as --kernel compiled")
    f.add_argument("--cv-pixels", type=int, default=CV_PIXELS, metavar="N",
                   help="the maps are fitted on every light; the held-out error comes from a cross-validation "
                        f"pass over the lights on N random sample pixels (default {CV_PIXELS}; 0 = no pass)")
    f.add_argument("--cv-folds", default="auto", metavar="auto|loo|K",
                   help="folds of that pass: 'loo' (leave-one-light-out), K (K folds, lights dealt round-robin in "
                        "id order) or 'auto' (the default: loo for at most 16 lights, else 8 folds)")
    f.add_argument("--checkpoint-every", type=int, default=50, metavar="N",
                   help="iterations between checkpoints, for a rerun to resume from (default: 50)")
    f.add_argument("--restart", action="store_true", help="ignore an existing checkpoint")
    f.add_argument("--stop-after", type=int, default=None, help=argparse.SUPPRESS)
    f.add_argument("--gt", default=None, metavar="MAPS",
                   help="ground-truth maps folder to score the fit against (evaluation only)")
    f.add_argument("--seed", type=int, default=0, help="seed of the component choice's and the cross-validation's pixel samples (default: 0)")
    f.add_argument("--no-previews", action="store_true", help="write the EXR maps without PNG previews (default: previews)")
    f.add_argument("--no-uncertainty", action="store_true",
                   help="do not compute the maps' per-pixel uncertainty (default: computed, written to "
                        "OUT/uncertainty/ as a 1-sigma EXR per map and undetermined.exr, summarised in fit.json; "
                        "without it the viewer, report and export have no sigma to show; the LM presets build it in "
                        "their last iteration's kernel pass, and it costs about 2-8 %% of the fit's time; "
                        "docs/FITTING.md)")
    f.add_argument("--memory", default=DEFAULT_MEMORY, metavar="SIZE",
                   help="memory budget of the fit, e.g. 2G, 800M, or 'unlimited' (the whole map in memory): a "
                        "dataset whose fit needs more is fitted out of core, band by band from disk, with the same "
                        f"maps (default: {DEFAULT_MEMORY}; docs/SCALE.md)")
    add_work_options(f)
    g = add_engine_options(f, "fit in pixel tiles on N local Dask worker processes, one thread each ("
                              "the same maps as one process; default: one process)")
    g.add_argument("--tile-px", type=int, default=64, metavar="PX",
                   help="side of a tile with --workers/--scheduler/--cluster (default 64; docs/SCALE.md)")
    f.set_defaults(fn=cmd_fit)

    s = subparsers.add_parser("study", help="studies of the micro fit")
    ss = s.add_subparsers(dest="study", required=True)
    sl = ss.add_parser("lights", help="fit with each light subset (supplementary Sec. 6) and evaluate it")
    sl.add_argument("dataset")
    add_output(sl, "output directory (study.json, study.png, one maps folder per subset)")
    sl.add_argument("--preset", choices=sorted(FIT_PRESETS), default="standard",
                    help="fit preset of each subset's fit (default: standard)")
    sl.add_argument("--subset", action="append", metavar="NAME=IDS",
                    help="extra subset: LED ids and ranges, e.g. 'mine=0,3,10-20'")
    sl.add_argument("--only", nargs="*", default=None, help="run only these subsets")
    sl.add_argument("--gt", default=None, help="ground-truth maps folder to score against (evaluation only)")
    sl.add_argument("--max-sigma", type=_max_sigma, default=None, metavar="MAP=SIGMA[,MAP=SIGMA]",
                    help="recommend the fewest lights whose median 1-sigma per named map is at most SIGMA, in the "
                         "map's sigma units (normal, tangent: degrees; ior: eta; else the map's value), e.g. "
                         "normal=0.5,roughness=0.01; no ground truth needed (default: by held-out SSIM)")
    add_work_options(sl)
    sl.set_defaults(fn=cmd_study_lights)

    fo = subparsers.add_parser("flyouts", help="detect fly-out fibres (supplementary Sec. 4.1)")
    fo.add_argument("dataset")
    add_output(fo, "output directory (flyouts.json, flyouts.svg, flyout_mask.exr, confidence.exr)")
    fo.add_argument("--tangent", default=None, help="maps directory with tangent.exr (fitted or ground truth)")
    fo.add_argument("--seeds", type=int, default=10000, help="seeds for a 1 Mpx image (scaled with the image size; default: 10000)")
    fo.add_argument("--min-length-mm", type=float, default=0.27, help="shortest fibre reported, in mm (default: 0.27)")
    fo.add_argument("--gt", default=None, help="ground-truth folder with flyouts.json and flyout_mask.exr to score against")
    fo.add_argument("--seed", type=int, default=0, help="seed of the detection's random choices (default: 0)")
    add_work_options(fo)
    fo.set_defaults(fn=cmd_flyouts)
