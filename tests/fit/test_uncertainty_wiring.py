"""fit_observations(uncertainty=True) -> FitResult.uncertainty -> save_fit writes MAPS/uncertainty/
and fit.json's summary (issue 26); without it, no uncertainty record is left beside the maps."""

from __future__ import annotations

import json

import numpy as np

from dualscale.fit.core import fit_observations
from dualscale.fit.io import save_fit
from dualscale.fit.observations import load_observations
from dualscale.fit.params import fit_components
from dualscale.fit.presets import PRESETS
from dualscale.formats.maps import load_uncertainty


def test_a_fit_writes_its_uncertainty_and_summary(datasets, tmp_path):
    obs = load_observations(datasets("twill")).crop(0, 4, 0, 4)
    comps = fit_components(opaque=True, isotropic=False, tinted=True)
    res = fit_observations(obs, PRESETS["standard"].scaled(0.3), comps, uncertainty=True)
    u = res.uncertainty
    assert u is not None and set(u.sigma) == {"albedo", "normal", "roughness", "anisotropy", "tangent", "ior",
                                              "specular_tint"}
    for n, s in u.sigma.items():
        assert s.shape[:2] == (4, 4) and bool(torch_isnan_matches(s, u.undetermined[n]))
    save_fit(tmp_path / "m", res, previews=False)
    sigma, und, doc = load_uncertainty(tmp_path / "m")
    np.testing.assert_allclose(sigma["roughness"], u.sigma["roughness"].numpy(), rtol=1e-3, atol=1e-7,
                               equal_nan=True)  # half float: no sigma below its 6e-8 subnormal step
    rec = json.loads((tmp_path / "m" / "fit.json").read_text())["uncertainty"]
    assert rec["noise"] == u.noise and rec["maps"]["albedo"]["channels"] == ["R", "G", "B"]
    assert 0.0 <= rec["maps"]["tangent"]["undetermined_fraction"][0] <= 1.0
    res2 = fit_observations(obs, PRESETS["standard"].scaled(0.3), comps)  # uncertainty off: the record goes
    assert res2.uncertainty is None
    save_fit(tmp_path / "m", res2, previews=False)
    assert not (tmp_path / "m" / "uncertainty" / "uncertainty.json").exists()
    assert "uncertainty" not in json.loads((tmp_path / "m" / "fit.json").read_text())


def torch_isnan_matches(s, und) -> bool:
    """NaN exactly where undetermined."""
    import torch

    return bool(torch.equal(torch.isnan(s), und))
