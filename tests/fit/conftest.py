from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)  # tiny maps: a second thread only adds OpenMP spin on a shared machine


def synth(root: Path, material: str, size: int = 16, texel_um: float = 9.0, extra: tuple[str, ...] = ()) -> Path:
    from dualscale.cli import main

    rc = main(["synth", material, "-o", str(root), "--size", str(size), "--texel-um", str(texel_um), "--dataset",
               "--no-previews", *extra])
    assert rc == 0
    return root


@pytest.fixture(scope="session")
def datasets(tmp_path_factory):
    """Small synthetic datasets (16 x 16 texels of 9 um, all 127 LEDs x P0/P90), made lazily."""
    base = tmp_path_factory.mktemp("fitdata")
    cache: dict[str, Path] = {}

    def get(material: str, size: int = 16) -> Path:
        key = f"{material}{size}"
        if key not in cache:
            cache[key] = synth(base / key, material, size)
        return cache[key]

    return get
