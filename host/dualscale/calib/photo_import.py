"""Import photographs from other rigs (RTI domes, relight, lab light stages, a camera and a lamp)
into our photometric dataset (:mod:`dualscale.formats.dataset`), as ``dualscale import`` runs it.

Input: a folder of images (PNG, JPEG, TIFF 8/16 bit, EXR), one per light, and a light file
(``.lp`` or our ``.json``, :mod:`dualscale.formats.lightfile`) naming each image and its light
direction (+x image right, +y image up, +z towards the camera; unit, from the object towards the
light).  Output: a dataset of one orthographic camera ``"photo"``, one unpolarised LED record
per image (``analyzer_deg`` None), linear Rec.709 radiance.

Radiometry (:func:`radiometry`).
  * Integer images are decoded by a camera response that is either **estimated from the
    photographs** (``transfer="auto"``: :mod:`dualscale.calib.response`, stated as an estimate
    with its uncertainty and evidence), taken from a matte reference sphere recorded in the
    light file (``"lights"``), or **stated** (``srgb``, ``linear``, ``gamma:G``).  A stated or
    recorded response is never taken on trust: it is checked against the photographs, and a
    contradiction is a warning naming the estimate (refused with ``strict``).  Nothing is a
    silent default: no transfer at all is refused.  EXR is linear already.
  * The lights' relative intensities are the light file's when it gives them, else estimated
    with the response (semi-calibrated photometric stereo; ``intensities=`` overrides:
    :data:`INTENSITIES`).  Everything is recorded in ``extra.import.radiometry``.
  * ``saturation`` = 1.0 for integer images (the top code value decodes to 1.0): pixels with a
    channel at the top code are clipped and never fitted.  EXR images have no known clip level
    (``null``).
  * **Light intensity.**  ``relative_radiance`` means an LED of intensity 1 gives unit
    irradiance; the power of another rig's lights (and its exposure) is unknown, and only the
    product ``albedo x intensity`` is observable.  The importer therefore sets every image's
    ``light.intensity`` to ``E x rel_k`` (``rel_k`` the light file's relative intensity, 1 when
    absent) with ``E`` chosen so that the 99th percentile of the Lambertian albedo over the
    sample (Woodham's least squares, brightest channel) is :data:`TARGET_ALBEDO`; readers
    divide by it.  Without this, 8-bit photographs read as radiance under unit irradiance
    imply albedos above 1, which the fit's [0, 1] box clips, and the fit then bends normals
    towards the lights to make up the brightness (docs/PHOTOS.md).  ``scale=`` a number sets
    ``E`` instead (e.g. 1 for images that are relative radiance already).
  * The images' pixels are stored as decoded (linear, not divided by ``E``), so
    ``saturation`` stays in their units.

Matching: each light-file name is matched to a file in the folder by its base name (folder
prefixes such as ``images/`` or ``C:\\captures\\`` are ignored), exactly, else ignoring case;
when no name matches (lights recovered from ``chrome.3.png`` for an object shot as
``cat.3.png``), by the numbers in the names if they pair the two sets one-to-one.  Images in
the folder that the light file does not name are refused, except mask images (a ``mask`` in the
name).

Refusals (nothing is written: the dataset is built in a temporary folder beside ``out`` and
renamed into place): a light file that cannot be read (:class:`FormatError`) or has a light at
or below the horizon (:class:`GeometryError`); images missing from the folder or not in the
light file (:class:`FormatError`, naming them); integer images without a transfer
(:class:`UnitsError`), too few lit pixels for ``auto`` (:class:`CalibrationError`), a
contradicted transfer under ``strict`` (:class:`UnitsError`); images of different sizes, a mask of another size
(:class:`GeometryError`); an output folder that exists and is not a dataset.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path, PureWindowsPath

import numpy as np

from dualscale.errors import FormatError, GeometryError, InputError, UnitsError
from dualscale.formats.atomic import atomic_dir
from dualscale.formats.lightfile import LightRecord, read_lights
from dualscale.formats.photo import SUFFIXES, Codes, Photo, decode_codes, read_codes, read_mask
from dualscale.formats.response import Response, response_from_json, stated_response

#: the 99th percentile of the imported sample's Lambertian albedo (max channel) with ``scale="auto"``
TARGET_ALBEDO = 0.8
CAMERA = "photo"
#: how light-file names are matched to the images (:func:`match_images`)
MATCHES = ("auto", "name", "number")
#: ``--intensities``: the file's when it has them else estimated (auto), always estimated, the
#: file's (1 where absent), or all equal
INTENSITIES = ("auto", "estimate", "file", "equal")


@dataclass
class ImportReport:
    """What :func:`import_photos` did: the dataset folder, the matched files in light order,
    the size ``(H, W)``, the light scale ``E`` and how it was chosen, the mask's source, the
    clipped pixel count per image (inside the mask when there is one), and notes."""

    dataset: Path
    files: list[str]
    size: tuple[int, int]
    scale: float
    scale_source: str
    mask: str | None
    clipped: list[int]
    bits: int
    transfer: str | None
    notes: list[str] = field(default_factory=list)
    response: Response | None = None
    intensities: list[float] | None = None
    intensities_source: str = "file"
    warnings: list[str] = field(default_factory=list)
    radiometry: dict | None = None


def _base(name: str) -> str:
    return PureWindowsPath(name).name if "\\" in name else Path(name).name


def read_light_records(path: str | Path) -> list[LightRecord]:
    """The light file's records; :class:`FormatError` for an unreadable file,
    :class:`GeometryError` for a light at or below the horizon (names the file and line)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"light file not found: {path}")
    try:
        return read_lights(path)
    except GeometryError:
        raise
    except ValueError as e:
        raise FormatError(str(e)) from e


def _numbers(name: str) -> tuple[int, ...]:
    return tuple(int(t) for t in re.findall(r"\d+", Path(name).stem))


def _by_number(files: list[Path], records: list[LightRecord]) -> list[Path] | None:
    """The images matched to the records by the numbers in their names (``chrome.3.png`` ->
    ``cat.3.png``, ``L07.jpg`` -> ``IMG_0007.JPG``), when that is one-to-one; else None."""
    keys = [_numbers(_base(r.file)) for r in records]
    by_key: dict[tuple[int, ...], Path] = {}
    for p in files:
        k = _numbers(p.name)
        if not k or k in by_key:
            return None
        by_key[k] = p
    if len(files) != len(records) or len(set(keys)) != len(keys) or set(keys) != set(by_key):
        return None
    return [by_key[k] for k in keys]


def match_images(folder: Path, records: list[LightRecord], match: str = "auto"
                 ) -> tuple[list[Path], list[Path], str]:
    """``(images in light order, mask candidates, how they were matched)``.

    ``match="name"``: each record's base name in ``folder`` (exactly, else ignoring case);
    ``"number"``: by the numbers in the names (a light file recovered from ``chrome.3.png``
    for an object shot as ``cat.3.png``); ``"auto"``: by name, and by number when *no* name
    matches and the numbers pair the two sets one-to-one.  :class:`FormatError` names the
    missing and the extra images."""
    if match not in MATCHES:
        raise InputError(f"--match {match!r}: choose one of {', '.join(MATCHES)}")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SUFFIXES
                   and not p.name.startswith("."))
    masks = [p for p in files if "mask" in p.name.lower()]
    images = [p for p in files if p not in masks]
    by_name = {p.name: p for p in files}
    by_lower: dict[str, list[Path]] = {}
    for p in files:
        by_lower.setdefault(p.name.lower(), []).append(p)
    out, missing = [], []
    for r in records:
        b = _base(r.file)
        p = by_name.get(b)
        if p is None and len(by_lower.get(b.lower(), [])) == 1:
            p = by_lower[b.lower()][0]
        if p is None:
            missing.append(r.file)
        else:
            out.append(p)
    how = "by name"
    if match == "number" or (match == "auto" and not out):
        numbered = _by_number(images, records)
        if numbered is not None:
            return numbered, masks, "by the numbers in the names"
        if match == "number":
            raise FormatError(f"{folder}: the numbers in the image names do not pair the {len(images)} images "
                              f"with the {len(records)} lights of the light file one-to-one")
    if len(set(out)) != len(out):
        dup = sorted({p.name for p in out if out.count(p) > 1})
        raise FormatError(f"{folder}: several lights name the same image {dup}")
    extra = [p.name for p in images if p not in out]
    if missing or extra:
        msg = [f"{folder}: the images and the light file do not match"]
        if missing:
            msg.append(f"{len(missing)} named in the light file but not in the folder: {', '.join(missing[:12])}"
                       + (" ..." if len(missing) > 12 else ""))
        if extra:
            msg.append(f"{len(extra)} in the folder but not in the light file: {', '.join(extra[:12])}"
                       + (" ..." if len(extra) > 12 else ""))
        raise FormatError("; ".join(msg))
    return out, masks, how


def _mask(folder: Path, mask: str | Path | None, candidates: list[Path], shape: tuple[int, int]
          ) -> tuple[np.ndarray | None, str | None]:
    if mask is None or (isinstance(mask, str) and mask == "none"):
        return None, None
    if isinstance(mask, str) and mask == "auto":
        if len(candidates) > 1:
            raise FormatError(f"{folder}: several mask images {[p.name for p in candidates]}; pass --mask MASK "
                              "(or --mask none)")
        if not candidates:
            return None, None
        mask = candidates[0]
    path = Path(mask)
    return read_mask(path, shape), str(path)


def light_scale(photos: list[Photo], dirs: np.ndarray, rel: np.ndarray, mask: np.ndarray | None,
                target: float = TARGET_ALBEDO) -> float:
    """``E`` such that the 99th percentile over the sample (the mask, or the whole image) of the
    Lambertian albedo of ``image_k / (E rel_k)`` is ``target``: per pixel, Woodham's least
    squares ``Y_k = g . l_k`` on the brightest channel over all lights, albedo ``pi |g|`` (in the
    sense of :mod:`dualscale.bsdf`; the classic estimate, shadows and clipping included, which
    the 99th percentile does not mind)."""
    h, w = photos[0].rgb.shape[:2]
    sel = np.flatnonzero(mask.ravel()) if mask is not None else np.arange(h * w)
    if sel.size > 200_000:  # the percentile needs no more
        sel = np.random.default_rng(0).choice(sel, 200_000, replace=False)
    y = np.stack([p.rgb.reshape(-1, 3)[sel].max(-1) / r for p, r in zip(photos, rel)]).astype(np.float64)
    if np.linalg.matrix_rank(dirs) < 3:
        raise GeometryError("the light directions are coplanar: they cannot fix a normal (photometric stereo "
                            "needs 3 non-coplanar lights)")
    g = np.linalg.lstsq(dirs, y, rcond=None)[0]  # (3, P)
    p99 = float(np.percentile(math.pi * np.linalg.norm(g, axis=0), 99))
    if not (math.isfinite(p99) and p99 > 0):
        raise InputError("the images are black over the sample: cannot set the light scale; pass --scale")
    return p99 / target


def _light_file_response(lights: Path) -> Response:
    """The response a light file records (``source.response``, from a matte reference sphere:
    ``dualscale lights sphere --matte``); :class:`FormatError` when it has none."""
    from dualscale.formats.lightfile import read_lights_json

    if lights.suffix.lower() != ".json":
        raise FormatError(f"--transfer lights: {lights} is not our .json light file, which records the response "
                          "of a matte reference sphere (dualscale lights sphere --matte)")
    doc = read_lights_json(lights).source or {}
    rad = doc.get("radiometry") or {}
    if "response" not in rad:
        raise FormatError(f"--transfer lights: {lights} records no response (make it with dualscale lights sphere "
                          "CHROME --matte MATTE)")
    return response_from_json(rad["response"], str(lights))


def radiometry(codes: list[Codes], dirs: np.ndarray, rel: np.ndarray | None, mask: np.ndarray | None,
               transfer: str | None, lights: Path, strict: bool = False, intensities: str = "auto"
               ) -> tuple[Response | None, np.ndarray, str, dict, list[str], list[str]]:
    """The response and the relative light intensities of integer photographs
    (:mod:`dualscale.calib.response`): ``(response, rel (K,), intensities source, record,
    notes, warnings)``.

    ``transfer``: ``"auto"`` (estimated), ``"lights"`` (the light file's, from a matte
    sphere) or a stated one; a stated or recorded response is checked against the data, and a
    contradiction is a warning (a :class:`UnitsError` with ``strict``).  ``rel``: the light
    file's relative intensities (None: it has none); ``intensities`` (:data:`INTENSITIES`)
    says whether they are estimated.  Float (EXR) images are linear: nothing is estimated."""
    from dualscale.calib.response import check_stated, estimate_response, estimate_intensities

    notes: list[str] = []
    warns: list[str] = []
    if intensities not in INTENSITIES:
        raise InputError(f"--intensities {intensities!r}: choose one of {', '.join(INTENSITIES)}")
    K = len(codes)
    if {c.bits for c in codes} == {32}:
        if transfer not in (None, "linear", "auto"):
            raise UnitsError("EXR images are linear already: drop --transfer or use --transfer linear")
        if transfer == "auto":
            notes.append("the images are floating point (EXR): linear already, no response to estimate")
        return None, np.ones(K) if rel is None else rel, "file" if rel is not None else "equal", {}, notes, warns
    if transfer is None:
        raise UnitsError("the transfer function of display-encoded images must be stated or estimated: "
                         "--transfer auto|lights|srgb|linear|gamma:G (auto: estimated from the photographs; lights: "
                         "the matte sphere's, from the light file)")
    bits = max(c.bits for c in codes)
    sel = np.flatnonzero(mask.ravel()) if mask is not None else np.arange(codes[0].code.shape[0] * codes[0].code.shape[1])
    stack = np.stack([c.code.reshape(-1, 3)[sel] for c in codes]).astype(np.float64)   # (K, P, 3)
    valid = ~np.stack([c.clipped.ravel()[sel] for c in codes])
    want_e = intensities == "estimate" or (intensities == "auto" and rel is None)
    if intensities == "file" and rel is None:
        notes.append(f"--intensities file: {lights.name} gives no intensities; every light is given 1")
    given = None if want_e else (np.ones(K) if (rel is None or intensities == "equal") else rel)
    e_src = "estimated" if want_e else ("equal" if given is not None and (rel is None or intensities == "equal")
                                         else "file")
    record: dict = {"transfer_requested": transfer}
    if transfer == "auto":
        est = estimate_response(stack, dirs, valid, bits=bits, intensities=given)
        resp = est.response
        record.update(est.record())
        e = est.intensities if want_e else given
        notes += est.notes
        if want_e:
            # the best power law with equal lights, against the one with the intensities estimated:
            # are the response and the intensities told apart by these lights?
            eq = estimate_response(stack, dirs, valid, bits=bits, intensities=np.ones(K), families=("gamma",),
                                   bootstrap=0)
            from dualscale.calib.response import curve_distance

            joint = Response("gamma", tuple(est.fits["gamma"]["params"]), "auto")
            dist = curve_distance(eq.response, joint, est.code_range)
            ratio = eq.score("gamma") / max(est.score("gamma"), 1e-12)
            record["equal_intensities"] = {"gamma": eq.response.to_json(), "curve_distance": dist,
                                           "loss_ratio": ratio}
            if dist > 0.02 and ratio < 1.10:
                notes.append(f"the response and the lights' intensities are confounded by this light layout: the best "
                             f"power law is {joint.params[0]:.3f} with the intensities estimated and "
                             f"{eq.response.params[0]:.3f} with them equal, which the photographs explain almost "
                             f"as well (loss {ratio:.2f}x); a matte reference sphere separates the two "
                             "(docs/RADIOMETRY.md)")
        return resp, np.asarray(e), e_src, record, notes, warns
    resp = _light_file_response(lights) if transfer == "lights" else stated_response(transfer)
    try:
        est = estimate_response(stack, dirs, valid, bits=bits, intensities=given, bootstrap=4)
    except InputError as exc:
        why = str(exc).split("; state the response")[0].split(": are these")[0]
        warns.append(f"--transfer {transfer} could not be checked against the photographs"
                     + (", and the lights' intensities could not be estimated (all set equal)" if given is None
                        else "") + f": {why}")
        return resp, np.ones(K) if given is None else given, "equal" if given is None else e_src, record, notes, warns
    bad, msg, check = check_stated(est, resp, stack, dirs, valid, bits)
    record["check"] = check
    record["estimate"] = est.response.to_json()
    if bad:
        if strict:
            raise UnitsError(msg + " (refused: --strict)")
        warns.append(msg)
    e = estimate_intensities(resp, stack, dirs, valid, bits) if want_e else given
    record["response"] = resp.to_json()
    record["intensities"] = {"values": np.round(e, 6).tolist(), "source": e_src, "normalisation": "geometric mean 1"}
    return resp, np.asarray(e), e_src, record, notes, warns


def _prepare_out(out: Path) -> None:
    if out.exists():
        if not out.is_dir():
            raise InputError(f"-o {out}: exists and is not a folder")
        # hidden files (the output folder's record, interrupted temporary files) are not outputs
        if any(not p.name.startswith(".") for p in out.iterdir()) and not (out / "manifest.json").is_file():
            raise InputError(f"-o {out}: exists, is not empty and is not a dataset; choose another -o")


def import_photos(images: str | Path, lights: str | Path, out: str | Path, transfer: str | None,
                  mask: str | Path | None = "auto", texel_mm: float | None = None,
                  scale: float | str = "auto", match: str = "auto", progress: bool = False,
                  intensities: str = "auto", strict: bool = False) -> ImportReport:
    """Import the photographs in folder ``images`` lit as ``lights`` says into the dataset
    folder ``out`` (module doc).  ``mask``: a mask image, ``"auto"`` (the folder's one image
    with ``mask`` in its name, if any) or ``None``/``"none"``; ``texel_mm``: the pixel pitch on
    the object (unknown: the camera's field is recorded as 1 mm per pixel and
    ``extra.texel_mm_known`` is false); ``scale``: ``"auto"`` or the light scale ``E``;
    ``match``: how light-file names find the images (:func:`match_images`); ``transfer``:
    ``"auto"`` (estimated from the photographs), ``"lights"`` (the light file's matte-sphere
    response) or stated, checked against the data (:func:`radiometry`; ``strict`` refuses a
    contradicted one); ``intensities``: :data:`INTENSITIES`.
    An existing dataset at ``out`` is replaced only once the new one is complete."""
    folder, out = Path(images), Path(out)
    if not folder.is_dir():
        raise FileNotFoundError(f"not a folder of images: {folder}")
    if texel_mm is not None and not (math.isfinite(texel_mm) and texel_mm > 0):
        raise InputError(f"--texel-mm {texel_mm}: must be a finite number > 0")
    if scale != "auto" and not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise InputError(f"--scale {scale!r}: must be 'auto' or a finite number > 0")
    _prepare_out(out)
    records = read_light_records(lights)
    if not records:
        raise FormatError(f"{lights}: the light file lists no images")
    paths, mask_candidates, how = match_images(folder, records, match)
    codes: list[Codes] = []
    from tqdm import tqdm

    for p in tqdm(paths, desc="import: reading", disable=not progress, leave=False):
        codes.append(read_codes(p))
    sizes = {c.code.shape[:2] for c in codes}
    if len(sizes) != 1:
        first = codes[0].code.shape[:2]
        odd = [f"{p.name} ({c.code.shape[1]}x{c.code.shape[0]})" for p, c in zip(paths, codes)
               if c.code.shape[:2] != first]
        raise GeometryError(f"{folder}: images of different sizes: {paths[0].name} is {first[1]}x{first[0]}, "
                            f"but {', '.join(odd)}")
    h, w = codes[0].code.shape[:2]
    m, mask_src = _mask(folder, mask, mask_candidates, (h, w))
    dirs = np.array([r.direction for r in records], np.float64)
    if any(r.intensity is not None and r.intensity <= 0 for r in records):
        bad = [r.file for r in records if r.intensity is not None and r.intensity <= 0]
        raise InputError(f"{lights}: lights {bad} have intensity 0; a dataset light needs intensity > 0")
    file_rel = (None if all(r.intensity is None for r in records)
                else np.array([1.0 if r.intensity is None else r.intensity for r in records], np.float64))
    resp, rel, rel_src, rad_rec, rad_notes, rad_warns = radiometry(codes, dirs, file_rel, m, transfer, Path(lights),
                                                                   strict, intensities)
    photos = [decode_codes(c, resp if resp is not None else (None if transfer == "auto" else transfer), str(p))
              for c, p in zip(codes, paths)]
    if scale == "auto":
        e = light_scale(photos, dirs, rel, m)
        source = (f"auto: 99th percentile of the Lambertian albedo (max channel) over the "
                  f"{'mask' if m is not None else 'image'} set to {TARGET_ALBEDO}")
    else:
        e, source = float(scale), "given (--scale)"
    is_float = {ph.bits == 32 for ph in photos}
    notes = ([] if how == "by name" else [f"images matched to the light file {how}"]) + rad_notes
    if texel_mm is None:
        notes.append("texel size unknown: the camera's field is recorded as 1 mm per pixel")
    clipped = [int((ph.clipped & m).sum()) if m is not None else int(ph.clipped.sum()) for ph in photos]
    if max(clipped) > 0:
        notes.append(f"{sum(clipped)} clipped pixels{' in the mask' if m is not None else ''} "
                     "(masked out by the images' saturation level)")
    from dualscale.formats.dataset import DatasetWriter
    from dualscale.geometry.cameras import Camera

    t = 1.0 if texel_mm is None else float(texel_mm)
    cam = Camera(CAMERA, "orthographic", w, h, (w * t, h * t), has_analyzer=False)
    report = ImportReport(out, [p.name for p in paths], (h, w), e, source, mask_src, clipped,
                          max(ph.bits for ph in photos), None if is_float == {True} else resp.transfer, notes,
                          resp, [float(v) for v in rel], rel_src, rad_warns, rad_rec)
    extra = {"import": {"images": str(folder.resolve()), "lights": str(Path(lights).resolve()),
                        "sources": [{"id": k, "file": p.name, "light_file_name": r.file,
                                     "relative_intensity": r.intensity, "intensity_used": float(rel[k])}
                                    for k, (p, r) in enumerate(zip(paths, records))],
                        "light_scale": e, "light_scale_source": source, "target_albedo": TARGET_ALBEDO,
                        "texel_mm": texel_mm, "texel_mm_known": texel_mm is not None,
                        "polarisation": "none (unpolarised lights, no analyser)", "notes": notes,
                        "radiometry": {**rad_rec, "warnings": rad_warns, "intensities_source": rel_src,
                                       "used": None if resp is None else resp.describe()}}}
    with atomic_dir(out) as tmp:
        writer = DatasetWriter(tmp, units="relative_radiance", colour_space="linear_rec709",
                               dome={"source": str(lights), "polarizer": "none"}, extra=extra, mask=m,
                               transfer=report.transfer, rig={"id": "photos", "layout": "light file"})
        with writer:
            for k, (ph, r) in enumerate(tqdm(list(zip(photos, records)), desc="import: writing",
                                             disable=not progress, leave=False)):
                writer.add(ph.rgb, cam, "led", light_id=k, direction=list(r.direction), intensity=e * rel[k],
                           analyzer_deg=None, exposure_s=1.0, saturation=None if ph.bits == 32 else 1.0)
    return report
