"""``dualscale lights sphere DIR -o LIGHTS``: light directions from photos of a mirror sphere.

Writes both light files (formats/lightfile.py): ``LIGHTS.json`` (ours, with the sphere and the
per-light diagnostics) and ``LIGHTS.lp`` (the RTI convention: the image count, then one line
``filename x y z`` per image).  ``-o lights``, ``-o lights.json`` and ``-o lights.lp`` all
write ``lights.json`` + ``lights.lp``.  Names in both files are the image file names in DIR,
so ``dualscale import DIR --lights LIGHTS.lp`` finds them.  Directions: unit vectors from the
sphere towards the light, +x image right, +y image up, +z towards the camera (docs/PHOTOS.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dualscale.errors import CalibrationError, FormatError, GeometryError


def light_paths(out: str | Path) -> tuple[Path, Path]:
    """``(LIGHTS.json, LIGHTS.lp)`` for ``-o LIGHTS`` (a ``.json`` or ``.lp`` suffix is dropped)."""
    out = Path(out)
    if out.suffix.lower() in (".json", ".lp"):
        out = out.with_suffix("")
    return out.with_name(out.name + ".json"), out.with_name(out.name + ".lp")


def cmd_lights_sphere(a: argparse.Namespace) -> int:
    from dualscale.calib.lightsphere import LightSphereError, recover_from_folder
    from dualscale.formats.lightfile import write_lights_json, write_lp

    folder = Path(a.folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"not a folder: {folder}")
    mask = None if a.mask in (None, "") else ("auto" if a.mask == "auto" else Path(a.mask))
    if isinstance(mask, Path) and not mask.is_file():
        raise FileNotFoundError(f"--mask {mask}: no such file")
    try:
        res = recover_from_folder(folder, mask, pattern=a.pattern)
    except LightSphereError as e:
        raise CalibrationError(str(e)) from e
    json_path, lp_path = light_paths(a.output)
    below = [f for f, d in zip(res.files, res.directions) if d[2] <= 0]
    if below:
        raise GeometryError(f"{folder}: the lights of {', '.join(below)} are at or below the horizon (z <= 0); "
                            "a light file cannot carry them (nothing written)")
    bad = [f for f in res.files if any(c.isspace() for c in f) or "#" in f]
    if bad:
        raise FormatError(f"{folder}: image names {bad} contain whitespace or '#', which a .lp file cannot "
                          "carry; rename them (nothing written)")
    json_path.parent.mkdir(parents=True, exist_ok=True)
    records = res.to_records()
    write_lp(lp_path, records)
    write_lights_json(json_path, records, res.source())
    s = res.sphere
    print(f"sphere: centre ({s.cx:.2f}, {s.cy:.2f}) px, radius {s.r:.2f} px, outline fit RMS {s.fit_rms_px:.2f} px "
          f"({s.source})")
    w = max(5, max(len(f) for f in res.files))
    print(f"{'image':<{w}}  {'x':>7} {'y':>7} {'z':>7}  {'elev deg':>8}  {'resid deg':>9}  {'deg/px':>6}  {'conf':>5}")
    for f, d, el, r, g, c in zip(res.files, res.directions, res.elevation_deg, res.residual_deg, res.deg_per_px,
                                 res.confidence):
        print(f"{f:<{w}}  {d[0]:7.4f} {d[1]:7.4f} {d[2]:7.4f}  {el:8.2f}  {r:9.3f}  {g:6.3f}  {c:5.2f}")
    for n in res.notes:
        print(f"note: {n}")
    print(f"wrote {json_path} and {lp_path}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("lights", help="light files for photographs from other rigs (docs/PHOTOS.md)")
    lsub = p.add_subparsers(dest="lights_cmd", required=True)
    s = lsub.add_parser("sphere", help="light directions from photos of a mirror (chrome) sphere")
    s.add_argument("folder", metavar="DIR", help="one photo per light (PNG/JPEG/TIFF/EXR); a '*mask*' image "
                                                  "in DIR is the sphere's mask unless --mask says otherwise")
    s.add_argument("-o", "--output", required=True, metavar="LIGHTS",
                   help="writes LIGHTS.json (ours) and LIGHTS.lp (RTI)")
    s.add_argument("--mask", metavar="MASK|auto", default=None,
                   help="the sphere's mask image, or 'auto' to find the sphere without one "
                        "(default: DIR's one '*mask*' image, else auto)")
    s.add_argument("--pattern", default=None, help="glob of the photos in DIR (default: every image without "
                                                   "'mask' in its name)")
    s.set_defaults(fn=cmd_lights_sphere)
