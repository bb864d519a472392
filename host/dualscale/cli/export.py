"""``dualscale export MAPS -o OUT --format ...``: materials that users' tools open."""

from __future__ import annotations

import argparse
from pathlib import Path

from dualscale.errors import InputError

from .common import add_output, output_folder

FORMATS_HELP = ("exr (Standard Surface inputs, float), mtlx (MaterialX), gltf, glb, u3m (.u3ma); "
                "blend (Blender .blend for Cycles, needs bpy: `make blender`; not in 'all')")


def parse_formats(text: str, option: str = "--format") -> list[str]:
    """``"gltf,mtlx"`` or ``"all"`` -> the list of format names (order kept, duplicates dropped);
    ``option`` names the command's option in the error."""
    from dualscale.export.material import ALL_FORMATS, OPTIONAL_FORMATS

    known = ALL_FORMATS + OPTIONAL_FORMATS
    names = list(ALL_FORMATS) if text.strip() == "all" else [t.strip() for t in text.split(",") if t.strip()]
    bad = [n for n in names if n not in known]
    if bad or not names:
        raise InputError(f"{option} {text!r}: choose from {', '.join(known)} or 'all' (comma-separated)")
    return list(dict.fromkeys(names))


def parse_size_mm(text: str | None) -> tuple[float, float] | None:
    """``"50"`` or ``"50x30"`` (mm) -> ``(w, h)``."""
    if text is None:
        return None
    try:
        parts = [float(p) for p in text.lower().split("x")]
    except ValueError:
        parts = []
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2 or not all(p > 0 and p < 1e5 for p in parts):
        raise InputError(f"--swatch-mm {text!r}: give W or WxH in mm, positive")
    return parts[0], parts[1]


def cmd_export(args: argparse.Namespace) -> int:
    from dualscale.export.material import export_material

    formats = parse_formats(args.format)
    from dualscale.export.material import check_output

    swatch = parse_size_mm(args.swatch_mm)
    check_output(args.maps, args.output)
    with output_folder(args, "export", [args.maps, bool(args.tile)]):
        doc = export_material(args.maps, args.output, formats, name=args.name, tile=args.tile,
                              swatch_mm=swatch, skip_unsized=args.format.strip() == "all")
    size = doc["repeat_mm"]
    where = f"{size[0]:.3g} x {size[1]:.3g} mm" if size else "physical size unknown (no texel size)"
    print(f"exported {doc['name']} ({'seamless tile, ' if doc['tiled'] else ''}{where}):")
    for fmt, files in doc["formats"].items():
        main = next((f for f in files if Path(f).suffix in (".mtlx", ".gltf", ".glb", ".u3ma", ".blend", ".json")), files[0])
        print(f"  {fmt:5s} {Path(args.output) / main}{'  (unchanged, kept)' if fmt in doc['reused'] else ''}")
    for fmt, why in doc.get("skipped", {}).items():
        print(f"  {fmt:5s} left out: {why}")
    if doc.get("uncertainty_sha256"):
        print(_sigma_line(doc))
    if doc["tiled"] and doc.get("tile"):
        seam = doc["tile"].get("seam", {})
        if "tile" in seam:
            print(f"  tile seam score {seam['tile']:.3g} (goal <= {seam.get('goal', 1.1)}; the untreated crop of the "
                  f"same size: {seam['untreated']:.3g}; 1 = a border like the inside, docs/TILE.md)")
            worst = seam.get("worst") or {}
            if worst.get("score") is not None and worst.get("map") != "albedo":
                print(f"  its worst map, {worst['map']}: {worst['score']:.3g}")
    return 0


def _sigma_line(doc: dict) -> str:
    """Where the maps' per-pixel uncertainty went (issue 26; docs/EXPORT.md)."""
    if doc["tiled"]:
        return "  sigma: left out (a tiled export: the tile is a resampled cut of the maps; exchange.json says so)"
    sigma = sorted(f for f in doc["formats"].get("exr", []) if f.endswith("_sigma.exr"))
    where = f"exr/*_sigma.exr ({len(sigma)} files) and maps/uncertainty/" if sigma else "maps/uncertainty/"
    return (f"  sigma: the maps' 1-sigma uncertainty in {where}; MaterialX, glTF and U3M have no field for it "
            "(docs/EXPORT.md)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write fitted or propagated maps as MaterialX, glTF/GLB, U3M and EXR",
                       description="Write a maps folder (fit, propagate or tile output) in the formats that "
                                   "users' tools open; see docs/EXPORT.md for what each format keeps. "
                                   "Each format goes to OUT/<format>/, and OUT/export.json lists the files; "
                                   "a rerun skips formats that are complete and unchanged.")
    p.add_argument("maps", help="maps folder (with material.json)")
    add_output(p, "export folder")
    p.add_argument("--format", default="all", help=f"comma-separated: {FORMATS_HELP}; or 'all' (default: every "
                                                   "format; U3M is left out when the texel size is unknown)")
    p.add_argument("--tile", action="store_true",
                   help="cut a seamless tile of whole weave/knit repeats first and export it (its physical "
                        "size goes into every format)")
    p.add_argument("--name", default=None, help="material name (file stem; default: the maps folder's name, or "
                                                "its parent's when it is called maps)")
    p.add_argument("--swatch-mm", default=None, metavar="W[xH]",
                   help="size of the glTF swatch in mm (default: one repeat, or 2 x 2 tiles)")
    p.set_defaults(fn=cmd_export)
