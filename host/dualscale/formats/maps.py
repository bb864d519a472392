"""SVBSDF maps on disk: one float32 EXR per active map, PNG previews, and ``material.json``.
The one reader (:func:`load_maps`) and writer (:class:`MapsWriter`, by rows; :func:`save_maps`,
whole maps) of maps, for ground truth (``synth``), fitted maps (``fit``), propagated maps
(``propagate run``, streamed by rows) and exports.

``material.json`` (version 2)::

    {"format": "dualscale-maps", "version": 2, "maps": [names], "height": H, "width": W,
     "texel_mm": t | null, "field_mm": [W * t, H * t] | null,
     "conventions": CONVENTIONS, "meta": {...}}

``texel_mm`` is the physical size of one texel (the dataset's pixel pitch, carried through fit
and propagation); version-1 files (no size) are still read, with ``texel_mm`` null.  The value
conventions (:data:`CONVENTIONS`) are the single source of truth for every map on disk; the
canonical in-memory maps are :class:`dualscale.bsdf.MaterialMaps` (seed Sec. 5).

``MAPS/uncertainty/`` (issue 26; :func:`save_uncertainty`, :class:`UncertaintyWriter` by rows,
:func:`load_uncertainty`): the 1-sigma uncertainty of each map in its own units
(:data:`SIGMA_UNITS`), half float, NaN where undetermined, with ``undetermined.exr`` and
``uncertainty.json`` (version 1).

Loading refuses (``FormatError``/``GeometryError``) names it does not know, sizes that disagree
with ``material.json``, non-finite values and normal maps whose vectors are not unit length
(tolerance 1e-2) or point below the sample plane (z < 0; z = 0, in the plane, is accepted).
"""

from __future__ import annotations

import contextlib
import hashlib
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dualscale.bsdf import MAP_CHANNELS, MaterialMaps, validate_maps
from dualscale.errors import FormatError, GeometryError

from .atomic import atomic_path, remove_file, write_json
from .exr import read_exr, srgb_encode, verify_image, write_exr, write_pixels
from .versioned import read_versioned_json

FORMAT = "dualscale-maps"
VERSION = 2
_CHANNELS = {1: ("Y",), 3: ("R", "G", "B")}
_NORMAL = ("X", "Y", "Z")
NORMAL_TOLERANCE = 1e-2
CONVENTIONS = {
    "albedo": "linear RGB (Rec.709 primaries), [0,1]",
    "normal": "unit vector XYZ in the macro frame, +z = macro normal, +x = image right, +y = image up",
    "tangent": "azimuth = pi * value, CCW from image +x (axial)",
    "ior": "eta = 1 + 2 * value",
    "roughness": "GGX roughness r in [0,1] (alpha = r^2, Burley 2015)",
    "rows": "row 0 is the top of the image (+y)",
    "texel_mm": "physical size of one texel in mm (null when unknown)",
}


def channel_names(name: str) -> tuple[str, ...]:
    """EXR channel names of map ``name``."""
    return _NORMAL if name == "normal" else _CHANNELS[MAP_CHANNELS[name]]


def save_maps(root: str | Path, maps: MaterialMaps, meta: dict | None = None, previews: bool = True,
              texel_mm: float | None = None, attributes: dict[str, str] | None = None) -> Path:
    """Write every active map as ``<name>.exr`` (+ ``.png`` previews) and ``material.json``
    (written last, atomically: a folder with ``material.json`` is complete).  An earlier
    ``material.json`` is removed before the first map is written, so a write that fails half-way
    (a full disk) never leaves new maps under an old, complete-looking record; maps and previews
    of an earlier set that this one lacks (e.g. ``transmittance`` of another material) are
    removed, so no reader picks up a stale map.  :class:`MapsWriter` writes the same files by rows.

    ``texel_mm``: texel size in mm (``None``: taken from ``meta["texel_mm"]`` when present);
    ``attributes``: extra EXR header attributes (``dualscale:*`` strings) for every map, plus
    ``dualscale:map`` = the map's name.  Returns the path of ``material.json``.
    """
    validate_maps(maps)
    root = Path(root)
    texel_mm = _texel(texel_mm, meta)
    remove_file(root / "material.json")
    for name, t in maps.items():
        arr = t.detach().cpu().numpy()
        write_exr(root / f"{name}.exr", arr, channel_names(name), _attributes(name, attributes))
        if previews:  # the bytes MapsWriter writes by rows (one encoding: _preview_u8)
            u8 = _preview_u8(name, arr.reshape(arr.shape[0], arr.shape[1], -1))
            write_pixels(root / f"{name}.png", u8, _png_spec(u8))
    h, w = maps.shape
    return _finish(root, [n for n, _ in maps.items()], h, w, texel_mm, meta, previews)


def _texel(texel_mm: float | None, meta: dict | None) -> float | None:
    if texel_mm is None and meta and meta.get("texel_mm"):
        texel_mm = float(meta["texel_mm"])
    if texel_mm is not None and not (np.isfinite(texel_mm) and texel_mm > 0):
        raise ValueError(f"texel_mm must be a positive number of mm, got {texel_mm!r}")
    return texel_mm


def _attributes(name: str, attributes: dict[str, str] | None) -> dict[str, str] | None:
    """EXR header attributes of map ``name``: none, or ``attributes`` plus ``dualscale:map``."""
    return {**attributes, "dualscale:map": name} if attributes else None


def _finish(root: Path, names: list[str], h: int, w: int, texel_mm: float | None, meta: dict | None,
            previews: bool) -> Path:
    """After the maps: remove stale maps and previews of an earlier set, write ``material.json``."""
    written = set(names)
    for name in MAP_CHANNELS:
        for suffix in (".exr", ".png"):
            if name not in written or (suffix == ".png" and not previews):
                remove_file(root / f"{name}{suffix}")
    doc = {"format": FORMAT, "version": VERSION, "maps": list(names), "height": h, "width": w,
           "texel_mm": texel_mm, "field_mm": None if texel_mm is None else [w * texel_mm, h * texel_mm],
           "conventions": CONVENTIONS, "meta": meta or {}}
    return write_json(root / "material.json", doc)


def _preview_u8(name: str, rows: np.ndarray) -> np.ndarray:
    """8-bit preview rows of map ``name`` (as :func:`dualscale.formats.exr.write_png_preview`:
    sRGB curve for albedo and transmittance, normals as ``0.5 n + 0.5``, others clipped)."""
    img = np.asarray(rows, np.float64)
    if name == "normal":
        img = np.clip(0.5 * img + 0.5, 0, 1)
    elif name in ("albedo", "transmittance"):
        img = srgb_encode(img)
    else:
        img = np.clip(np.nan_to_num(img), 0, 1)
    return np.ascontiguousarray(np.round(img * 255).astype(np.uint8))


def _png_spec(u8: np.ndarray):
    """The OpenImageIO spec of an 8-bit preview ``u8`` (H, W, C)."""
    import OpenImageIO as oiio

    return oiio.ImageSpec(u8.shape[1], u8.shape[0], u8.shape[2], "uint8")


def _close_quietly(out) -> None:
    with contextlib.suppress(Exception):
        out.close()



def _open_output(writer, final: Path, spec) -> None:
    """Open ``final`` for a writer by rows (:class:`MapsWriter`, :class:`UncertaintyWriter`): a
    temporary file in ``writer._stack``, checked whole before it takes its name (OpenImageIO
    reports success for a PNG a full disk truncated), its ImageOutput closed before the file is
    deleted (an error) or renamed, and kept in ``writer._outs``."""
    import OpenImageIO as oiio

    tmp = writer._stack.enter_context(atomic_path(final, verify=lambda t: verify_image(t, spec, final)))
    out = oiio.ImageOutput.create(str(tmp))
    if out is None or not out.open(str(tmp), spec):
        raise OSError(f"cannot write {final}: {oiio.geterror()}")
    writer._stack.callback(_close_quietly, out)
    writer._outs.append((final, out))


def _commit(writer, kind, value, tb, where: Path) -> bool:
    """The end of a writer's with-block (:class:`MapsWriter`, :class:`UncertaintyWriter`):
    on an error (``kind``) close and delete every temporary file and return False; else check
    that all rows came, close each file (a full disk shows here) and rename them into place,
    deleting them all if any fails; True when the files are in place."""
    stack, writer._stack = writer._stack, None
    if kind is not None:
        stack.__exit__(kind, value, tb)  # closes and deletes every temporary file
        return False
    try:
        if writer.rows != writer.height:
            raise ValueError(f"{where}: {writer.rows} of {writer.height} rows written")
        for final, out in writer._outs:  # the last buffered bytes go out here: a full disk can show only now
            if not out.close():
                raise OSError(f"cannot write {final}: {out.geterror() or 'closing the file failed'}")
    except BaseException:
        stack.__exit__(*sys.exc_info())
        raise
    stack.close()  # renames every file into place
    return True

class MapsWriter:
    """The maps writer by rows: the files of :func:`save_maps` (same EXR header, previews, stale
    maps removed, ``material.json`` last), written a strip of rows at a time, so that a tiled
    propagation (``dualscale.propagate.infer``) never holds the maps whole and writes while it
    computes.

    Use it as a context manager::

        with MapsWriter(root, ["albedo", "roughness"], H, W, meta, previews=False) as out:
            out.write(0, {"albedo": a0, "roughness": r0})     # rows 0 .. n0 - 1, (n0, W, C) each
            out.write(n0, {...})                               # the next rows, in order

    Entering removes an earlier ``material.json`` (as :func:`save_maps` does before its first
    map).  Every ``<name>.exr`` (float32, zip, OpenImageIO ``write_scanlines``) and preview goes
    to a temporary file (:func:`dualscale.formats.atomic.atomic_path`); a clean exit after all
    ``H`` rows closes them, checks each whole (:func:`dualscale.formats.exr.verify_image`; a full
    disk shows here, :class:`~dualscale.errors.OutputError` naming the file), renames them
    into place and writes ``material.json`` last.  An exit on an error or an interrupt
    (``KeyboardInterrupt``) closes and deletes the temporary files: no new file appears under a
    final name.  Rows must come in order and every call gives every map, finite (``ValueError``
    naming the map and the rows).  One thread writes (not thread-safe).
    """

    def __init__(self, root: str | Path, names: list[str], height: int, width: int, meta: dict | None = None,
                 previews: bool = True, texel_mm: float | None = None,
                 attributes: dict[str, str] | None = None) -> None:
        self.root = Path(root)
        self.path = self.root / "material.json"
        bad = [n for n in names if n not in MAP_CHANNELS]
        if bad or not names:
            raise ValueError(f"maps must be a non-empty subset of {list(MAP_CHANNELS)}, got {names}")
        if "albedo" not in names or "roughness" not in names:
            raise ValueError(f"albedo and roughness maps are required, got {names}")
        self.names, self.height, self.width = list(names), int(height), int(width)
        self.meta, self.previews, self.attributes = meta, previews, attributes
        self.texel_mm = _texel(texel_mm, meta)
        self.rows = 0  # rows written so far
        self._stack: contextlib.ExitStack | None = None
        self._outs: list[tuple[Path, Any]] = []  # (final path, OpenImageIO ImageOutput)

    def __enter__(self) -> "MapsWriter":
        import OpenImageIO as oiio

        self._stack = contextlib.ExitStack()
        try:
            remove_file(self.path)
            for name in self.names:
                spec = oiio.ImageSpec(self.width, self.height, MAP_CHANNELS[name], "float")
                spec.channelnames = channel_names(name)
                spec.attribute("compression", "zip")  # as formats.exr.write_exr
                spec.attribute("DateTime", "")  # as write_exr: the same pixels give the same bytes
                for k, v in (_attributes(name, self.attributes) or {}).items():
                    spec.attribute(k, str(v))
                self._open(self.root / f"{name}.exr", spec)
                if self.previews:
                    self._open(self.root / f"{name}.png",
                               oiio.ImageSpec(self.width, self.height, MAP_CHANNELS[name], "uint8"))
        except BaseException:
            self._stack.__exit__(*sys.exc_info())
            raise
        return self

    def _open(self, final: Path, spec) -> None:
        _open_output(self, final, spec)

    def write(self, y0: int, rows: dict[str, np.ndarray]) -> None:
        """Write rows ``y0 .. y0 + n - 1`` of every map: ``{name: (n, W, C) float}``."""
        if self._stack is None:
            raise RuntimeError("MapsWriter.write outside its with-block")
        if y0 != self.rows:
            raise ValueError(f"{self.root}: rows must come in order: got row {y0}, expected {self.rows}")
        if set(rows) != set(self.names):
            raise ValueError(f"{self.root}: rows for maps {sorted(rows)}, expected {sorted(self.names)}")
        n = None
        arrays = {}
        for name in self.names:
            a = np.asarray(rows[name], np.float32)
            if a.ndim == 2:
                a = a[..., None]
            c = MAP_CHANNELS[name]
            if a.ndim != 3 or a.shape[1:] != (self.width, c) or (n is not None and a.shape[0] != n):
                raise ValueError(f"map {name!r} rows must have shape ({n or 'n'}, {self.width}, {c}), "
                                 f"got {a.shape}")
            n = a.shape[0]
            if not np.isfinite(a).all():
                raise ValueError(f"map {name!r} contains NaN or Inf (rows {y0}..{y0 + n - 1})")
            arrays[name] = a
        if y0 + n > self.height:
            raise ValueError(f"{self.root}: rows {y0}..{y0 + n - 1} beyond the height {self.height}")
        outs = iter(self._outs)
        for name in self.names:
            self._scanlines(next(outs), y0, arrays[name])
            if self.previews:
                self._scanlines(next(outs), y0, _preview_u8(name, arrays[name]))
        self.rows = y0 + n

    @staticmethod
    def _scanlines(target: tuple[Path, Any], y0: int, a: np.ndarray) -> None:
        final, out = target
        if not out.write_scanlines(y0, y0 + a.shape[0], 0, np.ascontiguousarray(a)):
            raise OSError(f"cannot write {final}: {out.geterror()}")

    def __exit__(self, kind, value, tb) -> None:
        if not _commit(self, kind, value, tb, self.root):
            return
        _finish(self.root, self.names, self.height, self.width, self.texel_mm, self.meta, self.previews)


def read_material_json(root: str | Path) -> dict[str, Any]:
    """The validated ``material.json`` of a maps folder."""
    path = Path(root) / "material.json"
    if not path.is_file():
        raise FileNotFoundError(f"no material.json in {root} (not a maps folder)")
    doc = read_versioned_json(path, FORMAT, (1, VERSION))
    for key in ("maps", "height", "width"):
        if key not in doc:
            raise FormatError(f"{path}: missing {key!r}")
    return doc


def load_maps(root: str | Path, dtype: torch.dtype = torch.float32,
              box: tuple[int, int, int, int] | None = None) -> tuple[MaterialMaps, dict]:
    """Read a maps folder written by :func:`save_maps`; returns ``(maps, meta)`` where ``meta``
    is the file's ``meta`` plus ``texel_mm`` and ``field_mm`` (``None`` when unknown).  ``box``
    ``(y0, y1, x0, x1)``: only that region of every map (the whole maps' crop; read by
    :func:`~dualscale.formats.exr.read_exr` region reads, so a map larger than memory can be
    read a band at a time), ``ValueError`` when it is outside the maps."""
    root = Path(root)
    doc = read_material_json(root)
    arrays = {}
    size = (doc["height"], doc["width"])
    want = size if box is None else (box[1] - box[0], box[3] - box[2])
    for name in doc["maps"]:
        if name not in MAP_CHANNELS:
            raise FormatError(f"{root / 'material.json'}: unknown map {name!r}")
        arr = (read_exr(root / f"{name}.exr", channel_names(name)) if box is None else
               read_exr(root / f"{name}.exr", channel_names(name), box=box, size=size))
        if arr.shape[:2] != want:
            raise FormatError(f"{root / name}.exr is {arr.shape[:2]}, material.json says "
                              f"{(doc['height'], doc['width'])}")
        if not np.isfinite(arr).all():
            raise FormatError(f"{root / name}.exr: {int((~np.isfinite(arr)).sum())} non-finite values")
        if name == "normal":
            check_normals(arr, f"{root / name}.exr")
        arrays[name] = torch.from_numpy(np.ascontiguousarray(arr)).to(dtype)
    if "albedo" not in arrays or "roughness" not in arrays:
        raise FormatError(f"{root}: albedo and roughness maps are required")
    maps = MaterialMaps(**arrays)
    validate_maps(maps)
    meta = dict(doc.get("meta", {}))
    meta["texel_mm"] = doc.get("texel_mm", meta.get("texel_mm"))
    t = meta["texel_mm"]
    meta["field_mm"] = doc.get("field_mm") or (None if not t else [doc["width"] * t, doc["height"] * t])
    return maps, meta


def check_normals(normal: np.ndarray, where: str) -> None:
    """Refuse ``(H, W, 3)`` normals that are not unit length or point below the sample plane
    (``z < 0``).  ``z = 0`` -- a normal in the plane, which the fit's hemisphere mapping reaches
    at its rim on grazing surfaces -- is accepted (docs/APPEARANCE.md: stored with ``z >= 0``)."""
    n = np.asarray(normal, np.float64)
    length = np.linalg.norm(n, axis=-1)
    bad = np.abs(length - 1) > NORMAL_TOLERANCE
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise GeometryError(f"{where}: {int(bad.sum())} normals are not unit vectors (first at row {r}, col {c}: "
                            f"length {length[r, c]:.4f}; tolerance {NORMAL_TOLERANCE})")
    below = n[..., 2] < 0
    if below.any():
        r, c = np.argwhere(below)[0]
        raise GeometryError(f"{where}: {int(below.sum())} normals point below the sample plane "
                            f"(z < 0; first at row {r}, col {c})")


# --------------------------------------------------------------------------- uncertainty (issue 26)

#: the per-pixel uncertainty beside a maps folder, ``MAPS/uncertainty/`` (issue 26):
#: ``uncertainty.json`` (written last) and one half-float EXR per map
UNCERTAINTY_FORMAT = "dualscale-uncertainty"
UNCERTAINTY_VERSION = 1
UNCERTAINTY_DIR = "uncertainty"
#: channels of each map's 1-sigma uncertainty (the normal and the tangent as one angle)
SIGMA_CHANNELS = {"albedo": 3, "transmittance": 3, "specular_tint": 1, "opacity": 1, "roughness": 1,
                  "anisotropy": 1, "ior": 1, "normal": 1, "tangent": 1}
#: each map's uncertainty unit
#: the half-float files hold ``sigma / SIGMA_SCALE[map]`` (a power of two, recorded in
#: ``uncertainty.json``'s ``"scales"`` and each EXR's ``dualscale:sigma_scale``): half float's
#: 11 significant bits then reach from ~1e-12 (the map's value; 2e-10 degrees) up to 4 (256
#: degrees) instead of 6e-8..65504, so the tiny sigma of a nearly noise-free fit is not stored as
#: 0; larger sigmas are stored at the top of the range (they mean "unknown" anyway)
SIGMA_SCALE = {"albedo": 2.0 ** -14, "transmittance": 2.0 ** -14, "specular_tint": 2.0 ** -14, "opacity": 2.0 ** -14,
               "roughness": 2.0 ** -14, "anisotropy": 2.0 ** -14, "ior": 2.0 ** -14, "normal": 2.0 ** -8,
               "tangent": 2.0 ** -8}
_HALF_MAX = 65504.0
SIGMA_UNITS = {"albedo": "reflectance (the map's linear value)", "transmittance": "the map's linear value",
               "specular_tint": "the map's value", "opacity": "the map's value", "roughness": "the map's value",
               "anisotropy": "the map's value", "ior": "eta (index of refraction)",
               "normal": "degrees (RMS angle to the true normal)", "tangent": "degrees of azimuth"}


def _sigma_names(name: str) -> tuple[str, ...]:
    c = SIGMA_CHANNELS[name]
    return ("Y",) if c == 1 else ("R", "G", "B")


def save_uncertainty(root: str | Path, sigma: dict[str, np.ndarray], undetermined: dict[str, np.ndarray],
                     meta: dict | None = None) -> Path:
    """Write the 1-sigma uncertainty of the maps under ``root`` into ``root/uncertainty/``:
    ``<name>.exr`` per map (half float, zip; :data:`SIGMA_CHANNELS` channels, in
    :data:`SIGMA_UNITS`; NaN where the value is undetermined), ``undetermined.exr`` (one
    half-float channel per map and sigma channel, named ``<name>.<channel>``, 1 = undetermined)
    and ``uncertainty.json`` (written last, atomically: ``{"format", "version", "maps",
    "height", "width", "units", "meta"}``; an earlier one is removed first).  ``sigma``:
    ``{name: (H, W, C)}`` (or ``(H, W)`` for one channel), finite and >= 0 where determined;
    ``undetermined``: ``{name: (H, W, C)}`` bool.  Half float keeps the folder at half the
    maps' own size (a sigma needs 3 significant digits, half float has 3.3); the files hold
    ``sigma / SIGMA_SCALE`` (:data:`SIGMA_SCALE`, recorded in ``"scales"``), so the range
    reaches down to ~1e-12.  The whole maps as
    one strip of :class:`UncertaintyWriter` (the same bytes as a write by rows).  Returns the
    path of ``uncertainty.json``.  ``ValueError`` for an unknown map, a shape that is not the
    others', or a sigma that is negative or not finite where determined (nothing is written or
    removed then).  Source: issue 26; the maps' units, seed Sec. 5."""
    if set(sigma) != set(undetermined) or not sigma:
        raise ValueError(f"sigma maps {sorted(sigma)} and undetermined masks {sorted(undetermined)} must name "
                         "the same maps")
    first = np.asarray(next(iter(sigma.values())))
    if first.ndim not in (2, 3):
        raise ValueError(f"sigma of {next(iter(sigma))!r} is {first.shape}; expected (H, W, C)")
    writer = UncertaintyWriter(root, list(sigma), first.shape[0], first.shape[1], meta)
    strip = writer.check(0, sigma, undetermined)  # before anything is removed or written
    with writer:
        writer.put(0, strip)
    return writer.path


class UncertaintyWriter:
    """The uncertainty writer by rows: the files of :func:`save_uncertainty` (the same bytes),
    written a strip of rows at a time, so that the fit out of core (``dualscale.fit``), which
    never holds a whole map, writes the uncertainty as it computes it (issue 26).

    Use it as a context manager::

        with UncertaintyWriter(root, ["albedo", "normal"], H, W, meta) as out:
            out.write(0, {"albedo": s0, "normal": n0}, {"albedo": u0, "normal": m0})  # rows 0 .. n0 - 1
            out.write(n0, {...}, {...})                                               # the next rows

    ``sigma`` strips are ``{name: (n, W, C)}`` float (``(n, W)`` for one channel; ``C`` =
    :data:`SIGMA_CHANNELS`), in :data:`SIGMA_UNITS`, finite and >= 0 where determined;
    ``undetermined`` strips ``{name: (n, W, C)}`` bool (1 = undetermined: its sigma is stored
    as NaN, whatever was given).  Entering removes an earlier ``uncertainty.json``.  Every
    ``root/uncertainty/<name>.exr`` and ``undetermined.exr`` (half float, zip, OpenImageIO
    ``write_scanlines``) goes to a temporary file (:func:`dualscale.formats.atomic.atomic_path`);
    a clean exit after all ``height`` rows closes them, checks each whole
    (:func:`dualscale.formats.exr.verify_image`; a full disk shows here,
    :class:`~dualscale.errors.OutputError` naming the file), renames them into place, removes
    the maps of an earlier set that this one lacks and writes ``uncertainty.json`` last.  An
    exit on an error or an interrupt (``KeyboardInterrupt``) closes and deletes the temporary
    files: no new file appears under a final name.  ``ValueError`` for an unknown or missing
    map, rows out of order or beyond ``height``, a strip whose shape is not ``(n, W, C)`` for
    every map alike, or a sigma that is negative or not finite where determined (naming the map
    and the rows).  One thread writes (not thread-safe).  Source: issue 26; seed Sec. 5.
    """

    def __init__(self, root: str | Path, names: list[str], height: int, width: int,
                 meta: dict | None = None) -> None:
        self.folder = Path(root) / UNCERTAINTY_DIR
        self.path = self.folder / "uncertainty.json"
        bad = [n for n in names if n not in SIGMA_CHANNELS]
        if bad or not names:
            raise ValueError(f"unknown map(s) {bad or names!r}; expected a non-empty subset of {list(SIGMA_CHANNELS)}")
        if len(set(names)) != len(names):
            raise ValueError(f"maps named twice: {names}")
        self.names, self.height, self.width, self.meta = list(names), int(height), int(width), meta
        if self.height < 1 or self.width < 1:
            raise ValueError(f"the maps must have at least one row and column, got {self.height} x {self.width}")
        self.rows = 0  # rows written so far
        self._stack: contextlib.ExitStack | None = None
        self._outs: list[tuple[Path, Any]] = []  # (final path, OpenImageIO ImageOutput): maps, then the mask

    def _spec(self, channels: list[str] | tuple[str, ...]):
        import OpenImageIO as oiio

        spec = oiio.ImageSpec(self.width, self.height, len(channels), "half")
        spec.channelnames = tuple(channels)
        spec.attribute("compression", "zip")
        spec.attribute("DateTime", "")  # the same pixels give the same bytes
        return spec

    def __enter__(self) -> "UncertaintyWriter":
        self._stack = contextlib.ExitStack()
        try:
            remove_file(self.path)
            self.folder.mkdir(parents=True, exist_ok=True)
            for name in self.names:
                spec = self._spec(_sigma_names(name))
                spec.attribute("dualscale:sigma_of", name)
                spec.attribute("dualscale:unit", SIGMA_UNITS[name])
                spec.attribute("dualscale:sigma_scale", float(SIGMA_SCALE[name]))
                self._open(self.folder / f"{name}.exr", spec)
            self._open(self.folder / "undetermined.exr",
                       self._spec([f"{n}.{c}" for n in self.names for c in _sigma_names(n)]))
        except BaseException:
            self._stack.__exit__(*sys.exc_info())
            self._stack = None
            raise
        return self

    def _open(self, final: Path, spec) -> None:
        _open_output(self, final, spec)

    def check(self, y0: int, sigma: dict[str, np.ndarray],
              undetermined: dict[str, np.ndarray]) -> tuple[int, list[np.ndarray]]:
        """Validate a strip (see the class docstring) without writing it: ``(y0, [half-float
        (n, W, C) per map in order, NaN where undetermined] + [the (n, W, sum C) mask])``."""
        if y0 != self.rows:
            raise ValueError(f"{self.folder}: rows must come in order: got row {y0}, expected {self.rows}")
        if set(sigma) != set(self.names) or set(undetermined) != set(self.names):
            raise ValueError(f"{self.folder}: sigma for maps {sorted(sigma)} and masks for {sorted(undetermined)}, "
                             f"expected {sorted(self.names)} both")
        n = None
        arrays, masks = [], []
        for name in self.names:
            s = np.asarray(sigma[name], np.float64)
            u = np.asarray(undetermined[name], bool)
            s = s[..., None] if s.ndim == 2 else s
            u = u[..., None] if u.ndim == 2 else u
            c = SIGMA_CHANNELS[name]
            if s.ndim != 3 or s.shape[1:] != (self.width, c) or u.shape != s.shape or \
                    (n is not None and s.shape[0] != n):
                raise ValueError(f"sigma of {name!r} (rows from {y0}) is {s.shape}, its mask {u.shape}; expected "
                                 f"({n or 'n'}, {self.width}, {c}) both")
            n = s.shape[0]
            bad = ~u & ~(np.isfinite(s) & (s >= 0))
            if bad.any():
                raise ValueError(f"sigma of {name!r}: {int(bad.sum())} determined values are negative or not finite "
                                 f"(rows {y0}..{y0 + n - 1})")
            stored = np.minimum(s / SIGMA_SCALE[name], _HALF_MAX)
            arrays.append(np.ascontiguousarray(np.where(u, np.nan, stored).astype(np.float16)))
            masks.append(u)
        if n == 0 or y0 + n > self.height:
            raise ValueError(f"{self.folder}: rows {y0}..{y0 + n - 1} (n = {n}) empty or beyond the height "
                             f"{self.height}")
        arrays.append(np.ascontiguousarray(np.concatenate(masks, -1).astype(np.float16)))
        return y0, arrays

    def put(self, y0: int, strip: tuple[int, list[np.ndarray]]) -> None:
        """Write a strip that :meth:`check` returned (for rows ``y0``)."""
        if self._stack is None:
            raise RuntimeError("UncertaintyWriter.write outside its with-block")
        if strip[0] != y0 or y0 != self.rows:
            raise ValueError(f"{self.folder}: rows must come in order: got row {y0}, expected {self.rows}")
        arrays = strip[1]
        n = arrays[0].shape[0]
        for (final, out), a in zip(self._outs, arrays):
            if not out.write_scanlines(y0, y0 + n, 0, a):
                raise OSError(f"cannot write {final}: {out.geterror()}")
        self.rows = y0 + n

    def write(self, y0: int, sigma: dict[str, np.ndarray], undetermined: dict[str, np.ndarray]) -> None:
        """Write rows ``y0 .. y0 + n - 1`` of every map: ``sigma`` ``{name: (n, W, C)}``,
        ``undetermined`` ``{name: (n, W, C) bool}`` (see the class docstring)."""
        if self._stack is None:
            raise RuntimeError("UncertaintyWriter.write outside its with-block")
        self.put(y0, self.check(y0, sigma, undetermined))

    def __exit__(self, kind, value, tb) -> None:
        if not _commit(self, kind, value, tb, self.folder):
            return
        for stale in self.folder.glob("*.exr"):  # the maps of an earlier set that this one lacks
            if stale.stem not in self.names and stale.stem != "undetermined":
                remove_file(stale)
        from .run import file_sha256

        files = [f"{n}.exr" for n in self.names] + ["undetermined.exr"]
        doc = {"format": UNCERTAINTY_FORMAT, "version": UNCERTAINTY_VERSION, "maps": list(self.names),
               "height": self.height, "width": self.width, "units": {n: SIGMA_UNITS[n] for n in self.names},
               "scales": {n: SIGMA_SCALE[n] for n in self.names},
               "files_sha256": {f: file_sha256(self.folder / f) for f in files}, "meta": self.meta or {}}
        write_json(self.path, doc)


def maps_sha256(root: str | Path) -> str:
    """SHA-256 over the maps folder's map files (each listed map's name and its EXR's bytes, in
    ``material.json``'s order; not ``material.json`` itself, whose metadata differ between the
    fit's paths): the identity the uncertainty beside the maps records (``meta.maps_sha256``), so
    a reader can tell an uncertainty of other maps.  ``FileNotFoundError``/``FormatError`` as
    :func:`load_maps` for a folder without a readable ``material.json``."""
    from .run import file_sha256

    root = Path(root)
    doc = read_versioned_json(root / "material.json", FORMAT, VERSION)
    h = hashlib.sha256()
    for name in doc.get("maps", []):
        h.update(f"{name}:{file_sha256(root / f'{name}.exr')};".encode())
    return h.hexdigest()


def _check_files(folder: Path, doc: dict) -> None:
    """Each file ``uncertainty.json`` records (``"files_sha256"``; a record written before it
    had none is not checked) must be the one written with it: a sigma file copied from another
    fit, or a map put in its place, is refused (:class:`~dualscale.errors.FormatError` naming the
    file) rather than read as this fit's sigma."""
    from .run import file_sha256

    record = doc.get("files_sha256")
    if record is None:
        return
    if not isinstance(record, dict):
        raise FormatError(f"{folder / 'uncertainty.json'}: 'files_sha256' is {type(record).__name__}, not a record")
    for f, want in record.items():
        p = folder / str(f)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: listed in uncertainty.json but missing")
        if file_sha256(p) != want:
            raise FormatError(f"{p} is not the file uncertainty.json was written with (its SHA-256 differs): "
                              "a sigma file replaced or copied from another fit; fit again to rewrite the "
                              "uncertainty")


def load_uncertainty(root: str | Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, Any]]:
    """``(sigma, undetermined, doc)`` written by :func:`save_uncertainty` under ``root``
    (float32 ``(H, W, C)`` with NaN where undetermined; bool ``(H, W, C)``; the
    ``uncertainty.json`` record).  Raises ``FileNotFoundError`` when there is none,
    :class:`~dualscale.errors.FormatError` for another format or version, an unknown map, sizes
    that disagree with the record, a sigma that is negative or not finite where determined, or
    NaN where the mask says determined."""
    folder = Path(root) / UNCERTAINTY_DIR
    path = folder / "uncertainty.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no uncertainty beside these maps")
    doc = read_versioned_json(path, UNCERTAINTY_FORMAT, UNCERTAINTY_VERSION)
    _check_files(folder, doc)
    h, w = doc.get("height"), doc.get("width")
    mask = read_exr(folder / "undetermined.exr")
    if mask.shape[:2] != (h, w):
        raise FormatError(f"{folder / 'undetermined.exr'} is {mask.shape[:2]}, uncertainty.json says {(h, w)}")
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(folder / "undetermined.exr"))
    try:
        channels = list(inp.spec().channelnames)
    finally:
        inp.close()
    sigma, und = {}, {}
    for name in doc.get("maps", []):
        if name not in SIGMA_CHANNELS:
            raise FormatError(f"{path}: unknown map {name!r}")
        scale = (doc.get("scales") or {}).get(name, 1.0)  # (files without "scales" hold sigma itself)
        if not isinstance(scale, (int, float)) or not 0 < scale < float("inf"):
            raise FormatError(f"{path}: the scale of {name!r} is {scale!r}, not a positive number")
        s = read_exr(folder / f"{name}.exr", _sigma_names(name)) * np.float32(scale)
        if s.shape[:2] != (h, w):
            raise FormatError(f"{folder / name}.exr is {s.shape[:2]}, uncertainty.json says {(h, w)}")
        try:
            idx = [channels.index(f"{name}.{c}") for c in _sigma_names(name)]
        except ValueError:
            raise FormatError(f"{folder / 'undetermined.exr'}: no mask channel for {name!r}") from None
        u = mask[..., idx] > 0.5
        ok = np.isfinite(s) & (s >= 0)
        if (~u & ~ok).any():
            raise FormatError(f"{folder / name}.exr: {int((~u & ~ok).sum())} determined values are negative or "
                              "not finite")
        sigma[name], und[name] = np.where(u, np.nan, s).astype(np.float32), u
    return sigma, und, doc
