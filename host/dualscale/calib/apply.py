"""Apply a calibration file to a photometric dataset: any dataset the format accepts becomes the
canonical one the fit reads (``relative_radiance``, ``linear_rec709``, ``exposure_s = 1``;
see :mod:`dualscale.formats.dataset`).  Supplementary Sec. 2-3.

A raw dataset (``dn_normalized`` in ``camera_raw:<sensitivities>``) goes through these steps,
per image of camera ``c`` under light ``l`` taken with exposure ``t`` (the names are the
``applied`` entries of the summary):

1. ``dark`` -- subtract the dark signal ``bias + rate t``: per pixel from the dataset's own
   dark frames (``light.kind = "off"`` images of that camera; two or more exposures give the
   rate, one gives the bias only), else the calibration's per-camera mean (``dark[c]``);
2. ``exposure`` -- divide by ``t``: DN per second, the calibration's unit;
3. ``flat_field`` -- divide by the camera's flat field (``flat_field[c]``), when it has one;
4. ``white_balance`` -- ``i_hat = i / r_c[c][l] * r_ws`` (Eq. 1 and after): reflectance
   relative to the white sheet, whose reflectance is ``r_ws``; per-LED gains and the camera's
   spectral response to the light cancel here;
5. ``ccm`` -- white-balanced camera RGB to linear Rec.709 with ``ccm[c][kind]`` (``led`` for
   the LEDs and the back lights, which share the LED type, ``diffuse`` for the diffuse group);
6. ``irradiance`` -- back to radiance per unit light intensity: the white sheet is taken as
   Lambertian (as the paper's single irradiance value ``r_c`` per light assumes), so a
   reflectance ``i_hat`` under LED direction ``l`` is the radiance ``i_hat * l_z / pi``; under
   the diffuse group, ``i_hat * sum_k w_k l_kz / pi`` (the dome's solid-angle weights,
   ``geometry.dome.DomeGeometry.diffuse_weights``); back-lit images stay ``i_hat``: a panel of
   unit radiance seen through the sheet, calibrated with ``r_ws`` like reflection (the paper's
   convention, so a transmittance is relative to the sheet's, scaled by ``r_ws``).

The micro camera's ``r_c`` sums both analyser modes (P0 + P90), so a P0 or P90 image comes out
with the half of the diffuse light its analyser passes, as the fit's observation model expects.

Clipped pixels (any raw channel at or above its clip level: the image's ``saturation`` --
full scale 1.0 when a ``dn_normalized`` record gives none -- or, when lower, the channel's
white-level ``clip`` of the camera in the calibration, ``white_level[c]``, for a sensor that
clips below full scale) are carried exactly: in the output each such image's
``saturation`` is the smallest float32 above every unclipped value, and its clipped pixels are
written at or above it (at least their converted values, a lower bound of the true radiance).
The dataset's mask, rig, transfer and cameras are carried; dark frames are consumed.

A dataset already in ``relative_radiance`` / ``linear_rec709`` is rewritten with the exposure
folded in (images and saturation divided by ``exposure_s``), and ``calibration`` is ignored
(the summary says ``null``).  Other combinations of units and colour space are refused
(:class:`~dualscale.errors.UnitsError`), as is a raw dataset without a calibration.  A
calibration from another rig (the dataset's ``rig`` record against the file's ``rig``) or
without the dataset's camera raises :class:`~dualscale.errors.RigMismatchError`; one that lacks
a light the dataset uses raises :class:`~dualscale.errors.CalibrationError`.  Everything is
checked before anything is written, and the output folder appears only complete: it is written
as ``OUT.parent/.tmp-OUT-*`` and renamed into place.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dualscale.errors import CalibrationError, InputError, RigMismatchError, UnitsError
from dualscale.formats.atomic import atomic_dir as _atomic_dir
from dualscale.formats.calibration import read_calibration, white_level
from dualscale.formats.captures import light_key
from dualscale.formats.dataset import (CAMERA_RAW, CANONICAL_COLOUR_SPACE, CANONICAL_UNITS, Dataset, DatasetWriter,
                                       ImageRecord, read_dataset, resolve_root)
from dualscale.geometry.cameras import Camera
from dualscale.progress import Progress, iterate

from .radiometric import apply_flat_field, apply_white_balance, dark_at, fit_dark

RAW_UNITS = "dn_normalized"
DN_FULL_SCALE = 1.0


@dataclass
class _CameraCal:
    """What converts one camera's raw images: dark model, flat field, ``r_c`` per light, CCMs."""

    name: str
    dark: tuple[np.ndarray, np.ndarray]
    dark_source: str
    flat: np.ndarray | None
    r_c: dict[str, list[float]]
    r_ws: np.ndarray
    ccm: dict[str, np.ndarray]
    white_clip: np.ndarray | None = None


@dataclass
class _Plan:
    calibration: Path | None
    calib: dict[str, Any] | None
    r_ws: np.ndarray | None
    cameras: dict[str, _CameraCal] = field(default_factory=dict)
    applied: list[str] = field(default_factory=list)


def _camera(name: str, d: dict[str, Any], where: str = "dataset manifest") -> Camera:
    return Camera.from_json(name, d, where)


def _is_raw(rec: ImageRecord) -> bool:
    return rec.units != CANONICAL_UNITS or rec.colour_space != CANONICAL_COLOUR_SPACE


def _check_units(ds: Dataset) -> bool:
    """True when the dataset needs a calibration; refuses combinations no step converts."""
    raw = False
    for rec in ds.records:
        where = f"dataset {ds.root}: image {rec.file}"
        if rec.units == CANONICAL_UNITS and rec.colour_space == CANONICAL_COLOUR_SPACE:
            continue
        if rec.units == RAW_UNITS and rec.colour_space.startswith(CAMERA_RAW):
            raw = True
            continue
        raise UnitsError(f"{where}: units {rec.units!r} in colour_space {rec.colour_space!r} cannot be calibrated: "
                         f"a calibration converts {RAW_UNITS!r} camera raw ({CAMERA_RAW}<sensitivities>) captures, "
                         f"and {CANONICAL_UNITS!r} images must be in {CANONICAL_COLOUR_SPACE!r} already")
    return raw


def _dark(ds: Dataset, cam: str, calib: dict[str, Any], cal_path: Path) -> tuple[tuple[np.ndarray, np.ndarray], str]:
    frames = [i for i, r in enumerate(ds.records) if r.camera == cam and r.light_kind == "off" and _is_raw(r)]
    if frames:
        bias, rate = fit_dark([ds.load(i) for i in frames], [ds.records[i].exposure_s for i in frames])
        return (bias, rate), f"{len(frames)} dark frames of the dataset"
    d = calib.get("dark", {}).get(cam)
    if not d:
        raise CalibrationError(f"dataset {ds.root}: camera {cam!r} has no dark frames (light.kind 'off') and the "
                               f"calibration {cal_path} has no dark[{cam!r}]: the dark signal cannot be subtracted")
    bias, rate = np.asarray(d["bias"], np.float64), np.asarray(d["rate"], np.float64)
    return (bias.reshape(1, 1, 3), rate.reshape(1, 1, 3)), "the calibration's mean dark signal"


def _ccm_kind(rec: ImageRecord) -> str:
    return "diffuse" if rec.light_kind == "diffuse" else "led"


def _plan(ds: Dataset, calibration: str | Path | None) -> _Plan:
    """Check the dataset against the calibration before anything is written."""
    raw = _check_units(ds)
    if not raw:
        applied = ["exposure"] if any(r.exposure_s != 1.0 for r in ds.records) else []
        return _Plan(None, None, None, applied=applied)
    if calibration is None:
        rec = next(r for r in ds.records if _is_raw(r))
        raise UnitsError(f"dataset {ds.root}: image {rec.file}: units {rec.units!r} in colour_space "
                         f"{rec.colour_space!r} are raw sensor values; a calibration file is needed to turn them "
                         "into radiance (`dualscale digitize DATASET --calibration CAL`, or "
                         "to_radiance(DATASET, OUT, calibration=CAL))")
    cal_path = Path(calibration)
    if not cal_path.is_file():
        raise FileNotFoundError(f"calibration file not found: {cal_path}")
    rig = ds.rig or {}
    calib = read_calibration(cal_path, rig_id=rig.get("id"), layout=rig.get("layout"))
    try:
        r_ws = np.asarray(calib["r_ws"], np.float64).reshape(3)
    except (KeyError, ValueError) as e:
        raise CalibrationError(f"{cal_path}: no usable r_ws (white-sheet reflectance): {e}") from e
    plan = _Plan(cal_path, calib, r_ws)
    for rec in ds.records:
        if not _is_raw(rec) or rec.light_kind == "off":
            continue
        cam = rec.camera
        if cam not in plan.cameras:
            if cam not in calib.get("r_c", {}) or cam not in calib.get("ccm", {}):
                raise RigMismatchError(f"{cal_path}: the calibration has no camera {cam!r} (it calibrates "
                                       f"{sorted(calib.get('r_c', {}))}); dataset {ds.root} was taken with another "
                                       "camera or rig")
            dark, source = _dark(ds, cam, calib, cal_path)
            ff = calib.get("flat_field", {}).get(cam)
            ccm = {k: np.asarray(v["matrix"], np.float64) for k, v in calib["ccm"][cam].items()}
            wl = white_level(calib, cam, cal_path)
            plan.cameras[cam] = _CameraCal(cam, dark, source, None if not ff else np.asarray(ff["coef"]),
                                           calib["r_c"][cam], r_ws, ccm,
                                           None if wl is None else np.asarray(wl["clip"], np.float64))
        cc = plan.cameras[cam]
        key = light_key(rec.light_kind, rec.light_id)
        if key not in cc.r_c:
            raise CalibrationError(f"{cal_path}: no white-sheet capture (r_c) for camera {cam!r} under {key}, which "
                                   f"dataset image {rec.file} uses; recalibrate with that light")
        if _ccm_kind(rec) not in cc.ccm:
            raise CalibrationError(f"{cal_path}: no CCM for camera {cam!r} and light kind {_ccm_kind(rec)!r} "
                                   f"(dataset image {rec.file})")
        if rec.light_kind == "led" and rec.direction is None:
            raise InputError(f"dataset {ds.root}: image {rec.file}: LED image without light.direction")
    plan.applied = ["dark", "exposure"]
    if any(c.flat is not None for c in plan.cameras.values()):
        plan.applied.append("flat_field")
    plan.applied += ["white_balance", "ccm", "irradiance"]
    return plan


def _diffuse_factor(ds: Dataset) -> float:
    """``sum_k w_k l_kz / pi``: a Lambertian white's radiance under the diffuse group."""
    from dualscale.geometry.dome import DomeGeometry

    src = str((ds.manifest.get("dome") or {}).get("source", "regmap"))
    dome = DomeGeometry.from_calibration(src) if src != "regmap" and Path(src).is_file() else DomeGeometry.from_regmap()
    return float((dome.diffuse_weights() * dome.led_dirs[:, 2].clamp(min=0.0)).sum()) / math.pi


def _irradiance(rec: ImageRecord, diffuse: float) -> float:
    if rec.light_kind == "led":
        return float(rec.direction[2]) / math.pi  # type: ignore[index]
    return diffuse if rec.light_kind == "diffuse" else 1.0


def _convert_raw(raw: np.ndarray, rec: ImageRecord, cc: _CameraCal, diffuse: float) -> tuple[np.ndarray, np.ndarray]:
    """``(radiance (H, W, 3), clipped (H, W))`` of one raw image (module doc, steps 1-6)."""
    sat = np.full(3, rec.saturation if rec.saturation is not None else DN_FULL_SCALE)
    if cc.white_clip is not None:
        sat = np.minimum(sat, cc.white_clip)
    clipped = (raw >= sat).any(-1)
    x = (np.asarray(raw, np.float64) - dark_at(*cc.dark, rec.exposure_s)) / rec.exposure_s
    if cc.flat is not None:
        x = apply_flat_field(x, cc.flat)
    x = apply_white_balance(x, np.asarray(cc.r_c[light_key(rec.light_kind, rec.light_id)]), cc.r_ws)
    x = x @ cc.ccm[_ccm_kind(rec)].T
    return x * _irradiance(rec, diffuse), clipped


def _signal_scale(rec: ImageRecord, cc: _CameraCal | None, diffuse: float) -> list[float]:
    """Per channel, the factor from the image's sensor signal to its converted values
    (:mod:`dualscale.formats.dataset`, "Signal scale"): a raw image's ``irradiance / t`` times
    the CCM's rows applied to the white balance ``r_ws / r_c`` (their norm); an image already in
    radiance its own scale (``1`` when unrecorded) over ``t``."""
    if cc is None:
        own = np.ones(3) if rec.signal_scale is None else np.asarray(rec.signal_scale, np.float64)
        return [float(v) for v in own / rec.exposure_s]
    wb = np.asarray(cc.r_ws, np.float64) / np.asarray(cc.r_c[light_key(rec.light_kind, rec.light_id)], np.float64)
    rows = np.linalg.norm(cc.ccm[_ccm_kind(rec)] * wb, axis=1)
    return [float(v) for v in rows * _irradiance(rec, diffuse) / rec.exposure_s]


def _carry_clipped(img: np.ndarray, clipped: np.ndarray | None) -> tuple[np.ndarray, float | None]:
    """float32 image and output ``saturation`` that classify ``clipped`` exactly (module doc)."""
    out = np.asarray(img, np.float32)
    if clipped is None or not clipped.any():
        return out, None
    ok = ~clipped
    top = np.float32(out[ok].max()) if ok.any() else np.float32(0.0)
    sat = np.nextafter(max(top, np.float32(np.finfo(np.float32).tiny)), np.float32(np.inf))
    out = out.copy()
    out[clipped] = np.maximum(out[clipped], sat)
    return out, float(sat)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def to_radiance(dataset_dir: str | Path, out_dir: str | Path, calibration: str | Path | None = None,
                progress: Progress = False) -> dict[str, Any]:
    """Write the canonical (calibrated, exposure-folded) copy of a dataset to ``out_dir`` and
    return the summary (module doc for the steps and errors)::

        {"calibration": path | None, "applied": [step, ...], "units_in": str,
         "units_out": "relative_radiance", "colour_space_in": str, "colour_space_out":
         "linear_rec709", "transfer": str | None, "images": int, "clipped_share": float,
         "texel_mm": float | None, "field_mm": [w, h] | None}

    ``dataset_dir``: a dataset folder (or a ``synth`` output holding ``micro/``); ``images``
    counts the images written, ``clipped_share`` the share of their pixels (inside the mask)
    that are clipped; ``texel_mm`` / ``field_mm`` are those of the micro camera (else the
    first camera).  The output manifest records the calibration applied in
    ``extra.calibration``.  ``progress``: see :mod:`dualscale.progress` (one unit per image).
    """
    src = resolve_root(dataset_dir)
    ds = read_dataset(src)
    out = Path(out_dir)
    if out.resolve() == src.resolve():
        raise InputError(f"to_radiance: the output {out} is the input dataset; write elsewhere")
    plan = _plan(ds, calibration)
    where = str(src / "manifest.json")
    cameras = {name: _camera(name, d, where) for name, d in (ds.manifest.get("cameras") or {}).items()}
    for rec in ds.records:
        if rec.camera not in cameras:
            raise InputError(f"dataset {ds.root}: image {rec.file}: camera {rec.camera!r} is not in the manifest's "
                             "cameras")
    diffuse = _diffuse_factor(ds) if any(r.light_kind == "diffuse" for r in ds.records) else 1.0
    mask = ds.mask()
    calib_record = None
    if plan.calibration is not None:
        c = plan.calib or {}
        calib_record = {"file": str(plan.calibration.resolve()), "sha256": _sha256(plan.calibration),
                        "created": c.get("created"), "rig": c.get("rig"), "applied": plan.applied,
                        "dark": {k: v.dark_source for k, v in plan.cameras.items()},
                        "source_dataset": str(src.resolve())}
    extra = dict(ds.manifest.get("extra") or {})
    extra["calibration"] = calib_record
    extra["source_units"] = {"units": ds.manifest.get("units"), "colour_space": ds.manifest.get("colour_space")}
    written, clipped_px, total_px = 0, 0, 0
    todo = [i for i, r in enumerate(ds.records) if not (plan.calibration is not None and r.light_kind == "off")]
    with _atomic_dir(out) as tmp:
        w = DatasetWriter(tmp, units=CANONICAL_UNITS, colour_space=CANONICAL_COLOUR_SPACE,
                          dome=dict(ds.manifest.get("dome") or {}), extra=extra, mask=mask, transfer=ds.transfer,
                          rig=ds.rig)
        for i in iterate(progress, todo, "calibrate", unit="image"):
            rec = ds.records[i]
            img = ds.load(i)
            raw = _is_raw(rec)
            scale = _signal_scale(rec, plan.cameras[rec.camera] if raw else None, diffuse)
            if raw:
                rad, clipped = _convert_raw(img, rec, plan.cameras[rec.camera], diffuse)
            else:
                rad = np.asarray(img, np.float64) / rec.exposure_s
                clipped = ds.clipped(i, img)
            if not np.isfinite(rad).all():
                raise CalibrationError(f"dataset {ds.root}: image {rec.file}: calibration produced non-finite values")
            data, sat = _carry_clipped(rad, clipped)
            w.add(data, cameras[rec.camera], rec.light_kind, rec.light_id, rec.direction, rec.intensity,
                  rec.analyzer_deg, rec.analyzer_relative, 1.0, saturation=sat, signal_scale=scale)
            written += 1
            if rec.light_kind != "off":
                inside = mask if mask is not None and mask.shape == data.shape[:2] else np.ones(data.shape[:2], bool)
                total_px += int(inside.sum())
                clipped_px += 0 if clipped is None else int((clipped & inside).sum())
        w.close()
    cam = cameras.get("micro") or (next(iter(cameras.values())) if cameras else None)
    if not ds.texel_known:
        cam = None  # photographs imported without a scale: the camera's field is nominal
    return {"calibration": None if plan.calibration is None else str(plan.calibration),
            "applied": list(plan.applied), "units_in": str(ds.manifest.get("units")), "units_out": CANONICAL_UNITS,
            "colour_space_in": str(ds.manifest.get("colour_space")), "colour_space_out": CANONICAL_COLOUR_SPACE,
            "transfer": ds.transfer, "images": written,
            "clipped_share": clipped_px / total_px if total_px else 0.0,
            "texel_mm": None if cam is None else cam.field_mm[0] / cam.width,
            "field_mm": None if cam is None else [float(cam.field_mm[0]), float(cam.field_mm[1])]}
