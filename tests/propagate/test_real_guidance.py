"""Real guidance photographs (../shared/data/fabric-rt: 8-bit sRGB reflection and transmission
photos of woven fabrics, 512^2) through `dualscale propagate run --transfer srgb`, with the
shipped warm-start model.

Plausible maps, as tested here (the fabrics have no ground truth):
* finite, and every map inside its convention's range (load_maps refuses non-unit normals and
  normals with z < 0);
* the albedo follows the guidance: Pearson correlation of their luminances > 0.5;
* the weave repeat carries over: the guidance's strongest spectral peak (beyond 8 cycles per
  image) stands out in the albedo's spectrum too, >= 20x the median power at that radius;
* no tile seams: tiled with blending (256 px tiles, 64 px overlap), the largest row/column step
  near a tile edge is at most half that of naive tiling (no overlap) for albedo and roughness,
  3/4 for normals (see docs/PROPAGATION.md: per-tile GroupNorm statistics make this model's
  normals depend on the tile on photos lit unevenly).
"""

from pathlib import Path

import numpy as np

from dualscale.propagate.metrics import seam_score
import pytest

from dualscale.cli import main

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "fabric-rt"
from dualscale.propagate.train import WARM_START as WARM
PHOTOS = sorted(p.name for p in DATA.glob("*.png")) if DATA.is_dir() else []
pytestmark = pytest.mark.skipif(not PHOTOS, reason=f"real fabric photos not found at {DATA} (shared data absent)")

RANGES = {"albedo": (0, 1), "roughness": (0, 1), "anisotropy": (0, 1), "tangent": (0, 1), "ior": (0, 1),
          "specular_tint": (0, 1), "normal": (-1, 1)}


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    m = tmp_path_factory.mktemp("warm") / "warm.dsp"
    m.write_bytes(WARM.read_bytes())  # ONNX is exported next to the model: keep the package clean
    return m


def _spectrum(x: np.ndarray) -> np.ndarray:
    n = x.shape[0]
    w = np.hanning(n)[:, None] * np.hanning(n)[None]
    return np.abs(np.fft.fftshift(np.fft.fft2((x - x.mean()) * w))) ** 2


@pytest.mark.parametrize("photo", PHOTOS or ["none"])
def test_real_photo_gives_plausible_maps(model, photo, tmp_path):
    from dualscale.formats.maps import load_maps
    from dualscale.propagate.guidance import LUMA, read_guidance

    out = tmp_path / "maps"
    assert main(["propagate", "run", str(model), str(DATA / photo), "--transfer", "srgb", "-o", str(out),
                 "--threads", "1", "--no-progress"]) == 0
    maps, meta = load_maps(out)  # refuses non-finite values and bad normals
    assert maps.shape == (512, 512) and meta["propagate"]["transfer"] == "srgb"
    for name, t in maps.items():
        lo, hi = RANGES[name]
        assert float(t.min()) >= lo and float(t.max()) <= hi, name
    lum = read_guidance(DATA / photo, "srgb").luminance()
    alb = maps.albedo.numpy() @ LUMA
    assert np.corrcoef(lum.ravel(), alb.ravel())[0, 1] > 0.5
    pg, pa = _spectrum(lum), _spectrum(alb)
    fy, fx = np.mgrid[-256:256, -256:256]
    r = np.hypot(fx, fy)
    pg[r < 8] = 0
    y, x = np.unravel_index(np.argmax(pg), pg.shape)
    ring = np.abs(r - r[y, x]) < 2
    assert pa[y - 1:y + 2, x - 1:x + 2].max() >= 20 * np.median(pa[ring]), "the weave repeat is lost"


@pytest.mark.parametrize("photo", [p for p in PHOTOS if p == "satin1_T.png"] or ["none"])
def test_real_photo_tiles_without_seams(model, photo):
    from dualscale.propagate.export import export_model, onnx_paths
    from dualscale.propagate.guidance import read_guidance
    from dualscale.propagate.infer import OnnxModel, exposure_gain, propagate_image

    export_model(model, check=False)
    om = OnnxModel.open(onnx_paths(model)[0], 1)
    g = read_guidance(DATA / photo, "srgb")
    gain = exposure_gain(om, g.luminance())
    naive, _ = propagate_image(om, g.rgb, 256, 0, gain, progress=False)
    blended, _ = propagate_image(om, g.rgb, 256, 64, gain, progress=False)
    for name, limit in (("albedo", 0.5), ("roughness", 0.5), ("normal", 0.75)):
        b, n = seam_score(blended[name], 256, 64), seam_score(naive[name], 256, 0)
        assert b <= limit * n, (name, b, n)
