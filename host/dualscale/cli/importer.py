"""``dualscale import IMAGES --lights LIGHTS -o DATASET --transfer srgb|linear|gamma:G``: photographs
from another rig into our photometric dataset (:mod:`dualscale.calib.photo_import`,
docs/PHOTOS.md)."""

from __future__ import annotations

import argparse
import sys

from .common import add_output, add_work_options, apply_threads, output_folder, want_progress


def _scale(text: str) -> float | str:
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is neither 'auto' nor a number") from None


def cmd_import(a: argparse.Namespace) -> int:
    from dualscale.calib.photo_import import import_photos

    apply_threads(a)
    with output_folder(a, "import", [a.images, a.lights]):
        rep = import_photos(a.images, a.lights, a.output, a.transfer, mask=a.mask, texel_mm=a.texel_mm,
                            scale=a.scale, match=a.match, progress=want_progress(a), intensities=a.intensities,
                            strict=a.strict)
    h, w = rep.size
    print(f"imported {len(rep.files)} images of {w}x{h} px ({rep.bits}-bit, transfer {rep.transfer or 'linear EXR'}) "
          f"into {rep.dataset}")
    if rep.response is not None:
        print(f"response: {rep.response.describe()}")
        fits = (rep.response.evidence or {}).get("fits") or {}
        if fits:
            print("  consistency (lower is better): " + ", ".join(f"{k} {v['score']:.4f}" for k, v in fits.items()))
    if rep.intensities is not None:
        print(f"light intensities ({rep.intensities_source}): " + " ".join(f"{v:.3f}" for v in rep.intensities))
    for wmsg in rep.warnings:
        print(f"dualscale import: warning: {wmsg}", file=sys.stderr)
    print(f"mask: {rep.mask or 'none (every pixel is sample)'}; clipped pixels per image: {rep.clipped}")
    print(f"light scale E = {rep.scale:.4g} ({rep.scale_source})")
    for n in rep.notes:
        print(f"note: {n}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("import", help="photographs + a light file (.lp or ours) -> photometric dataset "
                                      "(docs/PHOTOS.md)")
    p.add_argument("images", metavar="IMAGES", help="folder of photographs, one per light (PNG/JPEG/TIFF 8 or "
                                                    "16 bit, EXR)")
    p.add_argument("--lights", required=True, metavar="LIGHTS", help=".lp (RTI) or our .json light file")
    add_output(p, "dataset folder DATASET to write")
    p.add_argument("--transfer", default=None, metavar="auto|lights|srgb|linear|gamma:G",
                   help="camera response of integer images (required for PNG/JPEG/TIFF; EXR is linear): auto = "
                        "estimated from the photographs; lights = the matte sphere's, recorded in the light file; "
                        "a stated one is checked against the data (a warning when they contradict it)")
    p.add_argument("--strict", action="store_true",
                   help="refuse (exit 2) a stated transfer that the photographs contradict, instead of warning")
    p.add_argument("--intensities", choices=("auto", "estimate", "file", "equal"), default="auto",
                   help="lights' relative intensities: auto = the light file's, else estimated from the "
                        "photographs; estimate; file (1 where absent); equal (default auto)")
    p.add_argument("--mask", default="auto", metavar="MASK|auto|none",
                   help="sample mask image (default auto: the folder's one '*mask*' image, if any)")
    p.add_argument("--texel-mm", type=float, default=None, metavar="T",
                   help="pixel pitch on the object in mm (default: unknown)")
    p.add_argument("--scale", type=_scale, default="auto", metavar="auto|E",
                   help="light scale: the intensity every light is given (default auto: 99th-percentile "
                        "albedo 0.8)")
    p.add_argument("--match", choices=("auto", "name", "number"), default="auto",
                   help="how light-file names find the images: by name, by the numbers in the names "
                        "(chrome.3.png -> cat.3.png), or auto (name, else number when no name matches; the default)")
    add_work_options(p)
    p.set_defaults(fn=cmd_import)
