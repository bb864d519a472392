"""Synthetic photograph sets for the photo workflow's tests: a mirror sphere (for ``lights
sphere``) and a diffuse (optionally glossy) sphere on black (for ``import`` and the fit), under
a dozen lights on one side, written as 8-bit sRGB PNGs with a mask and a ``.lp`` file."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
PSM = ROOT.parent / "shared" / "data" / "psm-12lights"


def lights_one_side(n: int = 12, seed: int = 0) -> np.ndarray:
    """``n`` unit directions at 45-80 deg elevation, azimuths spread over 200 deg (one side of
    the object, like the psm-12lights rig)."""
    rng = np.random.default_rng(seed)
    el = np.radians(rng.uniform(45, 80, n))
    az = np.radians(np.linspace(-10, 190, n) + rng.uniform(-5, 5, n))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)


def write_png(path: Path, img: np.ndarray) -> None:
    """Write a uint8 or uint16 ``(H, W)`` / ``(H, W, C)`` array as PNG (OpenImageIO)."""
    import OpenImageIO as oiio

    a = np.ascontiguousarray(img if img.ndim == 3 else img[..., None])
    buf = oiio.ImageBuf(a)
    assert buf.write(str(path)), buf.geterror()


def srgb8(linear: np.ndarray) -> np.ndarray:
    v = np.clip(linear, 0.0, 1.0)
    e = np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)
    return np.round(e * 255).astype(np.uint8)


@dataclass
class SphereSet:
    """A rendered set: ``folder`` with ``ball.<k>.png`` and ``ball.mask.png``, ``lp`` the light
    file, ``dirs`` ``(N, 3)``, ``normal`` ``(H, W, 3)`` truth, ``mask`` ``(H, W)``, ``linear``
    ``(N, H, W, 3)`` the linear images before encoding."""

    folder: Path
    lp: Path
    dirs: np.ndarray
    normal: np.ndarray
    mask: np.ndarray
    linear: np.ndarray


def render_sphere(folder: Path, dirs: np.ndarray, size: int = 40, albedo=(0.6, 0.45, 0.3), gain: float = 2.5,
                  roughness: float | None = None, ior: float = 1.5, name: str = "ball") -> SphereSet:
    """A sphere filling most of a ``size`` x ``size`` frame: diffuse (the package's BSDF with an
    IOR of 1) or, with ``roughness``, diffuse + an isotropic GGX lobe (unpolarised light), under
    ``dirs``; ``gain`` scales radiance into 8-bit range (the unknown exposure).  Writes the
    PNGs, the mask and ``lights.lp`` (names ``<name>.<k>.png``)."""
    from dualscale.bsdf import Components, MaterialMaps, evaluate, map_from_ior

    folder.mkdir(parents=True, exist_ok=True)
    c = (size - 1) / 2
    r = 0.42 * size
    yy, xx = np.mgrid[:size, :size]
    nx, ny = (xx - c) / r, (c - yy) / r
    rho2 = nx * nx + ny * ny
    mask = rho2 < 0.95 ** 2
    nz = np.sqrt(np.clip(1 - rho2, 0, 1))
    normal = np.where(mask[..., None], np.stack([nx, ny, nz], -1), np.array([0.0, 0.0, 1.0]))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    t = lambda a: torch.tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    ones = torch.ones(size, size, 1, dtype=torch.float64)
    spec = roughness is not None
    maps = MaterialMaps(albedo=t(albedo).expand(size, size, 3).clone(), roughness=ones * (roughness or 0.5),
                        normal=t(normal), ior=ones * float(map_from_ior(ior if spec else 1.0)))
    comps = Components(opaque=True, isotropic=True, tinted=False, normal_mapped=True, ior_mapped=True)
    f = evaluate(maps, t(dirs), t([0.0, 0.0, 1.0]), comps, w_s=0.5, w_p=0.5).numpy()
    lin = gain * f * mask[None, ..., None]
    for k, img in enumerate(lin):
        write_png(folder / f"{name}.{k}.png", srgb8(img))
    write_png(folder / f"{name}.mask.png", (mask * 255).astype(np.uint8))
    lp = folder.parent / f"{folder.name}.lp"
    lp.write_text(f"{len(dirs)}\n" + "".join(f"{name}.{k}.png {d[0]:.9f} {d[1]:.9f} {d[2]:.9f}\n"
                                              for k, d in enumerate(dirs)))
    return SphereSet(folder, lp, np.asarray(dirs), normal, mask, lin)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


def nothing_written(out: Path) -> bool:
    """``out`` does not exist and no temporary folder was left beside it."""
    return not out.exists() and not any(p.name.startswith(".tmp-") for p in out.parent.iterdir())


def no_tmp(parent: Path) -> bool:
    return not any(p.name.startswith(".tmp") for p in parent.rglob("*"))


def skip_without_psm():
    if not (PSM / "chrome").is_dir():
        pytest.skip(f"real photographs absent: {PSM} (../shared/data is not part of a user's clone)")

