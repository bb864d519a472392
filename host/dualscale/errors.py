"""One error tree for the whole package; the command line maps it to exit codes in one place
(:data:`EXIT_CODES`, used by :func:`dualscale.cli.main`).

Every error a user can cause derives from :class:`DualscaleError`.  Errors about the *input*
(a file, a value, a unit the stage cannot interpret) also derive from :class:`ValueError`, so
library callers that expect ``ValueError`` keep working.  Nothing is written when one is raised
(every artefact goes through a temporary file and a rename; see ``dualscale.formats.atomic``).

Exit codes (``dualscale ...``): 0 success, 1 a run that finished but failed its own check,
2 bad input (:class:`InputError`), 3 the rig or its simulator (:class:`RigError`), 4 missing
tools or environment (:class:`ToolError`; a full disk: :class:`OutputError`), 5 an internal
failure (an out-of-memory ``MemoryError`` is the environment: 4), 130 interrupted (Ctrl-C, or a
stop request: SIGTERM, SIGHUP, :class:`StopRequest`; resumable).
"""

from __future__ import annotations


class DualscaleError(Exception):
    """Base of every error this package raises on purpose."""

    exit_code = 5


class InputError(DualscaleError, ValueError):
    """An input cannot be interpreted (format, units, colour space, geometry, values); the
    message names the file and the field."""

    exit_code = 2


class FormatError(InputError):
    """A file is not in the expected on-disk format or version."""


class UnitsError(InputError):
    """Radiometric units, exposure or colour space that the stage cannot interpret."""


class GeometryError(InputError):
    """Directions, normals or windows that are physically impossible or unsupported."""


class CalibrationError(InputError):
    """A calibration input is unusable; nothing is written."""


class MissingBracketsError(CalibrationError):
    """An exposure bracket is missing, or the brackets do not cover every pixel."""


class SaturatedError(CalibrationError):
    """Every capture of a group is saturated."""


class ChartNotFoundError(CalibrationError):
    """No ColorChecker could be located in an image."""


class ImageSizeError(CalibrationError):
    """Images that must share a size do not."""


class RigMismatchError(CalibrationError):
    """A calibration file belongs to another rig."""


class RigError(DualscaleError, RuntimeError):
    """The rig (or its simulator) did not do what was asked."""

    exit_code = 3


class CameraError(RigError):
    """A camera (of the rig, or a backend of :mod:`dualscale.capture`) did not do what was asked.
    ``frames``: the frames of the acquisition that did arrive before it failed (kept, never
    silently dropped; empty when none or not applicable)."""

    def __init__(self, message: str = "", frames: list | None = None):
        super().__init__(message)
        self.frames = list(frames or [])


class CameraTimeout(CameraError):
    """Fewer frames arrived than the camera was armed for, before the timeout (``frames``: the
    ones that did arrive)."""


class CameraDisconnected(CameraError):
    """The camera stopped answering or went away (``frames``: those that arrived before)."""


class ToolError(DualscaleError, RuntimeError):
    """An external tool or environment requirement is missing (a flasher, a compiler, a browser)."""

    exit_code = 4


class OutputError(OSError, ToolError):
    """An output file could not be written whole: the disk (or the user's quota) is full, the
    file-size limit was reached (``ulimit -f``), or the bytes did not reach the disk although the
    writer reported success.  Raised by :mod:`dualscale.formats.atomic` after the temporary file
    was removed, so nothing is left under the final name.  An ``OSError`` (``errno``: ``ENOSPC``,
    ``EDQUOT``, ``EFBIG`` or ``EIO``; ``filename``: the final path) and an environment error:
    exit 4, the README's "a full disk".  Constructed as ``OSError(errno, strerror, filename)``;
    its message is ``cannot write FILENAME: STRERROR``."""

    def __str__(self) -> str:
        what = self.strerror or (self.args[0] if self.args else "the write failed")
        return f"cannot write {self.filename}: {what}" if self.filename is not None else str(what)


class Interrupted(DualscaleError, RuntimeError):
    """A long command stopped before the end (Ctrl-C, a stop request); its state is saved and a
    rerun resumes it."""

    exit_code = 130


class StopRequest(KeyboardInterrupt):
    """A stop request: SIGTERM (``kill``, ``timeout``, Slurm/PBS at the end of a job's time) or
    SIGHUP (the terminal went away), raised in the main thread by the handler that
    :func:`dualscale.cli.main` installs.  A ``KeyboardInterrupt``, so every command stops,
    saves and cleans up exactly as on Ctrl-C (exit 130, resumable); ``signal``: its name."""

    def __init__(self, signal: str):
        super().__init__(f"stopped by {signal}")
        self.signal = signal


def one_line(e: BaseException) -> str:
    """The error's message on one line, as the command line prints it (an ``OSError`` that is
    not one of ours as 'reason: file'; lines joined with '; ')."""
    if isinstance(e, OSError) and not isinstance(e, DualscaleError) and e.strerror:
        msg = f"{e.strerror}: {e.filename}" if e.filename is not None else e.strerror
    else:
        msg = str(e) or type(e).__name__
    return "; ".join(ln.strip() for ln in msg.splitlines() if ln.strip())


EXIT_CODES = {"ok": 0, "check_failed": 1, "input": InputError.exit_code, "rig": RigError.exit_code,
              "tool": ToolError.exit_code, "internal": DualscaleError.exit_code,
              "interrupted": Interrupted.exit_code}
