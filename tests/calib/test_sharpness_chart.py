import numpy as np
import pytest

from dualscale.calib import colourref as cr
from dualscale.calib import evaluate as ev
from dualscale.calib.chart import ChartLayout, detect_chart, sample_patches
from dualscale.errors import ChartNotFoundError
from dualscale.sim.targets import Defects, dot_albedo, dot_grid_truth


def test_sharpness_recovers_injected_blur():
    d = Defects()
    pts, sig = dot_grid_truth(384, 1.8, d)
    img = 0.9 - 0.85 * dot_albedo(384, 1.8, sig)
    xy, vals = ev.sharpness_map(img)
    assert len(xy) == 25
    rec, tru = [], []
    for (x, y), v, p in zip(xy, vals, ev.dot_phases(xy)):
        rec.append(ev.blur_from_sharpness(v, tuple(p)))
        tru.append(sig(np.array(x), np.array(y)))
    rec, tru = np.array(rec), np.array(tru, float)
    rel = np.abs(rec / tru - 1)
    assert rel.mean() < 0.1 and rel.max() < 0.3
    assert np.corrcoef(rec, tru)[0, 1] > 0.9


def test_sharp_dot_beats_blurred():
    a = ev.dot_sharpness(ev.ideal_dot_crop(0.5))
    b = ev.dot_sharpness(ev.ideal_dot_crop(3.0))
    assert 0 < b < a <= 1.0


def _chart_image(n=256):
    lay = ChartLayout()
    xs = (np.arange(n) + 0.5) / n * 100 - 50
    x, y = np.meshgrid(xs, -xs)
    lab = lay.patch_of(x, y)
    img = np.full((n, n, 3), 0.3)
    img[lab == -1] = 0.03
    for k in range(24):
        img[lab == k] = cr.reference_rgb()[k]
    return img


def test_detect_chart_and_orientation():
    img = _chart_image()
    c = detect_chart(img)
    assert np.allclose(sample_patches(img, c), cr.reference_rgb(), atol=1e-9)
    rot = np.rot90(img, 2).copy()  # upside down: orientation must be resolved
    assert np.allclose(sample_patches(rot, detect_chart(rot)), cr.reference_rgb(), atol=1e-9)


def test_chart_not_found():
    with pytest.raises(ChartNotFoundError):
        detect_chart(np.full((128, 128, 3), 0.5))
