"""``dualscale propagate train|export|run``: mesoscale propagation (docs/PROPAGATION.md)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dualscale.errors import InputError

from .choices import PERCEPTUAL, PROPAGATE_PRESETS, SCHEDULES
from .common import add_output, add_work_options, apply_threads, output_folder, want_progress


def cmd_train(args: argparse.Namespace) -> int:
    from dualscale.propagate.data import load_source
    from dualscale.propagate.train import TrainOptions, preset_with, train

    maps = args.maps or []
    if maps and len(maps) != len(args.datasets):
        raise InputError(f"--maps given {len(maps)} times for {len(args.datasets)} datasets; pair them one to one")
    apply_threads(args)
    args.resume_hint = "continue it with the same command and --resume (its checkpoint is OUTPUT.ckpt)"
    if args.checkpoint_every < 1:
        raise InputError(f"--checkpoint-every must be at least 1, got {args.checkpoint_every}")
    sources = [load_source(d, maps[i] if maps else None) for i, d in enumerate(args.datasets)]
    preset = preset_with(args.preset, iterations=args.iterations, batch=args.batch, lr=args.lr, crop=args.crop)
    sigma = (0.1, args.blur_sigma_max)
    opts = TrainOptions(width=args.width, perceptual=args.perceptual, amp=not args.no_amp, blur_sigma=sigma,
                        seed=args.seed, checkpoint_every=args.checkpoint_every, resume=args.resume, init=args.init,
                        progress=want_progress(args), device=args.device, schedule=args.schedule,
                        diffuse_fraction=args.diffuse_fraction)
    _refuse_foreign_model(Path(args.output), [s.name for s in sources], args.overwrite)
    with output_folder(args, "propagate train", record=False, folder=Path(args.output).absolute().parent):
        res = train(sources, preset, args.output, opts)
    print(f"wrote {args.output} ({res.iterations} iterations, {res.seconds:.1f} s this run, "
          f"final loss {res.history[-1]['loss']:.4f})")
    return 0


def _fraction(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0 <= v <= 1:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text}")
    return v


def _refuse_foreign_model(model: Path, names: list[str], overwrite: bool) -> None:
    """Refuse to replace a model file (or its checkpoint) trained on other datasets, unless
    ``--overwrite``; a damaged file is taken as this run's own (its rerun repairs it)."""
    from dualscale.formats.model import read_model_file
    from dualscale.formats.torchfile import load_torch
    from dualscale.propagate.train import checkpoint_path

    if overwrite:
        return
    ckpt = checkpoint_path(model)
    for path in (model, ckpt):
        if not path.is_file():
            continue
        try:
            if path == model:
                theirs = (read_model_file(path).get("train") or {}).get("datasets")
            else:
                theirs = ((load_torch(path, "training checkpoint").get("run") or {}).get("sources"))
        except (InputError, OSError, AttributeError):
            continue
        if theirs is not None and list(theirs) != names:
            raise InputError(f"-o {model}: {path.name} was trained on {theirs}, not {names}; pass --overwrite to "
                             "replace it, or choose another file")


def cmd_export(args: argparse.Namespace) -> int:
    from dualscale.propagate.export import export_model

    out = export_model(args.model, check=not args.no_check, int8=args.int8)
    print(json.dumps(out, indent=1))
    if "parity_fp32" in out and max(out["parity_fp32"].values()) >= 1e-4:
        import sys

        print("dualscale propagate export: check failed: fp32 ONNX parity is worse than 1e-4", file=sys.stderr)
        return 1
    return 0


def _onnx_for(model: Path, precision: str) -> Path:
    """The ONNX file to run: ``model`` itself, or the one exported next to a model file."""
    from dualscale.propagate.export import ensure_exported, onnx_paths

    if model.suffix == ".onnx":
        return model
    p32, p16 = onnx_paths(model)
    ensure_exported(model, check=False)  # by content: a model replaced by an older file is re-exported
    if precision == "int8":  # the int8 file is opened (and checked) beside the fresh fp32 export
        return p32
    if precision == "auto":
        import onnxruntime as ort

        precision = "fp16" if "CUDAExecutionProvider" in ort.get_available_providers() else "fp32"
    return p16 if precision == "fp16" else p32


def cmd_run(args: argparse.Namespace) -> int:
    from dualscale.propagate.infer import OnnxModel, run_tiled
    from dualscale.formats.model import read_model_file

    threads = apply_threads(args)
    model = Path(args.model)
    if not model.is_file():
        raise InputError(f"model file not found: {model}")
    from dualscale.propagate.guidance import read_guidance

    # read (linearise, check) the guidance first: its refusals come before anything is written
    guidance = read_guidance(Path(args.guidance), args.transfer, args.texel_mm)
    if model.suffix != ".onnx":
        read_model_file(model)  # clear error for foreign/incompatible files before exporting
    onnx = _onnx_for(model, args.precision)
    try:
        exposure = args.exposure if args.exposure == "auto" else float(args.exposure)
    except ValueError:
        raise InputError(f"--exposure {args.exposure!r}: use 'auto' or a positive gain") from None
    if args.precision == "int8":  # the quantised export beside the model, checked against its fp32 export
        net = OnnxModel.open(onnx if model.suffix == ".onnx" else model, threads, precision="int8")
    else:
        net = OnnxModel.open(onnx, threads)
    with output_folder(args, "propagate run", [args.model, args.guidance]):
        summary = run_tiled(net, guidance, args.output,
                            args.tile, args.overlap, exposure, args.batch, want_progress(args))
    for w in summary["warnings"]:
        print(f"dualscale propagate run: warning: {w}", file=sys.stderr)
    print(f"wrote {', '.join(summary['maps'])} ({summary['width']}x{summary['height']}, {summary['tiles']} tiles, "
          f"{summary['precision']}) to {args.output}")
    return 0


def register(subparsers) -> None:
    """Add ``propagate`` (train / export / run) to an ``argparse`` subparsers object."""
    p = subparsers.add_parser("propagate", help="mesoscale propagation: U-Net from micro capture to guidance image")
    sub = p.add_subparsers(dest="propagate_cmd", required=True)

    t = sub.add_parser("train", help="train on micro datasets with fitted maps")
    t.add_argument("datasets", nargs="+", metavar="DATASET",
                   help="folder with micro/ and maps/ (as 'dualscale synth --dataset' writes), or a micro dataset")
    add_output(t, "model file to write (checkpoints go to OUTPUT.ckpt)")
    t.add_argument("--maps", action="append", help="maps folder for each DATASET, in order (repeat)")
    t.add_argument("--preset", choices=sorted(PROPAGATE_PRESETS), default="fast",
                   help="training preset: quick, fast, balanced or paper (docs/PROPAGATION.md; default: fast)")
    t.add_argument("--iterations", type=int, help="override the preset's iteration count")
    t.add_argument("--batch", type=int, help="override the preset's batch size")
    t.add_argument("--lr", type=float, help="override the preset's learning rate")
    t.add_argument("--schedule", choices=SCHEDULES, default=None,
                   help="learning-rate schedule: constant (the preset's lr) or onecycle (one cycle peaking at the lr; "
                        "default: the preset's, onecycle peaking at 0.01 for quick/fast/balanced, so --schedule "
                        "constant alone runs at 0.01: pass --lr 0.002 with it)")
    t.add_argument("--diffuse-fraction", type=_fraction, default=None, metavar="F",
                   help="share of training crops under the diffuse light, the guidance's lighting, in [0, 1] "
                        "(default: the preset's)")
    t.add_argument("--crop", type=int, help="override the 128 px crop (multiple of 16)")
    t.add_argument("--width", type=int, help="width factor W (default 16 for one dataset, 32 for several)")
    t.add_argument("--perceptual", choices=sorted(PERCEPTUAL), default="gram",
                   help="perceptual loss of the style term (lpips_alex needs local weights; default: gram)")
    t.add_argument("--blur-sigma-max", type=float, default=3.0, help="blur sigma ~ U(0.1, MAX) px (default: 3; paper: 11)")
    t.add_argument("--init", metavar="MODEL|none",
                   help="warm-start model file, or 'none' to train from random weights (default: the preset's: "
                        "the packaged generic model where the preset warm-starts and the width is 16)")
    t.add_argument("--resume", action="store_true", help="continue from OUTPUT.ckpt")
    t.add_argument("--checkpoint-every", type=int, default=50, help="write OUTPUT.ckpt every N steps, for --resume (default: 50)")
    t.add_argument("--seed", type=int, default=0, help="seed of the initialisation, the crops and the augmentation (default: 0)")
    t.add_argument("--no-amp", action="store_true", help="train in float32")
    t.add_argument("--device", default="cpu", help="torch device to train on, e.g. cpu or cuda (default: cpu)")
    add_work_options(t, "torch intra-op threads (on busy shared cores, set OMP_WAIT_POLICY=PASSIVE or use 1)")
    t.set_defaults(fn=cmd_train)

    e = sub.add_parser("export", help="export a model to ONNX fp32 and fp16 and check parity")
    e.add_argument("model")
    e.add_argument("--no-check", action="store_true", help="skip the ONNX-vs-torch parity check (default: checked)")
    e.add_argument("--int8", action="store_true",
                   help="also write MODEL.int8.onnx (dynamic int8 quantisation; slower than fp32 on this CPU, "
                        "its loss per map is in docs/PROPAGATION.md)")
    e.set_defaults(fn=cmd_export)

    r = sub.add_parser("run", help="propagate maps over a guidance image (tiled, onnxruntime) to EXR")
    r.add_argument("model", help="model file or exported .onnx")
    r.add_argument("guidance", help="RGB image (EXR, or PNG/JPEG/TIFF with --transfer) or a photometric dataset "
                   "folder with a diffuse image")
    r.add_argument("--transfer", default=None, metavar="srgb|linear|gamma:G",
                   help="transfer function of a display-encoded guidance (PNG/JPEG/TIFF); required for those")
    r.add_argument("--texel-mm", type=float, default=None, metavar="MM",
                   help="texel size of the guidance, recorded in the maps (default: from its dataset's camera; "
                        "unknown: null, with a warning)")
    add_output(r, "output maps folder")
    r.add_argument("--tile", type=int, default=512, help="side of the inference tiles in guidance pixels (default: 512)")
    r.add_argument("--overlap", type=int, default=64, help="overlap of neighbouring tiles in pixels, blended (default: 64)")
    r.add_argument("--batch", type=int, default=1, help="tiles per onnxruntime call (default: 1)")
    r.add_argument("--precision", choices=("auto", "fp32", "fp16", "int8"), default="auto",
                   help="auto: fp16 on CUDA, fp32 on CPU; int8: the export made by 'propagate export --int8' "
                        "(refused when absent or stale); default: auto")
    r.add_argument("--exposure", default="auto", help="'auto' (match the training diffuse mean) or a gain (default: auto)")
    add_work_options(r, "onnxruntime (and torch/OpenCV) intra-op threads")
    r.set_defaults(fn=cmd_run)
