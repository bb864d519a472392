"""From a capture set to a calibration (and the calibrated measurements the evaluation uses).

Order per group: HDR merge of the brackets with the dark model subtracted (DN/s), flat field,
then ``r_c`` / anchor / white balance (:mod:`.radiometric`) and the CCMs (:mod:`.ccm`).
Each camera's merges exclude, per channel, the samples at or above its white level's threshold
(:class:`~.hdr.WhiteLevel`): the level declared in the capture set, else the calibration's
(when applying one), else measured from that camera's brackets; the calibration records it.
The HDR merges are the long part: ``progress`` (:mod:`dualscale.progress`) counts them.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import colourref as cr
from dualscale.formats.captures import CaptureSet, Group
from .ccm import fit_and_validate, patch_mask
from .chart import ChartLayout, detect_chart, orient_corners, sample_patches
from dualscale.errors import CalibrationError, ImageSizeError
from dualscale.formats.calibration import white_level as _white_level_record

from .hdr import HDRResult, WhiteLevel, measure_white_level, merge_debevec
from .radiometric import (apply_flat_field, apply_white_balance, dark_at, fit_dark, fit_flat_field,
                          irradiance_value, micro_footprint_mask, white_sheet_reflectance)
from dualscale.progress import Progress, Tracker, tracker

CALIBRATION_TARGETS = ("white_sheet", "patch", "chart")
"""Capture targets whose groups :func:`calibrate` merges (each one HDR merge)."""

WHITE_SAMPLES = 20000
"""Clipped samples per channel after which measuring a white level stops reading brackets."""


@dataclass
class Session:
    """A capture set with cached merges; ``calib`` holds what is known so far; ``progress``
    (a :class:`~dualscale.progress.Tracker`) counts each new HDR merge."""

    cs: CaptureSet
    calib: dict[str, Any] = field(default_factory=dict)
    progress: Tracker | None = None
    _dark: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    _merged: dict[str, HDRResult] = field(default_factory=dict)
    _white: dict[str, WhiteLevel] = field(default_factory=dict)

    def white_level(self, camera: str) -> WhiteLevel:
        """Camera ``camera``'s white level: declared in the captures, else the one of the
        calibration being applied (``calib["white_level"]``), else measured from the brackets of
        its :data:`CALIBRATION_TARGETS` groups, white sheet first
        (:func:`~.hdr.measure_white_level`, stopping at :data:`WHITE_SAMPLES` clipped samples
        per channel); ``nominal`` when none of them clips."""
        if camera not in self._white:
            declared = self.cs.white_level(camera)
            rec = _white_level_record(self.calib, camera, "calibration")
            if declared is not None:
                self._white[camera] = WhiteLevel(tuple(declared), "declared")
            elif rec is not None:
                self._white[camera] = WhiteLevel.from_record(rec)
            else:
                self._white[camera] = measure_white_level(self._bracket_stacks(camera), enough=WHITE_SAMPLES)
        return self._white[camera]

    def _bracket_stacks(self, camera: str):
        groups = [g for t in CALIBRATION_TARGETS for g in self.cs.select(target=t, camera=camera)]
        if not groups:
            groups = [g for g in self.cs.select(camera=camera) if g.target != "dark"]
        bias, rate = self.dark(camera)
        for g in groups:
            yield self.cs.load(g), g.exposures_s, [dark_at(bias, rate, t) for t in g.exposures_s]

    def dark(self, camera: str) -> tuple[np.ndarray, np.ndarray]:
        if camera not in self._dark:
            gs = self.cs.select(target="dark", camera=camera)
            if not gs:
                raise CalibrationError(f"no dark frames for camera {camera!r}")
            frames, ts = [], []
            for g in gs:
                frames += self.cs.load(g)
                ts += g.exposures_s
            self._dark[camera] = fit_dark(frames, ts)
        return self._dark[camera]

    def merged(self, g: Group) -> HDRResult:
        if g.id not in self._merged:
            bias, rate = self.dark(g.camera)
            imgs = self.cs.load(g)
            if imgs[0].shape != bias.shape:
                raise ImageSizeError(f"group {g.id}: images are {imgs[0].shape}, dark frames {bias.shape}")
            self._merged[g.id] = merge_debevec(imgs, g.exposures_s, dark=[dark_at(bias, rate, t) for t in g.exposures_s],
                                               name=g.id, white_level=self.white_level(g.camera))
            if self.progress is not None:
                self.progress.update(what=g.id)
        return self._merged[g.id]

    def image(self, g: Group) -> np.ndarray:
        """Merged, flat-fielded image [DN/s] of a group."""
        img = self.merged(g).radiance
        ff = self.calib.get("flat_field", {}).get(g.camera)
        return apply_flat_field(img, np.asarray(ff["coef"])) if ff else img

    def summed(self, groups: list[Group]) -> np.ndarray:
        """Sum over analyser modes (P0 + P90) of flat-fielded images."""
        if not groups:
            raise CalibrationError("no captures to sum")
        return np.sum([self.image(g) for g in groups], 0)

    def region(self, camera: str) -> np.ndarray | None:
        if camera == "micro" or "micro" not in self.cs.manifest["cameras"]:
            return None
        return micro_footprint_mask(self.cs.camera(camera), self.cs.camera("micro"))

    def by_light(self, target: str, camera: str, patch: int | None = None) -> dict[str, list[Group]]:
        out: dict[str, list[Group]] = {}
        for g in self.cs.select(target=target, camera=camera):
            if patch is None or g.patch == patch:
                out.setdefault(g.light, []).append(g)
        return out

    def layout(self) -> ChartLayout:
        return ChartLayout(**self.cs.manifest.get("chart", {}).get("layout", {}))

    def markers(self, camera: str) -> list[list[int]]:
        boxes = self.cs.manifest.get("markers", {}).get(camera)
        if not boxes:
            raise CalibrationError(f"no white-marker boxes for camera {camera!r} in the capture manifest")
        return boxes

    def marker_value(self, img: np.ndarray, camera: str) -> np.ndarray:
        vals = []
        for r0, r1, c0, c1 in self.markers(camera):
            if not (0 <= r0 < r1 <= img.shape[0] and 0 <= c0 < c1 <= img.shape[1]):
                raise ImageSizeError(f"marker box {(r0, r1, c0, c1)} is outside the {img.shape[:2]} image")
            vals.append(img[r0:r1, c0:c1].reshape(-1, 3).mean(0))
        return np.mean(vals, 0)

    def corners(self, camera: str, image: np.ndarray) -> np.ndarray:
        """Hand-given corners from the manifest if any, else automatic detection."""
        given = self.cs.manifest.get("chart", {}).get("corners", {}).get(camera)
        if given is not None:
            return orient_corners(image, np.asarray(given, float), self.layout())
        return detect_chart(image, self.layout())


def _check_sizes(s: Session) -> None:
    for g in s.cs.groups:
        cam = s.cs.camera(g.camera)
        for img in s.cs.load(g)[:1]:
            if img.shape[:2] != (cam.height, cam.width):
                raise ImageSizeError(f"group {g.id}: image size differs from camera {cam.name!r}")


def compute_flat_fields(s: Session) -> None:
    s.calib["flat_field"] = {}
    for cam in s.cs.manifest["cameras"]:
        gs = s.by_light("white_sheet", cam).get("diffuse")
        if gs:
            img = np.sum([s.merged(g).radiance for g in gs], 0)
            s.calib["flat_field"][cam] = {"coef": fit_flat_field(img).tolist()}


def compute_anchor(s: Session) -> None:
    """``r_ws`` from the mid-range camera's diffuse captures of the sheet and the white patch,
    each normalised by the holder's white markers (DSLR repeatability)."""
    ws = s.by_light("white_sheet", "mid").get("diffuse")
    ch = s.by_light("chart", "mid").get("diffuse")
    if not ws or not ch:
        raise CalibrationError("the anchor needs diffuse mid-range captures of the white sheet and the chart")
    img_ws = s.image(ws[0])
    region = s.region("mid")
    i_ws = irradiance_value(img_ws, region) / s.marker_value(img_ws, "mid")
    img_ch = s.image(ch[0])
    corners = s.corners("mid", img_ch)
    s.calib.setdefault("chart_corners", {})["mid"] = corners.tolist()
    i_wp = sample_patches(img_ch, corners, s.layout())[cr.WHITE_PATCH] / s.marker_value(img_ch, "mid")
    r_wp = cr.reference_rgb()[cr.WHITE_PATCH]
    s.calib["r_wp"] = r_wp.tolist()
    s.calib["r_ws"] = white_sheet_reflectance(i_ws, i_wp, r_wp).tolist()


def compute_r_c(s: Session) -> None:
    s.calib["r_c"] = {}
    for cam in s.cs.manifest["cameras"]:
        region = s.region(cam)
        for light, gs in s.by_light("white_sheet", cam).items():
            s.calib["r_c"].setdefault(cam, {})[light] = irradiance_value(s.summed(gs), region).tolist()


def calibrated(s: Session, camera: str, light: str, img: np.ndarray) -> np.ndarray:
    """``i_hat``: markers for diffuse mid-range captures, ``r_c`` otherwise."""
    r_ws = np.asarray(s.calib["r_ws"])
    if camera == "mid" and light == "diffuse":
        return apply_white_balance(img, s.marker_value(img, camera), r_ws)
    try:
        r_c = s.calib["r_c"][camera][light]
    except KeyError as e:
        raise CalibrationError(f"no white-sheet capture for camera {camera!r} under {light!r}") from e
    return apply_white_balance(img, r_c, r_ws)


def measure_patches(s: Session) -> dict[str, dict[str, dict[str, np.ndarray]]]:
    """White-balanced patch colours ``{camera: {light: {"rgb": (24, 3), "saturated": (24,)}}}``."""
    out: dict[str, dict[str, dict[str, np.ndarray]]] = {}
    for cam in s.cs.manifest["cameras"]:
        patch_groups = [g for g in s.cs.select(target="patch", camera=cam)]
        if patch_groups:
            lights = sorted({g.light for g in patch_groups})
            for light in lights:
                rgb, sat = np.zeros((cr.N_PATCHES, 3)), np.zeros(cr.N_PATCHES, bool)
                for k in range(cr.N_PATCHES):
                    gs = [g for g in patch_groups if g.light == light and g.patch == k]
                    if not gs:
                        raise CalibrationError(f"camera {cam!r}, light {light}: patch {k} was not captured")
                    img = calibrated(s, cam, light, s.summed(gs))
                    rgb[k] = img.reshape(-1, 3).mean(0)
                    sat[k] = any(s.merged(g).saturated.any() for g in gs)
                out.setdefault(cam, {})[light] = {"rgb": rgb, "saturated": sat}
        chart = s.by_light("chart", cam)
        if chart:
            ref_light = "diffuse" if "diffuse" in chart else sorted(chart)[0]
            corners = np.asarray(s.calib.get("chart_corners", {}).get(cam) or s.corners(cam, s.image(chart[ref_light][0])))
            s.calib.setdefault("chart_corners", {})[cam] = corners.tolist()
            for light, gs in chart.items():
                img = calibrated(s, cam, light, s.summed(gs))
                sat = sample_patches(s.merged(gs[0]).saturated.any(-1, keepdims=True).astype(float), corners, s.layout())
                out.setdefault(cam, {})[light] = {"rgb": sample_patches(img, corners, s.layout()),
                                                  "saturated": sat[:, 0] > 0}
    return out


def light_kind(light: str) -> str:
    return "diffuse" if light == "diffuse" else "led" if light.startswith("led") else light


def fit_ccms(s: Session, patches: dict) -> None:
    """One CCM per camera and light kind (directional LEDs pooled; the diffuse group has its
    own spectrum)."""
    s.calib["ccm"] = {}
    for cam, per_light in patches.items():
        kinds: dict[str, list[np.ndarray]] = {}
        sats: dict[str, np.ndarray] = {}
        for light, d in per_light.items():
            k = light_kind(light)
            kinds.setdefault(k, []).append(d["rgb"])
            sats[k] = sats.get(k, np.zeros(cr.N_PATCHES, bool)) | d["saturated"]
        for k, rgbs in kinds.items():
            rgb = np.mean(rgbs, 0)
            fit = fit_and_validate(rgb, patch_mask(rgb, sats[k]))
            s.calib["ccm"].setdefault(cam, {})[k] = fit.to_json()


def calibrate(cs: CaptureSet, progress: Progress = None) -> dict[str, Any]:
    """The whole calibration as a dict ready for
    :func:`dualscale.formats.calibration.write_calibration`; raises before anything is written
    if any input is bad.  ``progress``: one unit per HDR merge (:data:`CALIBRATION_TARGETS`)."""
    total = sum(g.target in CALIBRATION_TARGETS for g in cs.groups)
    with tracker(progress, total, "calibrate", "group") as bar:
        s = Session(cs, progress=bar)
        _check_sizes(s)
        compute_flat_fields(s)
        compute_anchor(s)
        compute_r_c(s)
        patches = measure_patches(s)
        fit_ccms(s, patches)
    dates = sorted(g.date for g in cs.groups if g.date)
    sha = hashlib.sha256((cs.root / "captures.json").read_bytes()).hexdigest()
    from dualscale import __version__ as ver

    s.calib["markers"] = cs.manifest.get("markers", {})
    s.calib["white_level"] = {c: s.white_level(c).to_json() for c in cs.manifest["cameras"]
                              if any(g.target != "dark" for g in cs.select(camera=c))}
    s.calib["dark"] = {c: {"bias": s.dark(c)[0].reshape(-1, 3).mean(0).tolist(),
                           "rate": s.dark(c)[1].reshape(-1, 3).mean(0).tolist()} for c in cs.manifest["cameras"]
                       if cs.select(target="dark", camera=c)}
    return {"created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), "rig": cs.rig,
            "provenance": {"captures": str(cs.root.resolve()), "manifest_sha256": sha,
                           "capture_dates": [dates[0], dates[-1]] if dates else [],
                           "capture_session_date": cs.manifest.get("date"), "n_groups": len(cs.groups),
                           "software": f"dualscale {ver}"},
            **s.calib}


def session_with(cs: CaptureSet, calib: dict[str, Any], progress: Tracker | None = None) -> Session:
    """A session that applies an existing calibration (flat fields, r_c, r_ws, corners, white
    levels where the captures declare none);
    ``progress`` counts its HDR merges (the caller opens and closes it)."""
    keep = {k: calib[k] for k in ("flat_field", "r_c", "r_ws", "r_wp", "ccm", "white_level") if k in calib}
    return Session(cs, keep, progress=progress)
