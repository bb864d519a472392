"""The ``gphoto2`` backend without a camera: the settings mapping (exposure, aperture, ISO,
RAW + JPEG onto a camera's choice lists), the one-line errors for libgphoto2's error codes, a
clean failure of ``gphoto2:`` with no camera attached (the real libgphoto2, bundled by PyPI
``gphoto2``), and the reading of a capture's downloaded files.  The contract suite runs only when
libgphoto2 detects a camera; what stays untested is listed in docs/CAPTURE.md "gphoto2".

The choice lists below are written in the style ``gphoto2 --get-config`` prints for Canon EOS,
Nikon and Sony bodies (strings vary by model and firmware; they are examples, not captures from
these bodies)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import dualscale.capture.gphoto2cam  # noqa: F401  (registers "gphoto2")
from dualscale.capture.camera import open_camera
from dualscale.capture.gphoto2cam import (gphoto2_error, iso_choice, nearest_aperture, nearest_shutterspeed,
                                          parse_fnumber, parse_shutterspeed, raw_jpeg_choice, read_capture)
from dualscale.errors import CameraDisconnected, CameraError, InputError

try:  # tests/capture may or may not be a package
    from .contract import CameraContract
except ImportError:
    from contract import CameraContract

try:
    import gphoto2 as gp
except ImportError:  # the mapping tests run without it; the libgphoto2 ones skip
    gp = None
needs_gp = pytest.mark.skipif(gp is None, reason="python-gphoto2 not installed (pip install 'dualscale[cameras]')")

CANON_SHUTTER = ["bulb", "30", "25", "20", "15", "13", "10", "8", "6", "5", "4", "3.2", "2.5", "2", "1.6", "1.3",
                 "1", "0.8", "0.6", "0.5", "0.4", "0.3", "1/4", "1/5", "1/6", "1/8", "1/10", "1/13", "1/15", "1/20",
                 "1/25", "1/30", "1/40", "1/50", "1/60", "1/80", "1/100", "1/125", "1/160", "1/200", "1/250",
                 "1/320", "1/400", "1/500", "1/640", "1/800", "1/1000", "1/1250", "1/1600", "1/2000", "1/2500",
                 "1/3200", "1/4000", "1/5000", "1/6400", "1/8000"]
NIKON_SHUTTER = ["1/4000", "1/2000", "1/1000", "1/500", "1/250", "1/125", "1/60", "1/30", "1/15", "10/10", "13/10",
                 "20/10", "300/10", "Bulb", "Time"]
CANON_APERTURE = ["implicit auto", "2.8", "3.2", "3.5", "4", "4.5", "5", "5.6", "6.3", "7.1", "8", "9", "10", "11",
                  "13", "14", "16", "18", "20", "22"]
NIKON_FNUMBER = ["f/2.8", "f/4", "f/5.6", "f/8", "f/11", "f/16", "f/22"]
ISO = ["Auto", "100", "125", "160", "200", "250", "320", "400", "500", "640", "800", "1600", "3200", "6400", "12800"]
CANON_FORMAT = ["Large Fine JPEG", "Large Normal JPEG", "Small Fine JPEG", "RAW + Small Fine JPEG",
                "RAW + Large Fine JPEG", "RAW + Large Normal JPEG", "RAW", "mRAW + Large Fine JPEG"]
NIKON_QUALITY = ["JPEG Basic", "JPEG Normal", "JPEG Fine", "NEF (Raw)", "NEF+Basic", "NEF+Normal", "NEF+Fine"]
SONY_QUALITY = ["Standard", "Fine", "Extra Fine", "RAW", "RAW+JPEG"]


def test_parse_shutterspeed():
    assert parse_shutterspeed("1/125") == pytest.approx(0.008)
    assert parse_shutterspeed("0.5") == 0.5 and parse_shutterspeed("2") == 2.0
    assert parse_shutterspeed('2"') == 2.0 and parse_shutterspeed("30s") == 30.0
    assert parse_shutterspeed("13/10") == pytest.approx(1.3)
    for c in ("bulb", "Bulb", "Time", "auto", "", "1/0"):
        assert parse_shutterspeed(c) is None


def test_exposure_maps_to_the_nearest_shutterspeed_in_stops():
    assert nearest_shutterspeed(0.005, CANON_SHUTTER) == ("1/200", pytest.approx(0.005))
    assert nearest_shutterspeed(0.02, CANON_SHUTTER)[0] == "1/50"
    assert nearest_shutterspeed(0.0083, CANON_SHUTTER)[0] == "1/125"
    assert nearest_shutterspeed(0.45, CANON_SHUTTER)[0] == "0.5"   # in stops: 0.15 below 0.5, 0.17 above 0.4
    assert nearest_shutterspeed(2.0, CANON_SHUTTER) == ("2", 2.0)
    assert nearest_shutterspeed(30.0, CANON_SHUTTER)[0] == "30"      # never bulb
    assert nearest_shutterspeed(1.0 / 8000, CANON_SHUTTER)[0] == "1/8000"
    assert nearest_shutterspeed(1.2, NIKON_SHUTTER)[0] == "13/10"
    assert nearest_shutterspeed(0.9, NIKON_SHUTTER)[0] == "10/10"


def test_exposure_out_of_range_is_refused_naming_the_range():
    with pytest.raises(InputError, match=r"exposure 60 s is outside the camera's range 0.000125-30 s"):
        nearest_shutterspeed(60.0, CANON_SHUTTER)
    with pytest.raises(InputError, match="outside"):
        nearest_shutterspeed(1.0 / 20000, CANON_SHUTTER)
    nearest_shutterspeed(30.0 * 2 ** (1 / 7), CANON_SHUTTER)  # within 1/6 stop of the end: the end
    with pytest.raises(InputError, match="no numeric exposure choice"):
        nearest_shutterspeed(0.01, ["bulb", "auto"])


def test_aperture_and_iso_choices():
    assert parse_fnumber("f/5.6") == 5.6 and parse_fnumber("8") == 8.0 and parse_fnumber("implicit auto") is None
    assert nearest_aperture(8, CANON_APERTURE)[0] == "8"
    assert nearest_aperture(6.0, CANON_APERTURE)[0] == "6.3"  # 0.15 stop vs 0.19 stop to 5.6
    assert nearest_aperture(9.5, NIKON_FNUMBER)[0] == "f/11"
    with pytest.raises(InputError, match="aperture f/1.4 is outside"):
        nearest_aperture(1.4, CANON_APERTURE)
    assert iso_choice(100, ISO) == "100" and iso_choice(1200, ISO) == "1600"  # 0.42 stop below 1600
    assert iso_choice(1000, ISO) == "800"  # 0.32 stop above 800, 0.68 below 1600
    assert iso_choice("auto", ISO) == "Auto"
    with pytest.raises(InputError, match="ISO 50 is outside"):
        iso_choice(50, ISO)
    with pytest.raises(InputError, match="no auto ISO"):
        iso_choice("auto", ISO[1:])


def test_raw_plus_jpeg_format_choice():
    assert raw_jpeg_choice(CANON_FORMAT) == "RAW + Large Fine JPEG"
    assert raw_jpeg_choice(NIKON_QUALITY) == "NEF+Fine"
    assert raw_jpeg_choice(SONY_QUALITY) == "RAW+JPEG"
    with pytest.raises(InputError, match="no RAW \\+ JPEG"):
        raw_jpeg_choice(["Large Fine JPEG", "RAW"])


@needs_gp
def test_libgphoto2_errors_are_one_line_and_name_what_to_check():
    e = gphoto2_error(gp.GPhoto2Error(gp.GP_ERROR_MODEL_NOT_FOUND), "gphoto2:", "opening")
    assert isinstance(e, CameraDisconnected) and "\n" not in str(e)
    assert "gphoto2:" in str(e) and "-105" in str(e) and "USB cable" in str(e)
    e = gphoto2_error(gp.GPhoto2Error(gp.GP_ERROR_IO), "gphoto2:usb:001,004", "capturing")
    assert isinstance(e, CameraDisconnected) and "I/O" in str(e) and "capturing" in str(e)
    e = gphoto2_error(gp.GPhoto2Error(gp.GP_ERROR_CAMERA_BUSY), "gphoto2:", "capturing")
    assert type(e) is CameraError and "autofocus" in str(e)


@needs_gp
def test_open_without_a_camera_fails_cleanly():
    if gp.Camera.autodetect().count():
        pytest.skip("a camera is attached")
    for spec in ("gphoto2:", "gphoto2:usb:001,004", "gphoto2:Canon EOS"):
        with pytest.raises(CameraDisconnected) as e:
            open_camera(spec)
        msg = str(e.value)
        assert spec in msg and "detected: none" in msg and "USB cable" in msg and "\n" not in msg


def test_read_capture_jpeg_keeps_the_raw_undecoded(tmp_path):
    pytest.importorskip("OpenImageIO")
    bgr = np.zeros((6, 8, 3), np.uint8)
    bgr[..., 2] = 255  # red
    bgr[0, 0] = (0, 0, 0)
    jpg = tmp_path / "IMG_0001.JPG"
    assert cv2.imwrite(str(jpg), bgr, [cv2.IMWRITE_JPEG_QUALITY, 100])
    raw = tmp_path / "IMG_0001.CR2"
    raw.write_bytes(b"not decoded")
    try:
        import rawpy  # noqa: F401
        pytest.skip("rawpy installed: the RAW path would be taken (and this CR2 is not a RAW)")
    except ImportError:
        pass
    img, meta = read_capture([raw, jpg])
    assert img.shape == (6, 8, 3) and img.dtype == np.float32 and 0 <= img.min() and img.max() <= 1
    assert img[3, 4, 0] > 0.9 and img[3, 4, 1] < 0.1  # RGB order (red first)
    assert meta["encoding"] == "srgb_jpeg" and meta["raw_path"] == str(raw) and "undecoded" in meta["note"]
    with pytest.raises(CameraError, match="no JPEG"):
        read_capture([raw])


@needs_gp
class TestGPhoto2Contract(CameraContract):
    """Runs only with a camera attached (and in manual mode, manual focus)."""

    @pytest.fixture(autouse=True)
    def _need_camera(self):
        if not gp.Camera.autodetect().count():
            pytest.skip("no camera detected by libgphoto2: the contract needs a real DSLR (docs/CAPTURE.md)")

    def make(self):
        return open_camera("gphoto2:")

    def disconnect(self, cam):
        pytest.skip("unplugging a DSLR is a manual step")
