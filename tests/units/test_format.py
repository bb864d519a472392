"""Dataset format version 2 (saturation, mask, transfer, rig) round trips; version 1 is still read."""

import json

import numpy as np
import pytest

from dualscale.fit.observations import load_observations
from dualscale.formats.dataset import COLOUR_SPACES, UNITS, VERSION, DatasetWriter, read_dataset
from dualscale.geometry.cameras import micro_camera

from .conftest import small_dataset


def test_version_2_round_trip(tmp_path):
    cam = micro_camera(4, 9.0)
    mask = np.ones((4, 4), bool)
    mask[3] = False
    img = np.full((4, 4, 3), 0.25, np.float32)
    img[1, 2, 0] = 1.0  # one clipped channel clips the pixel
    with DatasetWriter(tmp_path / "ds", mask=mask, transfer="gamma:2.2", rig={"id": "r", "layout": "l"}) as w:
        w.add(img, cam, "led", 3, [0.0, 0.6, 0.8], 2.0, None, False, 0.5, saturation=1.0)
        for t in (0.01, 0.1):  # dark frames differ by exposure only
            w.add(np.zeros((4, 4, 3)), cam, "off", None, None, 1.0, exposure_s=t)
    ds = read_dataset(tmp_path / "ds")
    assert ds.version == VERSION == 2 and ds.transfer == "gamma:2.2" and ds.rig == {"id": "r", "layout": "l"}
    assert ds.records[0].saturation == 1.0 and ds.records[1].saturation is None
    assert [r.file for r in ds.records[1:]] == ["images/micro_off_nopol_10000us.exr",
                                                "images/micro_off_nopol_100000us.exr"]
    np.testing.assert_array_equal(ds.mask(), mask)
    valid = ds.valid(0, ds.load(0))
    assert valid.sum() == 11 and not valid[1, 2] and not valid[3].any()
    assert float(ds.load_radiance(0)[0, 0, 0]) == pytest.approx(0.25 / (0.5 * 2.0))  # per unit exposure, intensity
    obs = load_observations(tmp_path / "ds")
    assert float(obs.images[0, 0, 0, 0]) == pytest.approx(0.25 / (0.5 * 2.0))
    assert obs.valid.shape == (1, 4, 4) and int(obs.valid.sum()) == 11


def test_version_1_is_still_read(tmp_path):
    ds = small_dataset(tmp_path / "ds")
    m = json.loads((ds / "manifest.json").read_text())
    m["version"] = 1
    for k in ("mask", "transfer", "rig"):
        m.pop(k)
    for r in m["images"]:
        r.pop("saturation")
    (ds / "manifest.json").write_text(json.dumps(m))
    d = read_dataset(ds)
    assert d.version == 1 and d.mask() is None and all(r.saturation is None for r in d.records)
    obs = load_observations(ds)
    assert obs.n == 6 and obs.valid is None


def test_registries_are_documented():
    from dualscale.formats import dataset

    doc = dataset.__doc__
    for name in list(UNITS) + list(COLOUR_SPACES):
        assert f"``{name}``" in doc, name


def test_signal_scale_round_trip_and_refusals(tmp_path):
    """An image's ``signal_scale`` (per channel, sensor signal to file values) is written only
    when given, read back, and folded with the exposure and the light by the fit's reader; a
    malformed one is refused with the field named."""
    import json

    import pytest

    from dualscale.errors import FormatError, UnitsError
    from dualscale.fit.observations import load_observations

    root = tmp_path / "ds"
    with DatasetWriter(root) as w:
        for i, (scale, t) in enumerate((([1.0, 2.0, 4.0], 1.0), (None, 0.5))):
            w.add(np.full((4, 4, 3), 0.2, np.float32), micro_camera(4, 9.0), "led", i + 1, [0.0, 0.6, 0.8], 2.0,
                  exposure_s=t, signal_scale=scale)
    recs = json.loads((root / "manifest.json").read_text())["images"]
    assert recs[0]["signal_scale"] == [1.0, 2.0, 4.0] and "signal_scale" not in recs[1]
    obs = load_observations(root)
    assert obs.signal_scale.tolist() == [[0.5, 1.0, 2.0], [1.0, 1.0, 1.0]]  # / (exposure x intensity)
    for bad, err in (([1.0, 2.0], FormatError), ([1.0, -1.0, 1.0], UnitsError), ([1.0, float("nan"), 1.0], UnitsError)):
        recs[0]["signal_scale"] = bad
        m = json.loads((root / "manifest.json").read_text())
        m["images"] = recs
        (root / "manifest.json").write_text(json.dumps(m))
        with pytest.raises(err, match="signal_scale"):
            read_dataset(root)
