"""PyTorch files (propagation models, fit and training checkpoints): one atomic writer and one
reader whose errors name the file and what is wrong with it.

``torch.save`` writes a zip archive whose members carry CRC-32 checksums.  ``torch.load``
does not verify them (a block of zeros inside a tensor loads silently) and, for a truncated or
emptied file, raises an error about miniz, pickles or ``weights_only``.  :func:`load_torch`
checks the archive first (empty, not a complete archive, a member failing its checksum) and
raises :class:`~dualscale.errors.FormatError` with one line: the file, what it is, what is
wrong, and what to do (``hint``).
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

from dualscale.errors import FormatError

from .atomic import atomic_path


def save_torch(path: str | Path, obj: Any) -> Path:
    """``torch.save(obj)`` to ``path`` atomically (a temporary file, flushed, then renamed)."""
    import torch

    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)
    return path


def check_torch_file(path: str | Path, what: str, hint: str = "") -> None:
    """Refuse a damaged ``torch.save`` archive: ``FileNotFoundError`` when missing,
    :class:`FormatError` (naming ``path``, ``what`` it is, the damage and ``hint``) when empty,
    truncated (no zip central directory) or failing a member's CRC-32."""
    path = Path(path)
    tail = f"; {hint}" if hint else ""
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    size = path.stat().st_size
    if size == 0:
        raise FormatError(f"{path}: damaged {what}: the file is empty (0 bytes: a save that was cut short){tail}")
    try:
        with zipfile.ZipFile(path) as zf:
            bad = zf.testzip()
    except zipfile.BadZipFile:
        raise FormatError(f"{path}: not a {what}, or a damaged one: not a complete PyTorch archive ({size} bytes; "
                          f"truncated or overwritten){tail}") from None
    except (OSError, EOFError, ValueError) as e:
        raise FormatError(f"{path}: damaged {what}: cannot read the archive "
                          f"({type(e).__name__}: {e}){tail}") from None
    if bad is not None:
        raise FormatError(f"{path}: damaged {what}: member {bad!r} fails its checksum (corrupted on disk){tail}")


def load_torch(path: str | Path, what: str, hint: str = "", weights_only: bool = True,
               map_location: str = "cpu") -> Any:
    """``torch.load`` of an archive checked by :func:`check_torch_file`; any error of the loader
    becomes :class:`FormatError` naming the file (its first line only)."""
    import torch

    check_torch_file(path, what, hint)
    try:
        return torch.load(path, map_location=map_location, weights_only=weights_only)
    except Exception as e:  # noqa: BLE001 -- torch raises many types for a foreign or damaged file
        first = (str(e).strip().splitlines() or [""])[0][:160]
        tail = f"; {hint}" if hint else ""
        raise FormatError(f"{path}: unreadable {what} ({type(e).__name__}: {first}){tail}") from None
