"""``dualscale tile``: a seamless tile of whole repeats, at real-world size, from a maps folder."""

from __future__ import annotations

import argparse
from pathlib import Path

from .common import add_output, add_work_options, apply_threads, output_folder

SOURCES = ("all", "albedo", "normal_x", "normal_y")


def _repeats(text: str) -> tuple[int, int]:
    try:
        nx, ny = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--repeats must be NxM (e.g. 2x2), got {text!r}") from None
    if nx < 1 or ny < 1:
        raise argparse.ArgumentTypeError(f"--repeats must be positive, got {text!r}")
    return nx, ny


def cmd_tile(args: argparse.Namespace) -> int:
    from dualscale.errors import InputError
    from dualscale.formats.maps import load_maps
    from dualscale.tile import find_lattice, make_tile, save_tile

    apply_threads(args)
    maps, meta = load_maps(args.maps)
    texel = meta.get("texel_mm")
    if args.source in SOURCES:
        lattice = find_lattice(maps, texel, source=args.source)
    else:  # a guidance image (EXR or a photo, read linear)
        from dualscale.formats.photo import read_photo

        path = Path(args.source)
        if not path.is_file():
            raise InputError(f"--source {args.source}: neither {', '.join(SOURCES)} nor an image file")
        img = read_photo(path, "linear" if path.suffix.lower() == ".exr" else args.transfer).rgb
        if img.shape[:2] != maps.shape:
            raise InputError(f"--source {path}: the image is {img.shape[1]} x {img.shape[0]}, the maps are "
                             f"{maps.shape[1]} x {maps.shape[0]}")
        lattice = find_lattice(img, texel)
    with output_folder(args, "tile", [args.maps]):
        tile = make_tile(maps, texel, lattice, repeats=args.repeats, blend_px=args.blend)
        save_tile(tile, args.output, meta={"source": str(args.maps)})
    v = lattice.vectors_px
    print(f"repeat: ({v[0, 0]:.2f}, {v[0, 1]:.2f}), ({v[1, 0]:.2f}, {v[1, 1]:.2f}) texels (col, row), "
          f"strength {lattice.strength:.2f}")
    size = (f"{tile.size_mm[0]:.3f} x {tile.size_mm[1]:.3f} mm" if tile.size_mm else
            f"{tile.size_px[0]:.2f} x {tile.size_px[1]:.2f} texels (texel size unknown: no mm)")
    print(f"tile: {tile.repeats[0]} x {tile.repeats[1]} repeats, {tile.maps.shape[1]} x {tile.maps.shape[0]} texels, "
          f"{size}{'' if tile.axis_aligned else f', sheared onto the axes ({tile.shear_deg:+.1f} deg)'}")
    worst = tile.seam.get("worst") or {}
    also = (f"; its worst map, {worst['map']}, {worst['score']:.3f}" if worst.get("score") is not None
            and worst.get("map") != "albedo" else "")
    print(f"seam score: {tile.seam['tile']:.3f} (untreated crop {tile.seam['untreated']:.3f}; goal <= "
          f"{tile.seam['goal']}{also})")
    print(f"wrote {Path(args.output) / 'material.json'}")
    return 0


def register(subparsers) -> None:
    """Add ``tile`` to an argparse subparsers object."""
    t = subparsers.add_parser("tile", help="cut a seamless tile of whole weave/knit repeats at real-world size",
                              description="Find the repeat (two lattice vectors) of a maps folder, cut a tile of "
                                          "whole repeats (sheared onto the axes where needed), feather its borders so "
                                          "it wraps without a seam, and write it as a maps folder whose material.json "
                                          "carries meta.tile.size_mm (docs/TILE.md). Exit 2 when the maps show no "
                                          "repeat or fewer than two repeats.")
    t.add_argument("maps", help="maps folder (material.json)")
    add_output(t, "output maps folder for the tile")
    t.add_argument("--repeats", type=_repeats, default=None, metavar="NxM",
                   help="repeats of the cell along x and y (default 1x1, more where a side would be under 32 texels)")
    t.add_argument("--source", default="all", metavar="all|albedo|normal_x|normal_y|IMAGE",
                   help="signal to find the repeat on: all (albedo luminance and normal x, y together; default), one "
                        "map, or a guidance image of the maps' size")
    t.add_argument("--transfer", default="srgb", help="transfer function of an 8/16-bit --source image (default srgb)")
    t.add_argument("--blend", type=int, default=None, metavar="PX",
                   help="feathered border band in texels (default: 1/8 of the tile's shorter side; 0 = none)")
    add_work_options(t)
    t.set_defaults(fn=cmd_tile)
