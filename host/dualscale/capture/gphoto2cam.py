"""``gphoto2``: DSLRs and mirrorless cameras (the paper's mid-range camera) through python-gphoto2
(PyPI ``gphoto2``, which bundles libgphoto2; ``pip install 'dualscale[cameras]'``).  Issue 14 §2.

Specs: ``gphoto2:`` (the first camera libgphoto2 detects), ``gphoto2:usb:001,004`` (the camera
on that port), ``gphoto2:MODEL`` (the first detected camera whose model contains ``MODEL``),
with options after ``?``: ``iso=100`` (or ``auto``), ``aperture=8`` (f-number), ``pixel_um=4.3``
(the pixel pitch [um]; PTP does not report it: without it ``SensorInfo.pixel_um`` is 1.0 and
``settings()["pixel_um_known"]`` is False).

Settings map to the camera's own choice lists (its config widgets):

* exposure [s] -> the nearest ``shutterspeed`` choice in stops (``"1/125"``, ``"0.5"``, ``"2"``,
  ``"13/10"``; ``bulb``/``time`` are never chosen), refused (``InputError``) more than 1/6 stop
  outside the camera's range; the frame reports the chosen speed, not the requested one;
* aperture -> the nearest ``aperture`` / ``f-number`` choice (``"f/8"``, ``"5.6"``), same rule;
* ISO -> the nearest ``iso`` choice, same rule (``auto`` only when asked for);
* image format -> the RAW + JPEG choice of ``imageformat`` / ``imagequality`` (best JPEG).

Trigger: ``internal`` only; :meth:`trigger` is one ``gp_camera_capture`` (the shutter), then the
files it made (RAW and JPEG: the capture's path plus ``FILE_ADDED`` events) are downloaded to a
temporary folder.  The frame is the RAW's Bayer mosaic (``(H, W)``, ``DN / (2^bits - 1)``) when
``rawpy`` is importable, else the JPEG (``(H, W, 3)``, ``DN / 255``, sRGB-encoded, *not* linear:
``metadata["encoding"]`` says which) with the RAW kept on disk undecoded
(``metadata["raw_path"]``).  Timestamps are the host's monotonic clock at the shutter call.

libgphoto2 errors become one-line :class:`~dualscale.errors.CameraDisconnected` (no camera,
I/O, USB) or :class:`~dualscale.errors.CameraError` naming the spec, the step and what to check.
Without a camera only the mapping and the errors are tested (docs/CAPTURE.md "gphoto2").
"""

from __future__ import annotations

import math
import os
import re
import shutil
import tempfile
import time
from fractions import Fraction
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from dualscale.capture.camera import SensorInfo, register_backend
from dualscale.capture.camera import HostTriggeredCamera, option_float, split_options
from dualscale.errors import CameraDisconnected, CameraError, InputError, ToolError

SHUTTER_KEYS = ("shutterspeed", "shutterspeed2", "exptime")
APERTURE_KEYS = ("aperture", "f-number", "fnumber")
ISO_KEYS = ("iso", "isospeed")
FORMAT_KEYS = ("imageformat", "imagequality", "imageformatsd")
SERIAL_KEYS = ("serialnumber", "eosserialnumber")
RAW_TOKENS = ("raw", "nef", "nrw", "cr2", "cr3", "crw", "arw", "srf", "sr2", "orf", "raf", "rw2", "pef", "dng",
              "srw", "3fr", "iiq", "x3f", "rwl")
JPEG_EXTS = (".jpg", ".jpeg")
TOLERANCE_STOPS = 1.0 / 6.0  # half of the usual 1/3-stop step beyond the ends of a choice list

# libgphoto2 result codes (gphoto2-result.h, gphoto2-port-result.h) that mean "no camera / the link failed"
_GONE = {-105: "no camera found", -52: "USB device not found", -53: "USB device claimed by another program",
         -7: "I/O problem", -31: "I/O initialisation failed", -34: "I/O read failed", -35: "I/O write failed",
         -10: "timed out", -5: "unknown port"}
_CHECK = ("check the USB cable, that the camera is on, awake and in PC/PTP (tethered) mode, and that no other "
          "program holds it (gvfs-gphoto2-volume-monitor, another gphoto2)")


# -- the settings mapping (pure: tested without a camera) -------------------------------------------
def parse_shutterspeed(choice: str) -> float | None:
    """A shutter-speed choice -> seconds: ``"1/125"`` 0.008, ``"0.5"``, ``"2"``, ``"2s"``, ``'2"'``,
    ``"13/10"`` 1.3 (Nikon's tenths); ``None`` for ``bulb``, ``time``, ``auto`` and the unreadable."""
    s = str(choice).strip().lower().rstrip('s"').strip()
    try:
        v = float(Fraction(s)) if "/" in s else float(s)
    except (ValueError, ZeroDivisionError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def parse_fnumber(choice: str) -> float | None:
    """An aperture choice -> f-number: ``"f/8"``, ``"F5.6"``, ``"8"``; ``None`` for ``implicit auto``."""
    m = re.fullmatch(r"\s*(?:f\s*/?\s*)?(\d+(?:\.\d+)?)\s*", str(choice).lower())
    return float(m.group(1)) if m and float(m.group(1)) > 0 else None


def parse_iso(choice: str) -> float | None:
    """An ISO choice -> ISO: ``"100"``, ``"ISO 100"``; ``None`` for ``Auto`` and the like."""
    m = re.fullmatch(r"\s*(?:iso\s*)?(\d+)\s*", str(choice).lower())
    return float(m.group(1)) if m and int(m.group(1)) > 0 else None


def _nearest(what: str, unit: str, wanted: float, choices: Sequence[str], parse, stop: float,
             fmt=lambda v: f"{v:g}") -> tuple[str, float]:
    """The choice nearest to ``wanted`` in stops (``log(value)/log(stop)``); ``InputError`` when
    ``wanted`` is more than :data:`TOLERANCE_STOPS` beyond the ends or nothing is numeric."""
    vals = [(c, parse(c)) for c in choices]
    vals = [(c, v) for c, v in vals if v is not None]
    if not vals:
        raise InputError(f"gphoto2: the camera offers no numeric {what} choice ({', '.join(map(str, choices)) or 'none'})")
    if not (math.isfinite(wanted) and wanted > 0):
        raise InputError(f"gphoto2: {what} must be a positive number, got {wanted!r}")
    lo, hi = min(v for _, v in vals), max(v for _, v in vals)
    if math.log(lo / wanted, stop) > TOLERANCE_STOPS or math.log(wanted / hi, stop) > TOLERANCE_STOPS:
        raise InputError(f"gphoto2: {what} {fmt(wanted)}{unit} is outside the camera's range "
                         f"{fmt(lo)}-{fmt(hi)}{unit}")
    return min(vals, key=lambda cv: abs(math.log(cv[1] / wanted)))


def nearest_shutterspeed(exposure_s: float, choices: Sequence[str]) -> tuple[str, float]:
    """``(choice, seconds)`` nearest to ``exposure_s`` (module docstring); bulb is never chosen."""
    return _nearest("exposure", " s", exposure_s, choices, parse_shutterspeed, 2.0)


def nearest_aperture(f_number: float, choices: Sequence[str]) -> tuple[str, float]:
    """``(choice, f-number)`` nearest to ``f_number`` (one stop = a factor sqrt 2)."""
    return _nearest("aperture", "", f_number, choices, parse_fnumber, math.sqrt(2.0), fmt=lambda v: f"f/{v:g}")


def iso_choice(iso: float | str, choices: Sequence[str]) -> str:
    """The ISO choice for ``iso`` (a number: the nearest in stops; ``"auto"``: the camera's auto
    choice, ``InputError`` if it has none)."""
    if isinstance(iso, str) and iso.strip().lower() == "auto":
        for c in choices:
            if "auto" in str(c).lower():
                return c
        raise InputError(f"gphoto2: the camera has no auto ISO choice ({', '.join(choices)})")
    return _nearest("ISO", "", float(iso), choices, parse_iso, 2.0)[0]


def raw_jpeg_choice(choices: Sequence[str]) -> str:
    """The image-format choice that saves RAW and JPEG together, preferring the largest, finest
    JPEG (``"RAW + Large Fine JPEG"``, ``"NEF+Fine"``, ``"RAW+JPEG"``); ``InputError`` if none."""
    def is_raw(c: str) -> bool:
        return any(re.search(rf"(?<![a-z0-9]){t}(?![a-z0-9])", c.lower()) for t in RAW_TOKENS)

    both = [c for c in choices if is_raw(c) and "+" in c]
    if not both:
        raise InputError(f"gphoto2: the camera offers no RAW + JPEG image format ({', '.join(choices)})")

    def rank(c: str) -> tuple[int, int]:
        low = c.lower()
        size = 2 if re.search(r"\blarge\b|\bl\b|\+ ?l", low) else (0 if re.search(r"small|medium|\bs\d?\b|\bm\b", low) else 1)
        qual = 2 if ("fine" in low or "extra" in low) else (0 if ("basic" in low or "normal" in low) else 1)
        return (size, qual)

    return max(both, key=rank)


def gphoto2_error(err: Exception, spec: str, doing: str) -> CameraError:
    """A libgphoto2 error (``GPhoto2Error``: ``.code``, ``.string``) -> one-line
    ``CameraDisconnected`` (no camera, I/O, USB, port, timeout) or ``CameraError``."""
    code = int(getattr(err, "code", 0) or 0)
    text = getattr(err, "string", None) or str(err)
    if code in _GONE:
        return CameraDisconnected(f"camera {spec!r}: {doing}: {_GONE[code]} (libgphoto2 {code}: {text}); {_CHECK}")
    hint = {-110: "the camera is busy (autofocus failed? set the lens to MF, or wait for the card write)",
            -6: "the camera's driver cannot do this (remote capture unsupported for this model?)"}.get(code, "")
    return CameraError(f"camera {spec!r}: {doing}: libgphoto2 {code}: {text}" + (f"; {hint}" if hint else ""))


def read_capture(files: Sequence[str | os.PathLike], spec: str = "gphoto2:") -> tuple[np.ndarray, dict[str, Any]]:
    """The frame from one capture's downloaded ``files`` (module docstring): the RAW's Bayer
    mosaic through ``rawpy`` when importable, else the JPEG through OpenImageIO with the RAW kept
    undecoded.  Returns ``(image, metadata)`` (``encoding``, ``bit_depth``, ``raw_path``,
    ``jpeg_path``, ``black_level``/``white_level`` normalised for a RAW)."""
    paths = [Path(f) for f in files]
    raw = next((p for p in paths if p.suffix.lower().lstrip(".") in RAW_TOKENS), None)
    jpeg = next((p for p in paths if p.suffix.lower() in JPEG_EXTS), None)
    meta: dict[str, Any] = {"raw_path": str(raw) if raw else None, "jpeg_path": str(jpeg) if jpeg else None}
    if raw is not None:
        try:
            import rawpy  # optional: not a dependency (docs/CAPTURE.md "gphoto2")
        except ImportError:
            rawpy = None
        if rawpy is not None:
            with rawpy.imread(str(raw)) as r:
                mosaic = np.array(r.raw_image_visible, dtype=np.float32)
                bits = max(8, int(math.ceil(math.log2(float(r.white_level) + 1))))
                full = float(2 ** bits - 1)
                meta.update(encoding="raw_bayer", bit_depth=bits, white_level=float(r.white_level) / full,
                            black_level=float(np.mean(r.black_level_per_channel)) / full,
                            bayer_pattern="".join("RGBG"[int(i)] for i in np.asarray(r.raw_pattern).ravel()))
                return mosaic / np.float32(full), meta
    if jpeg is None:
        raise CameraError(f"camera {spec!r}: the capture gave no JPEG ({', '.join(p.name for p in paths) or 'no file'})"
                          " and no RAW decoder (rawpy) is installed: set the image format to RAW + JPEG")
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(jpeg))
    pixels = buf.get_pixels(oiio.UINT8)
    if buf.has_error or pixels is None:
        raise CameraError(f"camera {spec!r}: cannot read {jpeg}: {buf.geterror()}")
    img = np.asarray(pixels, dtype=np.float32)[:, :, :3] / np.float32(255)
    meta.update(encoding="srgb_jpeg", bit_depth=8,
                note="sRGB-encoded JPEG, not linear raw DN" + ("; the RAW is kept undecoded at raw_path" if raw else ""))
    return (img[:, :, 0] if img.shape[2] == 1 else img), meta


# -- the camera ------------------------------------------------------------------------------------
def _gp():
    try:
        import gphoto2 as gp
    except ImportError as e:
        raise ToolError("camera backend gphoto2 needs python-gphoto2: pip install 'dualscale[cameras]' "
                        f"(or pip install gphoto2): {e}") from None
    return gp


class GPhoto2Camera(HostTriggeredCamera):
    """A camera through libgphoto2 (module docstring)."""

    def __init__(self, rest: str):
        super().__init__()
        gp = self._gp = _gp()
        self.spec = f"gphoto2:{rest}"
        target, opts = split_options(rest)
        self._pixel_um = option_float(opts, "pixel_um", self.spec)
        self._iso = opts.get("iso")
        self._aperture = option_float(opts, "aperture", self.spec)
        try:
            found = gp.Camera.autodetect()
            detected = [(str(found.get_name(i)), str(found.get_value(i))) for i in range(found.count())]
        except gp.GPhoto2Error as e:
            raise gphoto2_error(e, self.spec, "detecting cameras") from None
        if target and ":" in target:
            pick = [d for d in detected if d[1] == target]
        else:
            pick = [d for d in detected if target.lower() in d[0].lower()]
        if not pick:
            seen = "; ".join(f"{n} on {p}" for n, p in detected) or "none"
            raise CameraDisconnected(f"camera {self.spec!r}: no camera {('matching ' + repr(target)) if target else ''}"
                                     f"detected by libgphoto2 (detected: {seen}); {_CHECK}".replace("  ", " "))
        self.model, self.port = pick[0]
        cam = gp.Camera()
        try:
            abilities = gp.CameraAbilitiesList()
            abilities.load()
            cam.set_abilities(abilities[abilities.lookup_model(self.model)])
            ports = gp.PortInfoList()
            ports.load()
            cam.set_port_info(ports[ports.lookup_path(self.port)])
            cam.init()
        except gp.GPhoto2Error as e:
            raise gphoto2_error(e, self.spec, f"opening {self.model} on {self.port}") from None
        self._cam = cam
        self._tmp = tempfile.mkdtemp(prefix="dualscale-gphoto2-")
        self.serial = self._text(SERIAL_KEYS) or f"{self.model}@{self.port}"
        self._shutter: tuple[str, float] | None = None
        self._sensor: SensorInfo | None = None
        self._set(FORMAT_KEYS, raw_jpeg_choice, "image format")
        if self._iso is not None:
            self._set(ISO_KEYS, lambda ch: iso_choice(self._iso if self._iso == "auto" else float(self._iso), ch), "ISO")
        if self._aperture is not None:
            self._set(APERTURE_KEYS, lambda ch: nearest_aperture(self._aperture, ch)[0], "aperture")

    # -- config widgets ----------------------------------------------------------------------------
    def _widget(self, keys: Sequence[str]):
        gp = self._gp
        for k in keys:
            try:
                return self._cam.get_single_config(k)
            except gp.GPhoto2Error:
                continue
        return None

    def _text(self, keys: Sequence[str]) -> str | None:
        w = self._widget(keys)
        v = str(w.get_value()).strip() if w is not None else ""
        return v or None

    def _set(self, keys: Sequence[str], choose, what: str) -> str:
        w = self._widget(keys)
        if w is None:
            raise CameraError(f"camera {self.spec!r}: {self.model} has no {what} setting (config {'/'.join(keys)})")
        value = choose([str(c) for c in w.get_choices()])
        if str(w.get_value()) != value:
            try:
                w.set_value(value)
                self._cam.set_single_config(w.get_name(), w)
            except self._gp.GPhoto2Error as e:
                raise gphoto2_error(e, self.spec, f"setting {what} to {value!r}") from None
        return value

    # -- reports -----------------------------------------------------------------------------------
    def sensor(self) -> SensorInfo:
        """The sensor of the frames this camera delivers; before the first frame it is learnt by
        one probe capture (discarded): PTP reports no sensor size."""
        if self._sensor is None:
            image, meta = self._capture()
            self._sensor_from(image, meta)
        assert self._sensor is not None
        return self._sensor

    def _sensor_from(self, image: np.ndarray, meta: dict[str, Any]) -> None:
        bits = int(meta["bit_depth"])
        raw = meta["encoding"] == "raw_bayer"
        self._sensor = SensorInfo(width=image.shape[1], height=image.shape[0], pixel_um=self._pixel_um or 1.0,
                                  bit_depth=bits, black_level=meta.get("black_level", 0.0) if raw else 0.0,
                                  white_level=meta.get("white_level", 1.0) if raw else 1.0,
                                  pixel_format=(f"Bayer{meta.get('bayer_pattern', 'RGGB')[:4]}{bits}" if raw else "RGB8"))

    def settings(self) -> dict[str, Any]:
        out: dict[str, Any] = {"model": self.model, "port": self.port, "pixel_um_known": self._pixel_um is not None}
        for name, keys in (("shutterspeed", SHUTTER_KEYS), ("aperture", APERTURE_KEYS), ("iso", ISO_KEYS),
                           ("image_format", FORMAT_KEYS)):
            out[name] = self._text(keys)
        out["exposure_s"] = self._shutter[1] if self._shutter else None
        return out

    # -- lifecycle hooks ---------------------------------------------------------------------------
    def _apply_exposure(self, exposure_s: float) -> None:
        w = self._widget(SHUTTER_KEYS)
        if w is None:
            raise CameraError(f"camera {self.spec!r}: {self.model} has no shutter speed setting "
                              "(set the mode dial to M)")
        choice = nearest_shutterspeed(exposure_s, [str(c) for c in w.get_choices()])
        self._set(SHUTTER_KEYS, lambda _ch: choice[0], "shutter speed")
        self._shutter = choice

    def _capture(self) -> tuple[np.ndarray, dict[str, Any]]:
        gp = self._gp
        try:
            path = self._cam.capture(gp.GP_CAPTURE_IMAGE)
            names = [(path.folder, path.name)]
            while True:  # the other files of a RAW + JPEG capture arrive as FILE_ADDED events
                kind, data = self._cam.wait_for_event(300)
                if kind == gp.GP_EVENT_FILE_ADDED:
                    names.append((data.folder, data.name))
                elif kind == gp.GP_EVENT_TIMEOUT:
                    break
            local = []
            for folder, name in dict.fromkeys(names):
                dest = os.path.join(self._tmp, name)
                self._cam.file_get(folder, name, gp.GP_FILE_TYPE_NORMAL).save(dest)
                local.append(dest)
        except gp.GPhoto2Error as e:
            raise gphoto2_error(e, self.spec, "capturing") from None
        return read_capture(local, self.spec)

    def _grab(self) -> tuple[np.ndarray, float, float, dict[str, Any]]:
        ts = time.monotonic()
        image, meta = self._capture()
        if self._sensor is None:
            self._sensor_from(image, meta)
        return image, ts, self._shutter[1] if self._shutter else float("nan"), {"shutterspeed": self._shutter[0]
                                                                               if self._shutter else None, **meta}

    def close(self) -> None:
        self.disarm()
        cam, self._cam = getattr(self, "_cam", None), None
        if cam is not None:
            try:
                cam.exit()
            except self._gp.GPhoto2Error:
                pass
        tmp = getattr(self, "_tmp", None)
        if tmp and os.path.isdir(tmp) and not os.listdir(tmp):
            shutil.rmtree(tmp, ignore_errors=True)  # downloaded captures are kept: they are the data


register_backend("gphoto2", GPhoto2Camera)
