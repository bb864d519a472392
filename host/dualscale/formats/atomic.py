"""Atomic writes: every artefact is written to a temporary file in its final folder and renamed
into place (``os.replace``, atomic on POSIX), so an interrupted run (Ctrl-C, ``kill -9``) never
leaves a half-written file under a final name.  Temporary names start with ``.tmp-``; a rerun
removes stale ones with :func:`clean_stale`.

Before the rename the written file is checked and flushed to disk (``fsync``), and the folder is
flushed after it, so a power loss or a full disk leaves the previous file or the complete new
one, never an empty or truncated file under the final name:

* the temporary file must not be empty (``atomic_path(..., nonempty=False)`` for a file that may
  be), :func:`write_bytes` checks that every byte is in it, and an image writer passes its own
  ``verify`` (:func:`dualscale.formats.exr.verify_image`: the file re-opens with the spec written
  and its pixels read back whole), since OpenImageIO reports success for a PNG that a full disk
  truncated;
* a write that fails for lack of room is :class:`~dualscale.errors.OutputError` (exit 4) naming
  the final file and the cause -- disk full (``ENOSPC``, ``EDQUOT``), the file-size limit
  (``EFBIG``, ``ulimit -f``), or bytes that did not reach the disk (``EIO``); a writer that gives
  no ``errno`` (OpenImageIO's text) is diagnosed from the folder's free space and the process's
  file-size limit (:func:`output_error`).

Files get ``0666 & ~umask`` (folders ``0777 & ~umask``), as ``open()`` would give them: other
accounts of the lab read them when the umask allows it.  :func:`probe_writable` checks a folder
before a long command starts.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import resource
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator

from dualscale.errors import OutputError

TMP_PREFIX = ".tmp-"
LOW_SPACE = 1 << 20  # bytes: a folder with less free space than this is "full" for a failed write
_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO)  # errnos that mean the bytes did not fit
_NO_DIR_FSYNC = (errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EBADF, errno.EACCES, errno.EPERM,
                 errno.EROFS, errno.EISDIR)  # a filesystem or folder that refuses a folder fsync


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def output_error(path: str | Path, cause: BaseException | str | None = None,
                 written: str | Path | None = None, short: bool = False) -> OutputError | None:
    """The :class:`~dualscale.errors.OutputError` for a failed write of ``path`` (the final name),
    or ``None`` when ``cause`` is not about room on the disk.

    ``cause``: the ``OSError`` the writer raised (its ``errno`` decides: ``ENOSPC``/``EDQUOT``
    disk full, ``EFBIG`` the file-size limit, ``EIO`` the bytes did not reach the disk), or a
    writer's text without an ``errno`` (OpenImageIO's), which is diagnosed: disk full when the
    folder has less than :data:`LOW_SPACE` bytes free (``statvfs``, the space this account may
    use), the file-size limit when ``written`` (the temporary file) reached the process's
    ``RLIMIT_FSIZE``; otherwise ``EIO`` when ``short`` (the file is known to be short or
    unreadable), else ``None``."""
    path = Path(path)
    code = cause.errno if isinstance(cause, OSError) else None
    detail = "" if isinstance(cause, OSError) and code is not None else str(cause or "").strip()
    if written is not None and detail:
        detail = detail.replace(str(written), str(path))
    detail = detail.removeprefix(f"cannot write {path}: ")
    if code is None:
        code = _diagnose(path.parent, written)
        if code is None and short:
            code = errno.EIO
        if code is None:
            return None
    if code not in _ROOM:
        return None
    why = {errno.ENOSPC: "disk full", errno.EDQUOT: "disk quota full",
           errno.EFBIG: "file too large for the file-size limit (ulimit -f) or the filesystem",
           errno.EIO: "the bytes did not reach the disk"}[code]
    text = f"{why} ({os.strerror(code)}); nothing was kept under this name"
    if detail:
        text += f" [{detail.splitlines()[0][:200]}]"
    return OutputError(code, text, str(path))


def _diagnose(folder: Path, written: str | Path | None) -> int | None:
    """The ``errno`` a write without one most likely met: ``ENOSPC`` for a (nearly) full folder,
    ``EFBIG`` for a file that reached the process's file-size limit, else ``None``."""
    with contextlib.suppress(OSError):
        st = os.statvfs(folder)
        if st.f_bavail * st.f_frsize < LOW_SPACE:
            return errno.ENOSPC
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    if soft != resource.RLIM_INFINITY and written is not None:
        with contextlib.suppress(OSError):
            if os.stat(written).st_size >= soft:
                return errno.EFBIG
    return None


def _fsync_file(path: Path) -> None:
    """Flush a file that a foreign writer (OpenImageIO, torch, onnx) closed to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable.  A filesystem that refuses a folder fsync
    (``EINVAL``, ...) is let be; an I/O error or a full disk here raises ``OSError``."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError as e:
        if e.errno not in _NO_DIR_FSYNC:
            raise
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path, verify: Callable[[Path], None] | None = None,
                nonempty: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` (same suffix, so writers that choose a format by
    extension still work); on a clean exit check it, flush it to disk and rename it to ``path``,
    on an error delete it.

    The check: the file must not be empty (unless ``nonempty=False``), then ``verify(tmp)``
    (raise ``OSError`` -- :class:`~dualscale.errors.OutputError` when the file is short -- if the
    writer's file is not whole).  Errors: :class:`~dualscale.errors.OutputError` (see
    :func:`output_error`) for a disk full, a file-size limit or bytes that did not reach the
    disk, whatever the writer raised; other ``OSError`` renamed to name ``path``; no file is left
    under ``path`` by a failed write (a previous file there stays as it was, unless the failure
    came after the rename: a folder fsync that fails removes the new file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f"{TMP_PREFIX}{path.stem}-", suffix=path.suffix, dir=path.parent)
    except OSError as e:  # name the file the user asked for, not the temporary name that could not be made
        raise type(e)(e.errno, e.strerror or str(e), str(path)) from e
    os.close(fd)
    tmp_path = Path(tmp)
    renamed = False
    try:
        yield tmp_path
        if tmp_path.is_file():
            if nonempty and tmp_path.stat().st_size == 0:
                raise output_error(path, "the writer reported success but wrote 0 bytes", tmp_path, short=True)
            if verify is not None:
                verify(tmp_path)
            _fsync_file(tmp_path)  # a full disk or lost power shows here, not as a short final file
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600: give the file the usual mode
        os.replace(tmp_path, path)
        renamed = True
        _fsync_dir(path.parent)
    except BaseException as e:
        err = None
        if isinstance(e, OutputError):
            err = e if e.filename == str(path) else OutputError(e.errno, e.strerror, str(path))
        elif isinstance(e, OSError) and e.filename in (None, str(tmp_path), str(path)):
            err = output_error(path, e if e.errno is not None else str(e), tmp_path)
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        if renamed and err is not None:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()  # the folder's fsync failed: the rename may not last, keep no final name
        if err is not None:
            raise err from (None if err is e else e)
        if isinstance(e, OSError) and e.errno is not None and e.filename in (None, str(tmp_path)):
            # name the file the user knows (a permission: 'Permission denied: OUT/normal.exr')
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
    """Write ``data`` atomically, checked whole and flushed to disk (fsync) before the rename;
    returns ``path``.  :class:`~dualscale.errors.OutputError` when the disk is full (or the file
    is short), nothing left under ``path``."""
    path = Path(path)

    def whole(tmp: Path) -> None:
        size = tmp.stat().st_size
        if size != len(data):
            raise output_error(path, f"{size} of {len(data)} bytes written", tmp, short=True)

    with atomic_path(path, verify=whole, nonempty=bool(data)) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
    return path


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8, ``\n`` line ends) atomically; returns ``path``."""
    return write_bytes(path, text.encode("utf-8"))


def jsonable(obj: Any) -> Any:
    """``obj`` as the JSON value :func:`write_json` writes and reads back: dicts, lists, str,
    numbers, bool and None, with anything else (paths, enums, numpy scalars) made ``str`` (the
    same ``default=str``) and tuples made lists.  For a record that is compared with one read
    from disk (a journal entry, ``capture.json``) before or without writing it.  ``TypeError`` /
    ``ValueError`` as :func:`json.dumps` raises them (e.g. a dict key that is not a str,
    number, bool or None; a circular reference)."""
    return json.loads(json.dumps(obj, default=str))


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
