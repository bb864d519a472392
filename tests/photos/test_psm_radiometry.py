"""Radiometric self-calibration on real photographs (../shared/data/psm-12lights, skipped when
absent; issue 23): the three figurines were shot by one camera under the same lights, so their
estimates must agree, and the estimated decoding must predict held-out photographs (in code
values, which every decoding is compared on) better than sRGB, which they are not encoded with."""

from __future__ import annotations

import numpy as np
import pytest

from dualscale.calib.response import choose_family, curve_distance, estimate_intensities, estimate_response
from dualscale.cli import main
from dualscale.fit.lambertian import fit_lambertian, render_lambertian
from dualscale.formats.lightfile import read_lights
from dualscale.formats.photo import read_codes, read_mask
from dualscale.formats.response import Response
from photoset import PSM, skip_without_psm

OBJECTS = ("cat", "buddha", "owl")


@pytest.fixture(scope="module")
def psm(tmp_path_factory):
    skip_without_psm()
    out = tmp_path_factory.mktemp("psm") / "lights"
    assert main(["lights", "sphere", str(PSM / "chrome"), "-o", str(out)]) == 0
    dirs = np.array([r.direction for r in read_lights(out.with_name("lights.json"))])
    data = {}
    for name in OBJECTS:
        c = [read_codes(PSM / name / f"{name}.{k}.png") for k in range(12)]
        m = read_mask(PSM / name / f"{name}.mask.png")
        codes = np.stack([x.code[m] for x in c]).astype(np.float64)
        valid = ~np.stack([x.clipped[m] for x in c])
        data[name] = (codes, valid)
    return dirs, data


def test_choose_family_margins():
    assert choose_family({"linear": 1.0, "srgb": 2.0, "gamma": 0.97, "curve": 0.9}) == "linear"
    assert choose_family({"linear": 1.0, "srgb": 2.0, "gamma": 0.9, "curve": 0.86}) == "gamma"
    assert choose_family({"linear": 2.0, "srgb": 2.1, "gamma": 1.0, "curve": 0.5}) == "curve"


def test_one_camera_three_objects_one_response(psm):
    dirs, data = psm
    ests = {n: estimate_response(c, dirs, v, bits=8, bootstrap=0) for n, (c, v) in data.items()}
    ref = ests["cat"].response
    for n, e in ests.items():
        assert e.response.family == ref.family, {k: x.response.describe() for k, x in ests.items()}
        assert curve_distance(e.response, ref, (0.03, 0.98)) <= 0.01, (n, e.response.describe(), ref.describe())
        assert e.score("srgb") > 1.15 * e.score(e.response.family), "sRGB must be clearly less consistent"


def _loo_code_l1(codes, valid, dirs, resp, e, pixels=3000, seed=0):
    """Leave-one-light-out of the Lambertian baseline under ``resp`` and intensities ``e``,
    scored as relative L1 of the held-out *code values* (the prediction re-encoded)."""
    rng = np.random.default_rng(seed)
    sel = rng.choice(codes.shape[1], min(pixels, codes.shape[1]), replace=False)
    C, V = codes[:, sel], valid[:, sel]
    lin = resp.inverse(C) / e[:, None, None]
    errs = []
    for k in range(len(dirs)):
        tr = [j for j in range(len(dirs)) if j != k]
        pred = render_lambertian(fit_lambertian(lin[tr], dirs[tr], V[tr]), dirs[k:k + 1])[0] * e[k]
        v = V[k]
        errs.append(np.abs(resp.forward(np.clip(pred, 0, 1)) - C[k])[v].sum() / C[k][v].sum())
    return float(np.mean(errs))


def test_auto_predicts_held_out_photographs_better_than_srgb(psm):
    dirs, data = psm
    for name, (c, v) in data.items():
        est = estimate_response(c, dirs, v, bits=8, bootstrap=0)
        auto = _loo_code_l1(c, v, dirs, est.response, est.intensities)
        srgb = Response("srgb")
        s = _loo_code_l1(c, v, dirs, srgb, estimate_intensities(srgb, c, dirs, v, 8))
        assert auto < 0.95 * s, (name, auto, s)
