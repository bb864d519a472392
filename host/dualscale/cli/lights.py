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


def _check_targets(json_path: Path, lp_path: Path, overwrite: bool) -> None:
    """Refuse (``InputError``, exit 2) light-file targets that exist: any existing file without
    ``--overwrite``; with it, a file that is not a light file of ours (a dataset's
    ``manifest.json``, a ``material.json``: ``-o DATASET/manifest`` must never replace them)."""
    from dualscale.errors import InputError
    from dualscale.formats.lightfile import read_lights_json, read_lp

    for p, read in ((json_path, read_lights_json), (lp_path, read_lp)):
        if not (p.exists() or p.is_symlink()):
            continue
        if p.is_dir() or not p.is_file():
            raise InputError(f"-o: {p} exists and is not a file; choose another LIGHTS name")
        try:
            read(p)
            ours = True
        except Exception:  # noqa: BLE001 - unreadable or another format: not a light file
            ours = False
        if not ours:
            raise InputError(f"-o: {p} exists and is not a light file (dualscale lights sphere writes "
                             f"{json_path.name} and {lp_path.name}); choose another LIGHTS name (nothing written)")
        if not overwrite:
            raise InputError(f"-o: {p} exists; pass --overwrite to replace the light files, or choose another "
                             "LIGHTS name (nothing written)")


def cmd_lights_sphere(a: argparse.Namespace) -> int:
    from dualscale.calib.lightsphere import LightSphereError, recover_from_folder
    from dualscale.formats.lightfile import write_lights_json, write_lp

    folder = Path(a.folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"not a folder: {folder}")
    mask = None if a.mask in (None, "") else ("auto" if a.mask == "auto" else Path(a.mask))
    if isinstance(mask, Path) and not mask.is_file():
        raise FileNotFoundError(f"--mask {mask}: no such file")
    json_path, lp_path = light_paths(a.output)
    _check_targets(json_path, lp_path, bool(getattr(a, "overwrite", False)))  # before any work
    from .common import refuse_inside_held

    refuse_inside_held(json_path, "lights sphere")  # not into a folder a running digitize holds
    try:
        res = recover_from_folder(folder, mask, pattern=a.pattern)
    except LightSphereError as e:
        raise CalibrationError(str(e)) from e
    below = [f for f, d in zip(res.files, res.directions) if d[2] <= 0]
    if below:
        raise GeometryError(f"{folder}: the lights of {', '.join(below)} are at or below the horizon (z <= 0); "
                            "a light file cannot carry them (nothing written)")
    bad = [f for f in res.files if any(c.isspace() for c in f) or "#" in f]
    if bad:
        raise FormatError(f"{folder}: image names {bad} contain whitespace or '#', which a .lp file cannot "
                          "carry; rename them (nothing written)")
    records = res.to_records()
    source = res.source()
    matte = _matte(a, folder, records) if a.matte else None
    if matte is not None:
        from dataclasses import replace

        est, sph = matte
        records = [replace(r, intensity=float(e)) for r, e in zip(records, est.intensities)]
        source["radiometry"] = {**est.record(), "matte_sphere": {
            "folder": str(Path(a.matte).resolve()), "centre_px": [sph.cx, sph.cy], "radius_px": sph.r,
            "outline_rms_px": sph.fit_rms_px}}
    json_path.parent.mkdir(parents=True, exist_ok=True)
    write_lp(lp_path, records)
    write_lights_json(json_path, records, source)
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
    if matte is not None:
        est, sph = matte
        print(f"matte sphere: centre ({sph.cx:.2f}, {sph.cy:.2f}) px, radius {sph.r:.2f} px, outline fit RMS "
              f"{sph.fit_rms_px:.2f} px")
        print(f"response: {est.response.describe()}")
        print("light intensities (relative, geometric mean 1): " + " ".join(f"{v:.3f}" for v in est.intensities))
        for n in est.notes:
            print(f"note: {n}")
        print(f"wrote the response and the intensities into {json_path} (the .lp format carries neither); "
              f"import with --lights {json_path.name} --transfer lights")
    print(f"wrote {json_path} and {lp_path}")
    return 0


def _matte(a: argparse.Namespace, chrome: Path, records: list):
    """The matte reference sphere's response and intensities: its photos in ``--matte DIR``
    matched to the chrome photos' lights (by name, else by the numbers in the names), its mask
    ``--matte-mask`` or DIR's one ``*mask*`` image (required)."""
    from dualscale.calib.photo_import import match_images
    from dualscale.calib.response import estimate_from_matte_sphere
    from dualscale.formats.photo import read_codes, read_mask

    folder = Path(a.matte)
    if not folder.is_dir():
        raise FileNotFoundError(f"--matte {folder}: not a folder")
    paths, masks, _ = match_images(folder, records)
    if a.matte_mask:
        mpath = Path(a.matte_mask)
    elif len(masks) == 1:
        mpath = masks[0]
    else:
        raise FormatError(f"--matte {folder}: {'no' if not masks else 'several'} '*mask*' images; the matte sphere "
                          "needs its mask (--matte-mask MASK)")
    codes = [read_codes(p) for p in paths]
    if any(c.bits == 32 for c in codes):
        raise FormatError(f"--matte {folder}: the matte sphere's photos must be the camera's integer images (PNG, "
                          "JPEG, TIFF), shot as the object's are: a float image carries no camera response")
    shape = codes[0].code.shape[:2]
    if any(c.code.shape[:2] != shape for c in codes):
        raise GeometryError(f"--matte {folder}: images of different sizes")
    mask = read_mask(mpath, shape)
    import numpy as np

    dirs = np.array([r.direction for r in records])
    return estimate_from_matte_sphere(np.stack([c.code for c in codes]), mask, dirs, max(c.bits for c in codes),
                                      np.stack([c.clipped for c in codes]))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("lights", help="light files for photographs from other rigs (docs/PHOTOS.md)")
    lsub = p.add_subparsers(dest="lights_cmd", required=True)
    s = lsub.add_parser("sphere", help="light directions from photos of a mirror (chrome) sphere")
    s.add_argument("folder", metavar="DIR", help="one photo per light (PNG/JPEG/TIFF/EXR); a '*mask*' image "
                                                  "in DIR is the sphere's mask unless --mask says otherwise")
    s.add_argument("-o", "--output", required=True, metavar="LIGHTS",
                   help="writes LIGHTS.json (ours) and LIGHTS.lp (RTI)")
    s.add_argument("--overwrite", action="store_true",
                   help="replace LIGHTS.json / LIGHTS.lp when they exist and are light files (default: off, an "
                        "existing file is refused; a file that is not a light file is refused either way)")
    s.add_argument("--mask", metavar="MASK|auto", default=None,
                   help="the sphere's mask image, or 'auto' to find the sphere without one "
                        "(default: DIR's one '*mask*' image, else auto)")
    s.add_argument("--matte", metavar="MATTE_DIR", default=None,
                   help="photos of a matte (diffuse white or grey) sphere under the same lights: the camera "
                        "response and the lights' relative intensities come from it (docs/PHOTOS.md)")
    s.add_argument("--matte-mask", metavar="MASK", default=None,
                   help="the matte sphere's mask (default: MATTE_DIR's one '*mask*' image)")
    s.add_argument("--pattern", default=None, help="glob of the photos in DIR (default: every image without "
                                                   "'mask' in its name)")
    s.set_defaults(fn=cmd_lights_sphere)
