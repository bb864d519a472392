"""Photographs from other rigs and ordinary cameras: PNG, JPEG, TIFF (8 or 16 bit) and EXR,
read through OpenImageIO and linearised through colour-science.

Integer images are display-encoded: their transfer function is never guessed.  The caller
states it (``transfer``), one of :data:`TRANSFERS`:

* ``"srgb"`` -- IEC 61966-2-1 (``colour.cctf_decoding(..., function="sRGB")``);
* ``"linear"`` -- code values proportional to radiance (raw-developed linear TIFFs);
* ``"gamma:G"`` -- a pure power law ``V = L ** (1 / G)`` (e.g. ``gamma:2.2``).

EXR files hold linear values already and must be read with ``transfer="linear"`` (anything else
is refused).  The result is linear RGB on Rec.709/sRGB primaries (the primaries are assumed, as
no camera profile is given), float32 ``(H, W, 3)`` in [0, 1] for integer inputs, plus a boolean
``(H, W)`` mask of *clipped* pixels (any channel at the top code value, or above ``clip`` for
float inputs), which no stage fits as valid.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from dualscale.errors import FormatError, GeometryError, UnitsError

from .exr import check_window
from .response import TRANSFERS, Response, parse_transfer  # noqa: F401  (parse_transfer, TRANSFERS: re-exported)

SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr")


@dataclass(frozen=True)
class Photo:
    """A linearised photograph: ``rgb`` float32 ``(H, W, 3)``, ``clipped`` bool ``(H, W)``,
    ``bits`` (8, 16, or 32 for float), ``transfer`` as stated."""

    rgb: np.ndarray
    clipped: np.ndarray
    bits: int
    transfer: str


def decode(code: np.ndarray, transfer: str) -> np.ndarray:
    """Normalised code values in [0, 1] to linear values, by the stated ``transfer``."""
    kind, g = parse_transfer(transfer)
    x = np.clip(np.asarray(code, np.float64), 0.0, 1.0)
    if kind == "linear":
        return x
    if kind == "gamma":
        return x ** g
    import colour

    return np.asarray(colour.cctf_decoding(x, function="sRGB"), np.float64)


@dataclass(frozen=True)
class Codes:
    """A photograph's code values before decoding: ``code`` float32 ``(H, W, 3)`` normalised to
    [0, 1] (integer images) or linear values (float images), ``clipped`` bool ``(H, W)``,
    ``bits`` (8, 16, or 32 for float)."""

    code: np.ndarray
    clipped: np.ndarray
    bits: int


_FD2_LOCK = threading.Lock()


@contextlib.contextmanager
def library_stderr() -> Iterator[list[str]]:
    """Keep what the image libraries print to the process's stderr (libpng's ``libpng error:
    IDAT: ...`` on a truncated PNG: OpenImageIO lets it print) out of the terminal: file
    descriptor 2 goes to a temporary file for the block; the text is appended to the yielded
    list on the way out, for the caller to fold into its error.  Text left unclaimed by an error
    is for the caller to pass on (:func:`_pass_on`).  One block at a time (fd 2 is the process's)."""
    out: list[str] = []
    with _FD2_LOCK:
        try:
            sys.stderr.flush()
        except (AttributeError, OSError, ValueError):
            pass
        try:
            saved = os.dup(2)
        except OSError:  # no fd 2 to redirect: nothing can reach a terminal
            yield out
            return
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield out
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                tmp.seek(0)
                out.append(tmp.read().decode("utf-8", "replace").strip())


def _pass_on(text: list[str]) -> None:
    """Print, after all, what a block of :func:`library_stderr` caught when no error took it."""
    msg = "\n".join(t for t in text if t)
    if msg:
        print(msg, file=sys.stderr)


def _detail(*texts: str) -> str:
    """Error texts joined, each distinct line once (libpng's line repeats OpenImageIO's)."""
    lines: list[str] = []
    for t in texts:
        for ln in (t or "").splitlines():
            ln = ln.strip()
            bare = ln.removeprefix("libpng error:").strip()
            if ln and not any(bare in seen for seen in lines):
                lines.append(ln)
    return "; ".join(lines)


def open_unassociated(path: Path):
    """An ``ImageInput`` that reads the colour *as stored*: OpenImageIO associates
    (premultiplies) alpha on read by default, which would darken every pixel of an RGBA or
    grey+alpha photograph by its alpha (``oiio:UnassociatedAlpha`` = 1 keeps it unassociated)."""
    import OpenImageIO as oiio

    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    with library_stderr() as printed:
        inp = oiio.ImageInput.open(str(path), config)
        error = oiio.geterror() if inp is None else ""
    if inp is None:
        raise FormatError(f"{path}: not a readable image ({_detail(error, *printed) or 'unknown format'})")
    _pass_on(printed)
    return inp


def read_codes(path: str | Path, clip: float = 1.0) -> Codes:
    """Read one photograph's code values without decoding them (see :func:`read_photo`; the
    same refusals, but no transfer is needed).  Greyscale is expanded to RGB; an alpha channel
    is ignored and the colour is read as stored, not premultiplied by it."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise UnitsError(f"{path}: unsupported image type {path.suffix!r} (use {', '.join(SUFFIXES)})")
    inp = open_unassociated(path)
    try:
        spec = inp.spec()
        check_window(path, spec)
        fmt = str(spec.format)
        with library_stderr() as printed:  # libpng prints its error besides returning it
            native = inp.read_image(0, 0, 0, spec.nchannels, "float")
            inp_error = inp.geterror() if native is None else ""
    finally:
        inp.close()
    if native is None:
        raise FormatError(f"{path}: cannot read its pixels (truncated or corrupt image: "
                          f"{_detail(inp_error, *printed) or 'no detail'})")
    _pass_on(printed)
    data = np.asarray(native, np.float32).reshape(spec.height, spec.width, spec.nchannels)
    alpha = spec.alpha_channel
    colour_idx = [i for i in range(spec.nchannels) if i != alpha][:3]
    data = data[..., colour_idx]
    if data.shape[-1] == 1:
        data = np.repeat(data, 3, axis=-1)
    elif data.shape[-1] != 3:
        raise UnitsError(f"{path}: {data.shape[-1]} colour channels; need 1 (grey) or 3 (RGB)")
    if fmt in ("half", "float", "double"):
        if not np.isfinite(data).all():
            raise ValueError(f"{path}: {int((~np.isfinite(data)).any(-1).sum())} pixels are NaN or Inf")
        return Codes(data, (data >= clip).any(-1), 32)
    bits = 16 if fmt in ("uint16", "int16") else 8
    return Codes(data, (data >= 1.0 - 0.5 / (2 ** bits - 1)).any(-1), bits)


def decode_codes(codes: Codes, transfer: str | None | Response, where: str = "image") -> Photo:
    """Linearise :func:`read_codes`'s result by ``transfer`` (a stated transfer string, or a
    :class:`~dualscale.formats.response.Response`, e.g. estimated from the photographs);
    float images must be ``linear`` (:class:`UnitsError` otherwise)."""
    if codes.bits == 32:
        name = transfer.transfer if isinstance(transfer, Response) else transfer
        if name is not None and parse_transfer(name)[0] != "linear":
            raise UnitsError(f"{where}: a floating-point image is linear already; use --transfer linear")
        return Photo(codes.code.astype(np.float32), codes.clipped, 32, "linear")
    if isinstance(transfer, Response):
        return Photo(transfer.inverse(codes.code).astype(np.float32), codes.clipped, codes.bits, transfer.transfer)
    rgb = decode(codes.code, transfer)  # type: ignore[arg-type]
    return Photo(rgb.astype(np.float32), codes.clipped, codes.bits, str(transfer))


def read_photo(path: str | Path, transfer: str | None | Response, clip: float = 1.0) -> Photo:
    """Read and linearise one photograph (see the module docstring).

    Greyscale images are expanded to RGB; an alpha channel is ignored.  Raises
    ``FileNotFoundError``, :class:`~dualscale.errors.FormatError` (not a readable image: corrupt, truncated, unknown format), :class:`~dualscale.errors.UnitsError`
    (transfer missing or not applicable), :class:`~dualscale.errors.GeometryError` (a shifted
    data window), ``ValueError`` (non-finite pixels in a float image).
    """
    return decode_codes(read_codes(path, clip), transfer, str(path))


def read_mask(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """A binary mask image (any bit depth; values above half scale are in), not decoded by any
    transfer function; ``shape`` (H, W) must match when given."""
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mask not found: {path}")
    with library_stderr() as printed:
        buf = oiio.ImageBuf(str(path))
        pixels = None if buf.has_error else buf.get_pixels(oiio.FLOAT)
        error = buf.geterror() if buf.has_error or pixels is None else ""
    if error or pixels is None:
        raise FormatError(f"{path}: not a readable mask image ({_detail(error, *printed) or 'no detail'})")
    _pass_on(printed)
    check_window(path, buf.spec())
    arr = np.asarray(pixels, np.float32).reshape(buf.spec().height, buf.spec().width, -1)
    mask = arr[..., 0] > 0.5
    if shape is not None and mask.shape != tuple(shape):
        raise GeometryError(f"{path}: mask is {mask.shape[1]}x{mask.shape[0]}, the images are {shape[1]}x{shape[0]}")
    if not mask.any():
        raise ValueError(f"{path}: the mask is empty")
    return mask
