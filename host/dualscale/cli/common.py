"""Options every long command shares: ``-o/--output``, ``--threads N`` and
``--progress/--no-progress``.

``--threads N`` sets torch's intra-op threads and OpenCV's; onnxruntime takes it from the
command (``propagate run``); numpy's BLAS follows ``OMP_NUM_THREADS`` set before the start.
``--progress`` draws a bar on stderr for each long step; the default is on when stderr is a
terminal.  Library functions never print: they get the choice as their ``progress`` argument
(:mod:`dualscale.progress`).
"""

from __future__ import annotations

import argparse
import sys

from dualscale.errors import InputError


def add_output(parser: argparse.ArgumentParser, help: str, required: bool = True) -> None:
    """The one output option: ``-o/--output`` (dest ``output``)."""
    parser.add_argument("-o", "--output", required=required, help=help)


def add_work_options(parser: argparse.ArgumentParser, threads_help: str | None = None) -> None:
    """Add ``--threads N`` and ``--progress/--no-progress`` to a long command."""
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help=threads_help or "CPU threads for torch and OpenCV (default: theirs; on busy shared "
                                             "cores use 1)")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bar on stderr (default: on when stderr is a terminal)")


def apply_threads(args: argparse.Namespace) -> int | None:
    """Apply ``--threads``; returns it (``None`` = libraries' defaults).  Raises
    :class:`~dualscale.errors.InputError` for a count below 1."""
    n = getattr(args, "threads", None)
    if n is None:
        return None
    if n < 1:
        raise InputError(f"--threads must be at least 1, got {n}")
    import cv2
    import torch

    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    return n


def want_progress(args: argparse.Namespace) -> bool:
    """``--progress`` / ``--no-progress`` if given, else whether stderr is a terminal."""
    p = getattr(args, "progress", None)
    return sys.stderr.isatty() if p is None else bool(p)
