"""Random-noise datasets (issue 24 trial): a tiny synthetic dataset whose EXR pixels are replaced by
random values, uniform within ±30 % of a mean: the dataset's (``per_image=False``: the level
ignores the light too) or each image's own (the trial's ``noise2``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _read(path: Path):
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    img = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, spec.format)).reshape(spec.height, spec.width,
                                                                                   spec.nchannels)
    inp.close()
    return img, spec


def make_noise_dataset(root: Path, *, size: int = 16, per_image: bool = False, spread: float = 0.3,
                       seed: int = 2) -> Path:
    """``dualscale synth twill -o root --dataset`` (``size`` texels, every 4th LED), then every
    image of ``root/micro/images`` replaced by noise (module doc); returns the dataset folder."""
    from dualscale.cli import main
    from dualscale.formats.exr import write_pixels

    assert main(["synth", "twill", "-o", str(root), "--size", str(size), "--texel-um", "9", "--dataset", "--lights",
                 "mod4", "--no-previews", "--no-progress", "--threads", "1"]) == 0
    ds = root / "micro"
    files = sorted((ds / "images").glob("*.exr"))
    assert files
    level = float(np.mean([_read(p)[0].mean() for p in files]))
    rng = np.random.default_rng(seed)
    for p in files:
        img, spec = _read(p)
        m = float(img.mean()) if per_image else level
        write_pixels(p, (m * (1 + rng.uniform(-spread, spread, img.shape))).astype(img.dtype), spec)
    return ds
