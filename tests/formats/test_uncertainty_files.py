"""The uncertainty beside a maps folder (issue 26, ``formats.maps.save_uncertainty`` /
``load_uncertainty``): the round trip, half float within its precision, NaN exactly where
undetermined, stale maps removed, and every malformed file refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dualscale.errors import FormatError
from dualscale.formats.maps import load_uncertainty, save_uncertainty


def _set(h=9, w=7, seed=0):
    rng = np.random.default_rng(seed)
    sigma = {"albedo": rng.uniform(0, 0.2, (h, w, 3)), "normal": rng.uniform(0, 20, (h, w, 1)),
             "roughness": rng.uniform(0, 0.1, (h, w, 1)), "tangent": rng.uniform(0, 90, (h, w, 1))}
    und = {k: rng.random(v.shape) < 0.2 for k, v in sigma.items()}
    und["tangent"][:] = True  # a round lobe: the tangent undetermined everywhere
    return sigma, und


def test_the_round_trip_keeps_sigma_to_half_float_and_the_mask_exactly(tmp_path):
    sigma, und = _set()
    path = save_uncertainty(tmp_path, sigma, und, meta={"noise_scale": "robust residual"})
    assert path == tmp_path / "uncertainty" / "uncertainty.json"
    s2, u2, doc = load_uncertainty(tmp_path)
    assert doc["maps"] == list(sigma) and doc["units"]["normal"].startswith("degrees")
    assert doc["meta"] == {"noise_scale": "robust residual"} and (doc["height"], doc["width"]) == (9, 7)
    for k in sigma:
        assert np.array_equal(u2[k], und[k]), k
        assert np.isnan(s2[k][und[k]]).all() and np.isfinite(s2[k][~und[k]]).all()
        assert np.allclose(s2[k][~und[k]], sigma[k][~und[k]], rtol=1e-3, atol=1e-7), k  # half float: 11 bits


def test_the_uncertainty_is_at_most_the_maps_own_size(tmp_path):
    """Issue 26's cost: the uncertainty may double the maps folder at most; half float keeps it
    near half (measured against the same arrays written as the maps' float32 EXRs)."""
    from dualscale.formats.exr import write_exr

    sigma, und = _set(128, 128, seed=1)
    save_uncertainty(tmp_path / "u", sigma, und)
    for k, v in sigma.items():
        write_exr(tmp_path / "f" / f"{k}.exr", v.astype(np.float32))
    size = lambda d: sum(p.stat().st_size for p in d.glob("*.exr"))  # noqa: E731
    ratio = size(tmp_path / "u" / "uncertainty") / size(tmp_path / "f")
    assert 0.3 < ratio < 0.8, ratio


def test_tiny_and_huge_sigmas_survive_the_half_floats(tmp_path):
    """A nearly noise-free fit's sigma (1e-9 of the map's value, 1e-8 degrees) is stored, not
    rounded to 0 as plain half float would below 6e-8 (a fresh user's finding: "median sigma 0"
    read as a perfectly known albedo); one beyond the range is stored at its top, still finite."""
    h, w = 4, 5
    sigma = {"albedo": np.full((h, w, 3), 3.6e-9), "normal": np.full((h, w, 1), 1e-8),
             "roughness": np.full((h, w, 1), 1e-9)}
    sigma["roughness"][0, 0, 0] = 100.0  # beyond the range (4)
    und = {k: np.zeros(v.shape, bool) for k, v in sigma.items()}
    save_uncertainty(tmp_path, sigma, und)
    back, _, doc = load_uncertainty(tmp_path)
    assert doc["scales"]["albedo"] == 2.0 ** -14 and doc["scales"]["normal"] == 2.0 ** -8
    np.testing.assert_allclose(back["albedo"], 3.6e-9, rtol=2e-3)
    np.testing.assert_allclose(back["normal"], 1e-8, rtol=2e-3)
    np.testing.assert_allclose(back["roughness"][1:], 1e-9, rtol=2e-3)
    assert np.isfinite(back["roughness"][0, 0, 0]) and back["roughness"][0, 0, 0] >= 3.99


def test_a_new_set_removes_the_maps_an_earlier_set_had(tmp_path):
    sigma, und = _set()
    save_uncertainty(tmp_path, sigma, und)
    save_uncertainty(tmp_path, {"albedo": sigma["albedo"]}, {"albedo": und["albedo"]})
    assert sorted(p.name for p in (tmp_path / "uncertainty").glob("*.exr")) == ["albedo.exr", "undetermined.exr"]
    assert list(load_uncertainty(tmp_path)[0]) == ["albedo"]


@pytest.mark.parametrize("bad", ["negative", "nan", "shape", "name", "mismatch"])
def test_bad_sigma_is_refused_and_nothing_is_written(tmp_path, bad):
    sigma, und = _set()
    if bad == "negative":
        sigma["albedo"][0, 0, 0], und["albedo"][0, 0, 0] = -1.0, False
    elif bad == "nan":
        sigma["roughness"][1, 1, 0], und["roughness"][1, 1, 0] = np.nan, False
    elif bad == "shape":
        sigma["normal"] = np.zeros((9, 7, 3))
    elif bad == "name":
        sigma["sheen"], und["sheen"] = np.zeros((9, 7, 1)), np.zeros((9, 7, 1), bool)
    else:
        del und["albedo"]
    with pytest.raises(ValueError):
        save_uncertainty(tmp_path, sigma, und)
    assert not (tmp_path / "uncertainty" / "uncertainty.json").exists()


def test_malformed_files_are_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="no uncertainty"):
        load_uncertainty(tmp_path)
    sigma, und = _set()
    save_uncertainty(tmp_path, sigma, und)
    j = tmp_path / "uncertainty" / "uncertainty.json"
    doc = json.loads(j.read_text())
    j.write_text(json.dumps({**doc, "version": 99}))
    with pytest.raises(FormatError):
        load_uncertainty(tmp_path)
    j.write_text(json.dumps({**doc, "height": 10}))
    with pytest.raises(FormatError, match="uncertainty.json says"):
        load_uncertainty(tmp_path)
    j.write_text(json.dumps({**doc, "maps": ["albedo", "sheen"]}))
    with pytest.raises(FormatError, match="unknown map"):
        load_uncertainty(tmp_path)
    # a sigma file whose determined value is NaN (the mask says determined)
    j.write_text(json.dumps(doc))
    sigma2 = {k: v.copy() for k, v in sigma.items()}
    und2 = {k: v.copy() for k, v in und.items()}
    save_uncertainty(tmp_path, sigma2, und2)
    import OpenImageIO as oiio

    from dualscale.formats.exr import write_pixels

    p = tmp_path / "uncertainty" / "roughness.exr"
    inp = oiio.ImageInput.open(str(p))
    spec = inp.spec()
    a = np.asarray(inp.read_image(0, 0, 0, 1, "half")).reshape(9, 7, 1).copy()
    inp.close()
    k = np.argwhere(~und2["roughness"][..., 0])[0]
    a[k[0], k[1], 0] = np.nan
    write_pixels(p, a, spec)
    with pytest.raises(FormatError, match="roughness.exr is not the file uncertainty.json was written with"):
        load_uncertainty(tmp_path)
    from dualscale.formats.run import file_sha256

    doc = json.loads(j.read_text())  # a record that agrees with the damaged file: its pixels are checked too
    doc["files_sha256"]["roughness.exr"] = file_sha256(p)
    j.write_text(json.dumps(doc))
    with pytest.raises(FormatError, match="determined values are negative or not finite"):
        load_uncertainty(tmp_path)


def test_a_sigma_file_from_another_fit_or_a_map_in_its_place_is_refused(tmp_path):
    """Each sigma file must be the one its uncertainty.json was written with (``files_sha256``):
    another fit's sigma copied over, or a file of the right shape and channels that is not a
    sigma at all, is refused naming the file; a missing listed file too."""
    a, b = tmp_path / "a", tmp_path / "b"
    save_uncertainty(a, *_set(seed=0))
    save_uncertainty(b, *_set(seed=1))
    load_uncertainty(a)
    (a / "uncertainty" / "roughness.exr").write_bytes((b / "uncertainty" / "roughness.exr").read_bytes())
    with pytest.raises(FormatError, match="roughness.exr is not the file"):
        load_uncertainty(a)
    save_uncertainty(a, *_set(seed=0))
    from dualscale.formats.exr import write_exr

    write_exr(a / "uncertainty" / "normal.exr", np.full((9, 7, 1), 0.5, np.float32), ("Y",))  # a map, not a sigma
    with pytest.raises(FormatError, match="normal.exr is not the file"):
        load_uncertainty(a)
    save_uncertainty(a, *_set(seed=0))
    (a / "uncertainty" / "undetermined.exr").unlink()
    with pytest.raises(FileNotFoundError, match="undetermined.exr"):
        load_uncertainty(a)


# --------------------------------------------------------------------------- UncertaintyWriter (by rows)

def _bytes(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_the_writer_by_strips_writes_the_bytes_of_save_uncertainty(tmp_path):
    from dualscale.formats.maps import UncertaintyWriter

    sigma, und = _set(11, 5, seed=3)
    save_uncertainty(tmp_path / "whole", sigma, und, meta={"noise": "x"})
    with UncertaintyWriter(tmp_path / "rows", list(sigma), 11, 5, meta={"noise": "x"}) as out:
        for y0, y1 in ((0, 4), (4, 5), (5, 11)):
            out.write(y0, {k: v[y0:y1] for k, v in sigma.items()}, {k: v[y0:y1] for k, v in und.items()})
    assert _bytes(tmp_path / "rows" / "uncertainty") == _bytes(tmp_path / "whole" / "uncertainty")
    s2, u2, _ = load_uncertainty(tmp_path / "rows")
    for k in sigma:
        assert np.array_equal(u2[k], und[k]) and np.isnan(s2[k][und[k]]).all(), k


@pytest.mark.parametrize("how", ["interrupt", "error", "short"])
def test_an_interrupted_write_leaves_no_new_file(tmp_path, how):
    from dualscale.formats.maps import UncertaintyWriter

    sigma, und = _set()
    save_uncertainty(tmp_path, {"albedo": sigma["albedo"]}, {"albedo": und["albedo"]})
    folder = tmp_path / "uncertainty"
    before = _bytes(folder)
    exc = {"interrupt": KeyboardInterrupt, "error": RuntimeError, "short": ValueError}[how]
    with pytest.raises(exc):
        with UncertaintyWriter(tmp_path, list(sigma), 9, 7) as out:
            out.write(0, {k: v[:4] for k, v in sigma.items()}, {k: v[:4] for k, v in und.items()})
            if how == "interrupt":
                raise KeyboardInterrupt
            if how == "error":
                raise RuntimeError("the fit failed")
    after = _bytes(folder)
    # the earlier record is gone (a half-written set never looks complete), nothing new appeared
    assert "uncertainty.json" not in after
    assert after == {k: v for k, v in before.items() if k != "uncertainty.json"}
    with pytest.raises(FileNotFoundError):
        load_uncertainty(tmp_path)


def test_the_writer_refuses_rows_out_of_order_and_bad_strips(tmp_path):
    from dualscale.formats.maps import UncertaintyWriter

    sigma, und = _set()
    strip = lambda d, a, b: {k: v[a:b] for k, v in d.items()}  # noqa: E731
    with pytest.raises(ValueError, match="in order"):
        with UncertaintyWriter(tmp_path, list(sigma), 9, 7) as out:
            out.write(0, strip(sigma, 0, 3), strip(und, 0, 3))
            out.write(5, strip(sigma, 5, 9), strip(und, 5, 9))
    bad = {k: v.copy() for k, v in sigma.items()}
    bad["roughness"][6, 2, 0], und["roughness"][6, 2, 0] = -0.5, False
    with pytest.raises(ValueError, match=r"'roughness'.*rows 3\.\.8"):
        with UncertaintyWriter(tmp_path, list(sigma), 9, 7) as out:
            out.write(0, strip(sigma, 0, 3), strip(und, 0, 3))
            out.write(3, strip(bad, 3, 9), strip(und, 3, 9))
    with pytest.raises(ValueError, match="'albedo'"):
        with UncertaintyWriter(tmp_path, list(sigma), 9, 7) as out:
            out.write(0, {**strip(sigma, 0, 3), "albedo": sigma["albedo"][:3, :, :1]}, strip(und, 0, 3))
    with pytest.raises(ValueError, match="expected"):
        with UncertaintyWriter(tmp_path, list(sigma), 9, 7) as out:
            out.write(0, {"albedo": sigma["albedo"]}, {"albedo": und["albedo"]})
    with pytest.raises(ValueError, match="unknown"):
        UncertaintyWriter(tmp_path, ["sheen"], 9, 7)
    assert not (tmp_path / "uncertainty" / "uncertainty.json").exists()
    assert sorted(p.name for p in (tmp_path / "uncertainty").iterdir()) == []
