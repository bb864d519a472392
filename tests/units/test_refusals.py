"""Every input the stages cannot interpret is refused with an error that names the file and the
field, exit code 2 at the command line, and nothing written (docs/APPEARANCE.md, dataset format)."""

import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from dualscale.cli import main
from dualscale.errors import GeometryError, InputError, UnitsError
from dualscale.formats.dataset import DatasetWriter, read_dataset
from dualscale.geometry.cameras import micro_camera

from .conftest import small_dataset
from .helpers import edit_manifest, led_records, nothing_written


def _fit(ds: Path, out: Path, capsys) -> tuple[int, str]:
    rc = main(["fit", str(ds), "-o", str(out), "--preset", "draft", "--no-progress", "--no-previews",
               "--threads", "1"])
    return rc, capsys.readouterr().err


def _refused_by_fit(ds: Path, tmp_path: Path, capsys, *needles: str) -> str:
    out = tmp_path / "maps"
    rc, err = _fit(ds, out, capsys)
    assert rc == 2, err
    assert err.startswith("dualscale fit: error: ") and "Traceback" not in err
    for n in needles:
        assert n in err, (n, err)
    assert nothing_written(out)
    return err


def test_undocumented_colour_space(dataset, tmp_path, capsys):
    edit_manifest(dataset, lambda m: led_records(m)[2].update(colour_space="srgb"))
    with pytest.raises(UnitsError, match="colour_space 'srgb' is not documented"):
        read_dataset(dataset)
    _refused_by_fit(dataset, tmp_path, capsys, "manifest.json", "colour_space 'srgb'", "linear_rec709")


def test_undocumented_units(dataset, tmp_path, capsys):
    edit_manifest(dataset, lambda m: m.update(units="nits") or [r.pop("units") for r in m["images"]])
    with pytest.raises(UnitsError, match="units 'nits' are not documented"):
        read_dataset(dataset)
    _refused_by_fit(dataset, tmp_path, capsys, "manifest.json", "units 'nits'", "relative_radiance")


def test_raw_dataset_is_not_fitted_without_a_calibration(tmp_path, capsys):
    ds = small_dataset(tmp_path / "raw", units="dn_normalized", colour_space="camera_raw:Nikon 5100 (NPL)")
    err = _refused_by_fit(ds, tmp_path, capsys, "units 'dn_normalized'", "calibration", "--calibration")
    assert "micro_led000" in err  # the file
    from dualscale.calib.apply import to_radiance

    with pytest.raises(UnitsError, match="calibration file is needed"):
        to_radiance(ds, tmp_path / "cal")
    assert nothing_written(tmp_path / "cal")


def test_camera_raw_colour_space_is_not_fitted(tmp_path, capsys):
    ds = small_dataset(tmp_path / "raw", colour_space="camera_raw:Nikon 5100 (NPL)")
    _refused_by_fit(ds, tmp_path, capsys, "colour_space 'camera_raw:Nikon 5100 (NPL)'", "calibration")


@pytest.mark.parametrize("direction", [[1.0, 0.0, 0.0], [0.6, 0.0, -0.8]])
def test_light_below_the_sample_plane(dataset, tmp_path, capsys, direction):
    edit_manifest(dataset, lambda m: led_records(m)[1]["light"].update(direction=direction))
    with pytest.raises(GeometryError, match=r"light.direction .* <= 0"):
        read_dataset(dataset)
    _refused_by_fit(dataset, tmp_path, capsys, "light.direction", "below or on the sample plane", "led000")


def test_non_unit_direction(dataset, tmp_path, capsys):
    edit_manifest(dataset, lambda m: led_records(m)[0]["light"].update(direction=[0.0, 0.0, 2.0]))
    _refused_by_fit(dataset, tmp_path, capsys, "light.direction", "not a unit vector")


@pytest.mark.parametrize("intensity", [0.0, -1.0])
def test_light_intensity_not_positive(dataset, tmp_path, capsys, intensity):
    edit_manifest(dataset, lambda m: led_records(m)[3]["light"].update(intensity=intensity))
    with pytest.raises(InputError, match="light.intensity must be a finite number > 0"):
        read_dataset(dataset)
    _refused_by_fit(dataset, tmp_path, capsys, "light.intensity", "led008")


@pytest.mark.parametrize("exposure", [math.nan, math.inf, 0.0, -0.01, None, "fast"])
def test_exposure_not_finite_positive(dataset, tmp_path, capsys, exposure):
    edit_manifest(dataset, lambda m: led_records(m)[4].update(exposure_s=exposure))
    with pytest.raises(UnitsError, match="exposure_s must be a finite number > 0"):
        read_dataset(dataset)
    _refused_by_fit(dataset, tmp_path, capsys, "exposure_s", "led040")


def test_saturation_not_finite_positive(dataset, tmp_path, capsys):
    edit_manifest(dataset, lambda m: led_records(m)[0].update(saturation=-1))
    _refused_by_fit(dataset, tmp_path, capsys, "saturation must be a finite number > 0")


def test_writer_refuses_what_the_reader_refuses(tmp_path):
    cam = micro_camera(4, 9.0)
    img = np.full((4, 4, 3), 0.1)
    with pytest.raises(UnitsError, match="units 'lux'"):
        DatasetWriter(tmp_path / "a", units="lux")
    with pytest.raises(UnitsError, match="colour_space 'sRGB'"):
        DatasetWriter(tmp_path / "b", colour_space="sRGB")
    with pytest.raises(UnitsError, match="transfer"):
        DatasetWriter(tmp_path / "c", transfer="log")
    w = DatasetWriter(tmp_path / "d")
    with pytest.raises(GeometryError, match="light.direction"):
        w.add(img, cam, "led", 1, [0.0, 0.6, -0.8])
    with pytest.raises(InputError, match="light.intensity"):
        w.add(img, cam, "led", 1, [0.0, 0.0, 1.0], intensity=0.0)
    with pytest.raises(UnitsError, match="exposure_s"):
        w.add(img, cam, "led", 1, [0.0, 0.0, 1.0], exposure_s=float("nan"))
    with pytest.raises(UnitsError, match="saturation"):
        w.add(img, cam, "led", 1, [0.0, 0.0, 1.0], saturation=0.0)
    with pytest.raises(GeometryError, match="mask is 3x4"):
        DatasetWriter(tmp_path / "e", mask=np.ones((4, 3))).add(img, cam, "led", 1, [0.0, 0.0, 1.0])
    assert not list((tmp_path / "d" / "images").iterdir())  # nothing refused was written
    assert not (tmp_path / "d" / "manifest.json").exists()


def test_mask_of_another_size(dataset, tmp_path, capsys):
    from dualscale.formats.exr import write_exr

    write_exr(dataset / "mask.exr", np.ones((5, 6), np.float32), ("Y",))
    edit_manifest(dataset, lambda m: m.update(mask="mask.exr"))
    with pytest.raises(GeometryError, match="mask is 6x5"):
        read_dataset(dataset)
    _refused_by_fit(dataset, tmp_path, capsys, "mask.exr", "mask is 6x5")


def test_shifted_data_window(dataset, tmp_path, capsys):
    """An image moved with `oiiotool --origin` would be fitted misaligned: refused."""
    oiiotool = Path(__file__).resolve().parents[2] / ".venv" / "bin" / "oiiotool"
    if not oiiotool.is_file():
        pytest.skip(f"oiiotool (OpenImageIO wheel) not found at {oiiotool}")
    victim = dataset / read_dataset(dataset).records[2].file
    shifted = tmp_path / "shifted.exr"
    subprocess.run([str(oiiotool), str(victim), "--origin", "+5+3", "-o", str(shifted)], check=True)
    shifted.replace(victim)
    ds = read_dataset(dataset)  # the manifest is fine; the pixels are refused when read
    with pytest.raises(GeometryError, match=r"data window origin \(5, 3\)"):
        ds.load(2)
    _refused_by_fit(dataset, tmp_path, capsys, victim.name, "data window origin (5, 3)")
    from dualscale.calib.apply import to_radiance

    with pytest.raises(GeometryError, match="data window"):
        to_radiance(dataset, tmp_path / "canonical")
    assert nothing_written(tmp_path / "canonical")


def test_non_unit_normals_in_maps(tmp_path, capsys):
    from dualscale.formats.exr import read_exr, write_exr

    assert main(["synth", "leather", "-o", str(tmp_path / "s"), "--size", "8", "--no-previews"]) == 0
    maps = tmp_path / "s" / "maps"
    n = read_exr(maps / "normal.exr")
    n[2, 5] *= 1.5
    write_exr(maps / "normal.exr", n, ("X", "Y", "Z"))
    out = tmp_path / "render"
    rc = main(["render", str(maps), "-o", str(out), "--led", "0", "--analyzer", "0"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "normal" in err and "not unit vectors" in err and "row 2, col 5" in err
    assert nothing_written(out)


def test_malformed_camera_record_is_refused_naming_the_field(dataset, tmp_path, capsys):
    """A camera whose field_mm is null (a hand-edited manifest) was an internal error (exit 5):
    the one camera reader refuses it, naming the camera and the field."""
    from dualscale.geometry.cameras import Camera

    with pytest.raises(ValueError, match="camera 'micro' is malformed.*field_mm"):
        Camera.from_json("micro", {"kind": "orthographic", "width": 8, "height": 8, "field_mm": None}, "m.json")
    with pytest.raises(ValueError, match="has no 'width'"):
        Camera.from_json("micro", {"kind": "orthographic", "field_mm": [1, 1]}, "m.json")
    edit_manifest(dataset, lambda m: [c.update(field_mm=None) for c in m["cameras"].values()])
    run = tmp_path / "run"
    rc = main(["digitize", str(dataset), "-o", str(run), "--quality", "draft", "--threads", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "field_mm" in err and "Traceback" not in err, err


def test_normals_in_the_plane_load_and_below_it_are_refused(tmp_path):
    """docs/APPEARANCE.md stores normals with z >= 0 (issue 24 §8): z = 0, which the fit's
    hemisphere mapping reaches at grazing tilt, loads; z < 0 is refused naming the texel."""
    from dualscale.formats.exr import read_exr, write_exr
    from dualscale.formats.maps import load_maps

    assert main(["synth", "leather", "-o", str(tmp_path / "s"), "--size", "8", "--no-previews"]) == 0
    maps = tmp_path / "s" / "maps"
    n = read_exr(maps / "normal.exr")
    n[1, 2] = (1.0, 0.0, 0.0)
    write_exr(maps / "normal.exr", n, ("X", "Y", "Z"))
    got, _ = load_maps(maps)
    assert float(got.normal[1, 2, 2]) == 0.0
    n[3, 4] = (0.0, 0.6, -0.8)
    write_exr(maps / "normal.exr", n, ("X", "Y", "Z"))
    with pytest.raises(GeometryError, match=r"below the sample plane \(z < 0; first at row 3, col 4\)"):
        load_maps(maps)
