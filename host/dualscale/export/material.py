"""``dualscale export``: one maps folder -> every requested format, with a manifest.

Layout of an export folder ``OUT``::

    OUT/export.json          manifest (written last: a folder with it is complete)
    OUT/maps/                the exported maps in our own conventions (dualscale-maps); with
                             ``tile``, the seamless tile, its record in ``meta.tile``
    OUT/exr/                 exchange EXR set (+ exchange.json; + the 1-sigma maps when the
                             maps folder has uncertainty/, issue 26)
    OUT/mtlx/<name>.mtlx     + textures
    OUT/gltf/<name>.gltf     + <name>.bin + textures
    OUT/glb/<name>.glb
    OUT/u3m/<name>.u3ma
    OUT/blend/<name>.blend   (only when asked for by name: needs bpy)

Each format folder is written in a temporary folder and renamed (:func:`atomic_dir`), so a
rerun after an interruption redoes only what is missing; a format whose folder is complete
and whose source is unchanged (same ``material.json`` digest and options; for ``exr`` also the
same ``uncertainty/`` digest) is skipped.

``export.json`` (version 1)::

    {"format": "dualscale-export", "version": 1, "name": ..., "source": "<maps dir>",
     "source_sha256": ..., "formats": {"glb": ["glb/<name>.glb"], ...},
     "repeat_mm": [w, h] | null, "tiled": bool, "tile": {...} | null, "options": {...},
     "uncertainty_sha256": ... | null}
"""

from __future__ import annotations

import hashlib
import re
import shutil
from pathlib import Path
from typing import Any, Callable, Sequence

from dualscale.errors import FormatError, InputError
from dualscale.formats.atomic import atomic_dir, write_json
from dualscale.formats.maps import (UNCERTAINTY_DIR, load_maps, load_uncertainty, maps_sha256, save_maps,
                                    save_uncertainty)
from dualscale.formats.versioned import read_versioned_json

from . import NAME_RE, ExportContext, _registry
from .exchange import exchange

FORMAT = "dualscale-export"
VERSION = 1
ALL_FORMATS = ("exr", "mtlx", "gltf", "glb", "u3m")
# formats given by name only, not part of "all": they need a tool outside the project's venv
# (blend: Blender's bpy, `make blender`)
OPTIONAL_FORMATS = ("blend",)


def formats_available() -> dict[str, Callable]:
    """The writers of :data:`ALL_FORMATS` (the ``method=`` registry of this package)."""
    return _registry()


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _uncertainty_digest(maps_dir: Path) -> str | None:
    """SHA-256 over ``uncertainty/``'s record and EXR files (names and bytes, read in chunks), or
    ``None`` when the maps folder has no uncertainty (no ``uncertainty.json``)."""
    folder = maps_dir / UNCERTAINTY_DIR
    if not (folder / "uncertainty.json").is_file():
        return None
    h = hashlib.sha256()
    for path in [folder / "uncertainty.json", *sorted(folder.glob("*.exr"))]:
        h.update(path.name.encode() + b"\0")
        with open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                h.update(chunk)
    return h.hexdigest()


def read_export(out: str | Path) -> dict[str, Any]:
    """The validated ``export.json`` of an export folder (``FileNotFoundError``/``FormatError``)."""
    path = Path(out) / "export.json"
    if not path.is_file():
        raise FileNotFoundError(f"no export.json in {out} (not a dualscale export folder)")
    doc = read_versioned_json(path, FORMAT, (VERSION,))
    for key in ("name", "formats", "repeat_mm"):
        if key not in doc:
            raise FormatError(f"{path}: missing {key!r}")
    return doc


def export_material(maps_dir: str | Path, out: str | Path, formats: Sequence[str] = ALL_FORMATS, *,
                    name: str | None = None, tile: bool = False, swatch_mm: tuple[float, float] | None = None,
                    meta: dict[str, Any] | None = None, tile_options: dict[str, Any] | None = None,
                    skip_unsized: bool = False) -> dict[str, Any]:
    """Export the maps folder ``maps_dir`` into ``out`` in each of ``formats``; returns the manifest.

    ``tile``: first cut a seamless tile of whole repeats (:func:`dualscale.tile.make_tile`, with
    ``tile_options``) and export the tile, whose physical size (``Tile.size_mm``) then goes into
    every format.  ``name``: the material's file stem (default: the maps folder's name, or its
    parent's when it is called ``maps``, sanitised).  ``skip_unsized``: leave out the formats that
    need a physical size (U3M) when the texel size is unknown, and list them under ``skipped``
    (else that is a ``UnitsError``).

    Every check happens before anything is written: ``InputError`` for an unknown format or name,
    or an ``out`` that holds the source maps (writing there would replace them); ``UnitsError``
    for U3M without a physical size; the maps' own ``FormatError``/``GeometryError``.  A rerun
    keeps the formats of an earlier export of the same source and options (``reused``); after an
    export of another source or options, the format folders it does not rewrite are removed, so
    nothing stale is left beside the manifest.

    The maps' 1-sigma uncertainty (``maps_dir/uncertainty/``, issue 26) goes into the ``exr``
    set (:mod:`.exr`; absent: nothing changes); a tiled export leaves it out (the tile is
    resampled, its sigma is not) and says so in ``exchange.json``, and an untiled export's
    ``maps/`` copy keeps it beside them (``maps/uncertainty/``, re-bound to the copy's
    ``maps_sha256``), where ``dualscale view`` finds it when the source has moved.  A changed
    uncertainty redoes ``exr`` and ``maps`` only.  ``FormatError`` for an uncertainty folder that does not read or whose size is
    not the maps'.
    """
    from dualscale.errors import UnitsError

    maps_dir, out = Path(maps_dir), Path(out)
    reg = formats_available()
    unknown = [f for f in formats if f not in reg]
    if unknown:
        raise InputError(f"unknown export format(s) {unknown}; choose from {sorted(reg)}")
    if not formats:
        raise InputError("no export format given")
    check_output(maps_dir, out)
    if "blend" in formats:
        from .blend import blender_python

        blender_python()  # ToolError now, not after the other formats are written
    src = maps_dir.resolve()
    if name is None:
        stem = src.parent.name if src.name == "maps" else src.name
        name = re.sub(r"[^A-Za-z0-9_.-]", "_", stem).strip("._-") or "material"
    check_name(name)
    maps, mmeta = load_maps(maps_dir)
    texel = mmeta.get("texel_mm")
    formats = list(dict.fromkeys(formats))
    skipped: dict[str, str] = {}
    if not texel and "u3m" in formats:
        why = (f"U3M needs the physical size of the texture and {maps_dir / 'material.json'} has no texel "
               "size (import photographs with --texel-mm)")
        if not skip_unsized:
            raise UnitsError(why)
        formats.remove("u3m")
        skipped["u3m"] = why
    source_sha = _digest(maps_dir / "material.json")
    uncertainty_sha = _uncertainty_digest(maps_dir)
    uncertainty, uncertainty_note = None, None
    if uncertainty_sha is not None:
        if tile:
            uncertainty_note = ("a tiled export: the tile is a resampled, feathered cut of the maps "
                                "(dualscale.tile) and the uncertainty is not cut with it")
        else:
            uncertainty = load_uncertainty(maps_dir)
            udoc = uncertainty[2]
            theirs = (udoc.get("meta") or {}).get("maps_sha256")
            if theirs and theirs != maps_sha256(maps_dir):
                raise FormatError(f"{maps_dir / UNCERTAINTY_DIR}: the uncertainty belongs to other maps (its "
                                  "maps_sha256 is not these maps'): refit, or remove the folder")
            if (udoc.get("height"), udoc.get("width")) != tuple(maps.shape):
                raise FormatError(f"{maps_dir / UNCERTAINTY_DIR / 'uncertainty.json'}: the uncertainty is "
                                  f"{udoc.get('height')} x {udoc.get('width')}, the maps {maps.shape[0]} x "
                                  f"{maps.shape[1]}")
    options = {"tile": bool(tile), "swatch_mm": list(swatch_mm) if swatch_mm else None,
               "tile_options": tile_options or {}}
    previous, stale = _previous(out, source_sha, options, uncertainty_sha)
    tile_info, repeat = None, None
    if tile:
        from dualscale.tile import make_tile

        t = make_tile(maps, texel, **(tile_options or {}))
        maps, texel, tile_info = t.maps, t.texel_mm, t.meta()
        repeat = tuple(float(v) for v in t.size_mm) if t.size_mm is not None else None
    ex = exchange(maps, texel)
    if not tile:
        repeat = ex.size_mm
    ctx = ExportContext(name=name, repeat_mm=repeat, tiled=bool(tile), swatch_mm=swatch_mm,
                        meta={"generator": _generator(), "source": str(maps_dir),
                              **({"radiometry": mmeta["radiometry"]} if mmeta.get("radiometry") else {}),
                              **(meta or {})},
                        uncertainty=uncertainty, uncertainty_note=uncertainty_note)
    out.mkdir(parents=True, exist_ok=True)
    done: dict[str, list[str]] = {}
    reused: list[str] = []
    if "maps" in previous and (out / "maps").is_dir():
        done["maps"] = previous["maps"]
    else:
        with atomic_dir(out / "maps") as tmp:
            save_maps(tmp, maps, {"source": str(maps_dir), "tile": tile_info}, texel_mm=texel)
            if uncertainty is not None:  # the export's maps keep their uncertainty (the viewer reads it there)
                sigma, und, udoc = uncertainty
                save_uncertainty(tmp, sigma, und, {**(udoc.get("meta") or {}), "maps_sha256": maps_sha256(tmp)})
            done["maps"] = sorted(f"maps/{p.relative_to(tmp).as_posix()}" for p in tmp.rglob("*") if p.is_file())
    for fmt in formats:
        if fmt in previous and (out / fmt).is_dir():
            done[fmt] = previous[fmt]
            reused.append(fmt)
            continue
        with atomic_dir(out / fmt) as tmp:
            files = reg[fmt](ex, ctx, tmp)
            done[fmt] = sorted(f"{fmt}/{Path(f).relative_to(tmp).as_posix()}" for f in files)
    for fmt, files in previous.items():  # complete formats of the same export not asked for this time
        if fmt not in done:
            done[fmt] = files
    for fmt in stale:
        if fmt not in done and fmt in reg and (out / fmt).is_dir():
            shutil.rmtree(out / fmt)
    doc = {"format": FORMAT, "version": VERSION, "name": name, "source": str(maps_dir),
           "source_sha256": source_sha, "formats": done, "repeat_mm": list(repeat) if repeat else None,
           "texel_mm": texel, "tiled": bool(tile), "tile": tile_info, "options": options,
           "skipped": skipped, "generator": ctx.meta["generator"], "uncertainty_sha256": uncertainty_sha}
    write_json(out / "export.json", doc)
    return {**doc, "reused": reused}


def check_output(maps_dir: str | Path, out: str | Path) -> None:
    """Refuse (``InputError``) an output folder that is or holds the source maps: the export
    writes ``OUT/maps`` and the format folders, which would replace them."""
    src, dst = Path(maps_dir).resolve(), Path(out).resolve()
    if src == dst or dst in src.parents:
        raise InputError(f"output folder {out} holds the source maps {maps_dir}: the export would replace "
                         "them; choose another output folder")


def check_name(name: str) -> str:
    """Refuse (``InputError``) a material name that is not a safe file stem."""
    if not NAME_RE.match(name or ""):
        raise InputError(f"material name {name!r}: use letters, digits, '_', '.', '-' (at most 64, not "
                         "starting with '.' or '-')")
    return name


def _previous(out: Path, source_sha: str, options: dict,
              uncertainty_sha: str | None = None) -> tuple[dict[str, list[str]], list[str]]:
    """``(formats, stale)``: the complete formats of an earlier export of the same source with the
    same options, or, when the earlier export was of something else, its format folders; an
    earlier ``exr`` of another uncertainty (``uncertainty_sha256``; none: ``None``) is stale."""
    try:
        doc = read_export(out)
    except (FileNotFoundError, FormatError):
        return {}, []
    if doc.get("source_sha256") != source_sha or doc.get("options") != options:
        return {}, list(doc["formats"])
    done = dict(doc["formats"])
    stale = []
    if doc.get("uncertainty_sha256") != uncertainty_sha:  # the exr set and the maps' copy carry it
        for fmt in ("exr", "maps"):
            if fmt in done:
                done.pop(fmt)
                stale.append(fmt)
    return {f: files for f, files in done.items() if all((out / p).is_file() for p in files)}, stale


def _generator() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"dualscale {version('dualscale')}"
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "dualscale"
