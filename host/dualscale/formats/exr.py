"""Image I/O through OpenImageIO: float EXR (data) and 8-bit sRGB PNG (previews only).

Every write is atomic (:mod:`.atomic`) and checked whole before it takes its name
(:func:`verify_image`; a full disk is :class:`~dualscale.errors.OutputError`).  :func:`read_exr` refuses images whose data window is
not the display window at the origin (``oiiotool --origin`` / ``--crop`` shifted or cropped
files), since a shifted image would be fitted misaligned; pass ``allow_window=True`` only where
the caller handles the offset itself."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from dualscale.errors import FormatError, GeometryError

from .atomic import atomic_path

_DEFAULT_NAMES = {1: ("Y",), 2: ("X", "Y"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


def write_exr(path: str | Path, image: np.ndarray, channels: Sequence[str] | None = None,
              attributes: dict[str, str] | None = None, tile: int | None = None) -> None:
    """Write ``(H, W)`` or ``(H, W, C)`` float data as a float32 EXR (zip compression).

    ``tile``: ``None`` (default) writes a scanline file; a positive pixel count writes a tiled
    file of ``tile`` x ``tile`` tiles (the last row and column of tiles cut short by the image
    edge), whose regions :func:`read_exr` ``box=`` reads tile by tile (docs/APPEARANCE.md,
    "Image layout").  Both layouts hold the same float32 values and read the same through
    :func:`read_exr` and any OpenEXR reader.  ``ValueError`` for a bad shape, channel names or
    ``tile`` (not a whole number >= 1)."""
    import OpenImageIO as oiio

    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3:
        raise ValueError(f"image must be (H, W) or (H, W, C), got {img.shape}")
    names = tuple(channels) if channels is not None else _DEFAULT_NAMES.get(img.shape[2])
    if names is None or len(names) != img.shape[2]:
        raise ValueError(f"need {img.shape[2]} channel names, got {names}")
    spec = oiio.ImageSpec(img.shape[1], img.shape[0], img.shape[2], "float")
    spec.channelnames = names
    spec.attribute("compression", "zip")
    if tile is not None:
        if isinstance(tile, bool) or not isinstance(tile, (int, np.integer)) or tile < 1:
            raise ValueError(f"tile must be a whole number of pixels >= 1 or None, got {tile!r}")
        spec.tile_width = spec.tile_height = int(tile)
        spec.tile_depth = 1
    # no write time in the file (OpenImageIO adds one by default): the same pixels give the same
    # bytes, so a recomputed, unchanged stage output keeps the content hash the next stage keys on
    spec.attribute("DateTime", "")
    for k, v in (attributes or {}).items():
        spec.attribute(k, str(v))
    write_pixels(path, img, spec)


def write_pixels(path: str | Path, pixels: np.ndarray, spec) -> Path:
    """Write ``pixels`` ``(H, W, C)`` (dtype matching ``spec.format``) with the OpenImageIO
    ``ImageSpec`` ``spec`` (its attributes: compression, colour space, ...), atomically; the file
    type follows the suffix.  The written file is checked (:func:`verify_image`) and flushed
    before it takes its name.  Raises :class:`~dualscale.errors.OutputError` (exit 4) when the
    disk is full, the file-size limit is reached or the file reads back short (OpenImageIO
    reports success for a PNG that a full disk truncated); ``OSError`` naming the file when
    OpenImageIO refuses for another reason.  Nothing is left under ``path`` by a failed write."""
    import OpenImageIO as oiio

    with atomic_path(path, verify=lambda tmp: verify_image(tmp, spec, path)) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise OSError(f"cannot write {path}: {oiio.geterror()}")
        try:
            if not out.write_image(np.ascontiguousarray(pixels)):
                raise OSError(f"cannot write {path}: {out.geterror()}")
        finally:
            closed = out.close()  # the last buffered bytes go out here: a full disk can show only now
        if not closed:
            raise OSError(f"cannot write {path}: {out.geterror() or 'closing the file failed'}")
    return Path(path)


_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # PNG's last chunk: IEND, no data, its CRC


def verify_image(tmp: str | Path, spec, final: str | Path | None = None) -> None:
    """Check that the image file ``tmp`` that a writer just closed is whole: it re-opens with
    ``spec``'s width, height, channel count and pixel type, and its pixels read back -- all of
    them (a PNG also ends in its ``IEND`` chunk, the 12 bytes a truncated PNG loses first and
    that a reader does not miss), or, for an EXR (whose chunks are written in order, so a short
    file lacks the last), the last scanline, or a tiled one's last (bottom-right) tile.  Raises
    :class:`~dualscale.errors.OutputError` naming ``final`` (default ``tmp``) with the cause
    (:func:`dualscale.formats.atomic.output_error`; ``EIO`` when neither a full disk nor the
    file-size limit explains it)."""
    import OpenImageIO as oiio

    from .atomic import output_error

    tmp = Path(tmp)
    final = Path(final) if final is not None else tmp

    def fail(why: str):
        raise output_error(final, why, tmp, short=True)

    size = tmp.stat().st_size
    if size == 0:
        fail("the writer reported success but the file is empty")
    if tmp.suffix.lower() == ".png":
        with open(tmp, "rb") as f:
            f.seek(max(0, size - len(_PNG_END)))
            if f.read() != _PNG_END:
                fail(f"the PNG is truncated at {size} bytes (no IEND chunk)")
    inp = oiio.ImageInput.open(str(tmp))
    if inp is None:
        fail(f"the written file does not re-open ({_oiio_error(oiio.geterror())})")
    try:
        got = inp.spec()
        want = (spec.width, spec.height, spec.nchannels, str(spec.format))
        have = (got.width, got.height, got.nchannels, str(got.format))
        if have != want:
            fail(f"the written file re-opens as {have[0]}x{have[1]}x{have[2]} {have[3]}, "
                 f"not {want[0]}x{want[1]}x{want[2]} {want[3]}")
        if tmp.suffix.lower() == ".exr" and got.tile_width == 0:
            data = inp.read_scanlines(0, 0, got.y + got.height - 1, got.y + got.height, 0, 0, got.nchannels,
                                      got.format)
        elif tmp.suffix.lower() == ".exr" and got.tile_width > 0 and got.tile_height > 0:
            # a tiled EXR written in increasing-y order: its last chunk is the bottom-right tile
            tx = got.x + (got.width - 1) // got.tile_width * got.tile_width
            ty = got.y + (got.height - 1) // got.tile_height * got.tile_height
            data = inp.read_tile(tx, ty, got.z, got.format)
        else:
            data = inp.read_image(0, 0, 0, got.nchannels, got.format)
        if data is None:
            fail(f"the written file's pixels do not read back ({_oiio_error(inp.geterror())})")
    finally:
        inp.close()


def open_image(path: str | Path):
    """An OpenImageIO ``ImageInput`` for ``path`` (close it); ``FileNotFoundError`` when missing,
    :class:`~dualscale.errors.FormatError` when it is not a readable image, naming the file."""
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    try:
        inp = oiio.ImageInput.open(str(path))
    except OSError as e:  # a file the process may not read: the permission is the user's to fix
        raise FormatError(f"cannot read the image {path}: {e.strerror or e}") from None
    if inp is None:
        raise FormatError(f"cannot read the image {path}: {_oiio_error(oiio.geterror())}")
    return inp


def _oiio_error(text: str) -> str:
    """OpenImageIO's error text, its first line (it may repeat the file name in several)."""
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    return lines[0][:300] if lines else "not a readable image"


def read_exr(path: str | Path, channels: Sequence[str] | None = None, allow_window: bool = False,
             box: tuple[int, int, int, int] | None = None, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image as float32 ``(H, W, C)``; ``channels`` selects by name (EXR reorders them).

    ``box`` ``(y0, y1, x0, x1)`` (pixels, end exclusive, relative to the data window's origin):
    read only that region, ``(y1 - y0, x1 - x0, C)``, always the same values as the whole
    image's crop ``[y0:y1, x0:x1]``.  A scanline file is read by its scanlines ``y0..y1`` at full
    width (OpenImageIO's ``read_scanlines``, which decodes only the chunks holding them), then
    cut to the columns; a tiled file (:func:`write_exr` ``tile=``) by the tiles the box touches
    (``read_tiles`` on the box aligned outward to the tile grid, cut short at the image edge),
    then cut to the box -- so a square tile of a fit decodes about its own pixels, not whole
    rows.  ``size`` ``(H, W)``: the size the whole image must have (``ValueError`` otherwise),
    checked before a region is read.

    Raises :class:`~dualscale.errors.GeometryError` when the data window is not the display
    window with its origin at (0, 0) (unless ``allow_window``), ``FileNotFoundError`` for a
    missing file, :class:`~dualscale.errors.FormatError` for one that is not a readable image
    (corrupt, truncated) or that is a volume (depth > 1), ``ValueError`` for a missing channel or
    a ``box`` outside the image."""
    inp = open_image(path)
    try:
        spec = inp.spec()
        if not allow_window:
            check_window(path, spec)
        if spec.depth > 1:
            raise FormatError(f"{path}: a volume image (depth {spec.depth}); dualscale reads 2-D images only")
        if size is not None and (spec.height, spec.width) != tuple(size):
            raise ValueError(f"{Path(path).name}: image is {(spec.height, spec.width)}, expected {tuple(size)}")
        crop = None
        if box is None:
            data = inp.read_image(0, 0, 0, spec.nchannels, "float")
            shape = (spec.height, spec.width, spec.nchannels)
        else:
            y0, y1, x0, x1 = (int(v) for v in box)
            if not (0 <= y0 < y1 <= spec.height and 0 <= x0 < x1 <= spec.width):
                raise ValueError(f"{path}: region rows {y0}..{y1}, columns {x0}..{x1} is outside the "
                                 f"{spec.width}x{spec.height} image")
            tw, th = spec.tile_width, spec.tile_height
            if tw > 0 and th > 0:
                # read_tiles wants tile-aligned bounds (the image edge may end a tile short)
                ty0, tx0 = y0 // th * th, x0 // tw * tw
                ty1, tx1 = min(-(-y1 // th) * th, spec.height), min(-(-x1 // tw) * tw, spec.width)
                data = inp.read_tiles(0, 0, spec.x + tx0, spec.x + tx1, spec.y + ty0, spec.y + ty1,
                                      spec.z, spec.z + 1, 0, spec.nchannels, "float")
                shape = (ty1 - ty0, tx1 - tx0, spec.nchannels)
                crop = (y0 - ty0, y1 - ty0, x0 - tx0, x1 - tx0)
            else:
                data = inp.read_scanlines(0, 0, spec.y + y0, spec.y + y1, 0, 0, spec.nchannels, "float")
                shape = (y1 - y0, spec.width, spec.nchannels)
                crop = (0, y1 - y0, x0, x1)
        err = inp.geterror() if data is None else ""
    finally:
        inp.close()
    if data is None:
        raise FormatError(f"cannot read the pixels of the image {path} (corrupt or truncated?): {_oiio_error(err)}")
    data = np.asarray(data, dtype=np.float32).reshape(shape)
    if crop is not None and (crop[0], crop[1], crop[2], crop[3]) != (0, shape[0], 0, shape[1]):
        data = np.ascontiguousarray(data[crop[0]:crop[1], crop[2]:crop[3]])
    if channels is None:
        return data
    idx = []
    for c in channels:
        i = spec.channelindex(c)
        if i < 0:
            raise ValueError(f"{path}: no channel {c!r} (has {list(spec.channelnames)})")
        idx.append(i)
    return data[..., idx]


def check_window(path: str | Path, spec) -> None:
    """Refuse an image whose data window is shifted or differs from its display window."""
    data = (spec.x, spec.y, spec.width, spec.height)
    full = (spec.full_x, spec.full_y, spec.full_width, spec.full_height)
    if data != full or spec.x != 0 or spec.y != 0:
        raise GeometryError(
            f"{path}: data window origin ({spec.x}, {spec.y}) size {spec.width}x{spec.height} differs from the "
            f"display window origin ({spec.full_x}, {spec.full_y}) size {spec.full_width}x{spec.full_height}; "
            "dualscale reads only images whose pixels start at (0, 0) and fill the display window "
            "(reset with: oiiotool IN --origin +0+0 --fullpixels -o OUT, after checking the alignment)")


def read_exr_attributes(path: str | Path, prefix: str = "dualscale:") -> dict[str, str]:
    """The header attributes named ``prefix...`` (as :func:`write_exr` writes them), keyed
    without the prefix."""
    inp = open_image(path)
    try:
        return {a.name[len(prefix):]: str(a.value) for a in inp.spec().extra_attribs if a.name.startswith(prefix)}
    finally:
        inp.close()


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer function on [0, 1]-clipped linear values."""
    x = np.clip(np.nan_to_num(linear), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def write_png_preview(path: str | Path, image: np.ndarray, srgb: bool = True, exposure: float = 1.0) -> None:
    """8-bit preview; ``srgb=True`` applies the sRGB curve (use it for linear radiance/albedo)."""
    import OpenImageIO as oiio

    img = np.asarray(image, dtype=np.float64) * exposure
    if img.ndim == 2:
        img = img[..., None]
    if img.shape[2] == 2:
        img = np.concatenate([img, np.zeros_like(img[..., :1])], -1)
    img = srgb_encode(img) if srgb else np.clip(img, 0, 1)
    u8 = np.ascontiguousarray(np.round(img * 255).astype(np.uint8))
    write_pixels(path, u8, oiio.ImageSpec(u8.shape[1], u8.shape[0], u8.shape[2], "uint8"))
