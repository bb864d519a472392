"""Atomic writes: every artefact is written to a temporary file in its final folder and renamed
into place (``os.replace``, atomic on POSIX), so an interrupted run (Ctrl-C, ``kill -9``) never
leaves a half-written file under a final name.  Temporary names start with ``.tmp-``; a rerun
removes stale ones with :func:`clean_stale`.

Every file is flushed to disk (``fsync``) before the rename, and the folder after it, so a power
loss or a full disk leaves the previous file or the complete new one, never an empty or
truncated file under the final name.  Files get ``0666 & ~umask`` (folders ``0777 & ~umask``),
as ``open()`` would give them: other accounts of the lab read them when the umask allows it.
:func:`probe_writable` checks a folder before a long command starts.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

TMP_PREFIX = ".tmp-"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _fsync_file(path: Path) -> None:
    """Flush a file that a foreign writer (OpenImageIO, torch, onnx) closed to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (best effort: some filesystems refuse a folder fsync)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` (same suffix, so writers that choose a format by
    extension still work); on a clean exit rename it to ``path``, on an error delete it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f"{TMP_PREFIX}{path.stem}-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.is_file():
            _fsync_file(tmp_path)  # a full disk or lost power shows here, not as a short final file
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600: give the file the usual mode
        os.replace(tmp_path, path)
        _fsync_dir(path.parent)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        if isinstance(e, OSError) and e.errno is not None and e.filename in (None, str(tmp_path)):
            # name the file the user knows (a full disk: 'No space left on device: OUT/normal.exr')
            raise type(e)(e.errno, e.strerror or str(e), str(path)) from e
        raise


@contextlib.contextmanager
def atomic_dir(out: str | Path) -> Iterator[Path]:
    """Yield a temporary folder beside ``out``; on a clean exit it replaces ``out`` (a previous
    ``out`` is moved aside first and removed once the new one is in place), on an error it is
    deleted, so a reader sees the old folder or the complete new one, never a half-written one."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{out.name}-", dir=out.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes 0700
        old = None
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{out.name}-old-", dir=out.parent))
            os.replace(out, old / out.name)
        os.replace(tmp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` atomically, flushed to disk (fsync) before the rename; returns ``path``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
    return path


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8, ``\n`` line ends) atomically; returns ``path``."""
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, data: Any, indent: int | None = 1) -> Path:
    """Write ``data`` as JSON atomically (``default=str`` for paths and the like)."""
    return write_text(path, json.dumps(data, indent=indent, default=str) + "\n")


def clean_stale(folder: str | Path) -> int:
    """Remove temporary files left by an interrupted writer under ``folder`` (recursively);
    returns how many were removed."""
    n = 0
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    for p in folder.rglob(f"{TMP_PREFIX}*"):
        if p.is_file():
            p.unlink()
            n += 1
    return n


PROBE = ".tmp-probe"


def probe_writable(folder: str | Path) -> Path:
    """Create ``folder`` (and its parents) and write, rename and remove a probe file in it through
    :func:`atomic_path`, so that a folder a long command could not write is found before any
    work.  Returns the folder; raises ``OSError`` (``PermissionError``, read-only filesystem,
    no space left, a file in the way) naming it."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / PROBE
        write_bytes(probe, b"dualscale write probe\n")
        probe.unlink()
    except OSError as e:
        raise type(e)(e.errno, e.strerror or str(e), str(folder)) from e
    return folder


def remove_file(path: str | Path) -> bool:
    """Remove ``path`` if it is a file (a stale artefact of an earlier run); returns whether it was."""
    try:
        Path(path).unlink()
        return True
    except FileNotFoundError:
        return False
