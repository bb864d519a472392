"""The `dualscale` command line.

Every subcommand raises on failure; :func:`main` is the one place where an error meets the
user: one line on stderr (``dualscale CMD: error: ...``) and the exit code of
:func:`exit_code` (the table is :data:`dualscale.errors.EXIT_CODES`), never a traceback
(``DUALSCALE_DEBUG=1`` shows it).  Long commands share ``-o/--output``, ``--threads N`` and
``--progress/--no-progress`` (:mod:`.common`).
"""
from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import time

from dualscale.errors import EXIT_CODES, DualscaleError, StopRequest, one_line

#: the signals that are a stop request, handled like Ctrl-C (:class:`~dualscale.errors.StopRequest`)
STOP_SIGNALS = ("SIGTERM", "SIGHUP")


def cmd_sim(a: argparse.Namespace) -> int:
    from dualscale.rig.launcher import SimError, SimulatedRig

    stop = {"now": False}

    def handler(_signum, _frame):
        stop["now"] = True

    # before the device line goes out: a caller may signal as soon as it has read it; Ctrl-C
    # and a stop request (SIGTERM, SIGHUP) end the simulator the same way (exit 0)
    signal.signal(signal.SIGINT, handler)
    for name in STOP_SIGNALS:
        signal.signal(getattr(signal, name), handler)
    rig = SimulatedRig(a.target, link=a.link, speed=a.speed, hw_socket=a.hw_socket, icount=a.icount,
                       parity=a.parity, stop_bits=a.stopbits)
    rig.start()
    print(rig.port, flush=True)
    if a.link:
        print(f"linked {a.link} -> {rig.port}", file=sys.stderr)
    try:
        while not stop["now"] and rig.alive():
            time.sleep(0.1)
    finally:
        died = not rig.alive()
        rig.stop()
    if died and not stop["now"]:
        raise SimError(f"the {a.target} simulator exited unexpectedly")
    return 0


def cmd_console(a: argparse.Namespace) -> int:
    from dualscale.rig.client import RigClient
    from dualscale.rig.console import Console, run_script

    with RigClient(a.port, address=a.address, parity=a.parity, stopbits=a.stopbits) as rig:
        con = Console(rig)
        if a.c is not None:
            return run_script(con, a.c)
        con.cmdloop()
    return 0


def cmd_flash(a: argparse.Namespace) -> int:
    from dualscale.rig.flash import flash

    return flash(a.tool, dry_run=a.dry_run, port=a.port)


def cmd_demo(a: argparse.Namespace) -> int:
    from dualscale.rig.demo import run_demo

    rep = run_demo(a.target, speed=a.speed, on_event=print if a.events else None, parity=a.parity,
                   stopbits=a.stopbits)
    return 0 if rep.state == "DONE" and rep.dropped == 0 else 1


class _Parser(argparse.ArgumentParser):
    """argparse with the house's one-line errors: ``dualscale CMD: error: ... (see --help)``,
    exit code 2 (subparsers inherit the class)."""

    def error(self, message: str):  # noqa: D102 - argparse's hook
        self.exit(EXIT_CODES["input"], f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _serial_format_options(p: argparse.ArgumentParser) -> None:
    """--parity/--stop-bits of a command that opens the rig's serial port (PROTOCOL.md §1; the simulator binary spells it the same)."""
    from dualscale.rig.client import DEFAULT_PARITY, PARITIES

    p.add_argument("--parity", choices=PARITIES, default=DEFAULT_PARITY, type=str.upper,
                   help=f"serial parity (default {DEFAULT_PARITY}: 8E1, the Modbus serial-line default)")
    p.add_argument("--stop-bits", "--stopbits", dest="stopbits", type=int, choices=(1, 2), default=None,
                   help="stop bits (default 1 with parity, 2 with --parity N; the rig refuses 8N1)")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="dualscale", description=__doc__.split("\n\n")[0],
                formatter_class=argparse.RawDescriptionHelpFormatter)
    from importlib.metadata import version

    p.add_argument("--version", action="version", version=f"dualscale {version('dualscale')}")
    sub = p.add_subparsers(dest="cmd", required=True)

    s = sub.add_parser("sim", help="start the simulated rig (prints its serial device first)")
    s.add_argument("--target", choices=("posix", "qemu"), default="posix",
                   help="posix: the C core as a host program; qemu: the STM32F405 image under QEMU (default: posix)")
    s.add_argument("--link", help="make a symlink to the serial device at this path")
    s.add_argument("--speed", type=float, default=1.0,
                   help="posix: 1 = real time, >1 accelerated virtual time, 0 = as fast as possible (default 1)")
    s.add_argument("--hw-socket", help="posix: Unix socket for the simulated hardware side channel")
    s.add_argument("--icount", help="qemu: -icount option, e.g. shift=4")
    _serial_format_options(s)
    s.set_defaults(fn=cmd_sim)

    c = sub.add_parser("console", help="interactive serial console")
    c.add_argument("--port", required=True, help="serial device or pyserial URL")
    c.add_argument("--address", type=int, default=1, help="Modbus unit address of the rig (default: 1)")
    c.add_argument("-c", metavar="CMDS", help='run ";"-separated commands and exit')
    _serial_format_options(c)
    c.set_defaults(fn=cmd_console)

    f = sub.add_parser("flash", help="build and flash the STM32F405 firmware")
    f.add_argument("--tool", choices=("auto", "pio", "openocd", "st-flash", "dfu-util"), default="auto",
                   help="flasher to use; auto takes the first one installed (default: auto)")
    f.add_argument("--dry-run", action="store_true", help="print the exact commands only")
    f.add_argument("--port", help="serial port to check the firmware version on afterwards")
    f.set_defaults(fn=cmd_flash)

    d = sub.add_parser("demo", help="run the full micro-capture sequence on the simulated rig")
    d.add_argument("--target", choices=("posix", "qemu"), default="posix",
                   help="simulator to run the sequence on: posix or qemu (default: posix)")
    d.add_argument("--speed", type=float, default=10.0, help="posix simulator speed (see sim; default 10)")
    d.add_argument("--events", action="store_true", help="print every event")
    _serial_format_options(d)
    d.set_defaults(fn=cmd_demo)

    from .capture import register as register_capture

    register_capture(sub)
    from .sim import register as register_appearance

    register_appearance(sub)
    from .calib import register as register_calib

    register_calib(sub)
    from .fit import register as register_fit

    register_fit(sub)
    from .propagate import register as register_propagate

    register_propagate(sub)
    from .digitize import register as register_digitize

    register_digitize(sub)
    from .batch import register as register_batch

    register_batch(sub)
    from .lights import register as register_lights

    register_lights(sub)
    from .importer import register as register_import

    register_import(sub)
    from .tile import register as register_tile

    register_tile(sub)
    from .export import register as register_export

    register_export(sub)
    from .view import register as register_view

    register_view(sub)
    return p


def out_of_memory(e: BaseException) -> bool:
    """Whether ``e`` says the process ran out of memory: a ``MemoryError`` (numpy's "Unable to
    allocate ...") or torch's CPU allocator failure (a ``RuntimeError`` "can't allocate memory")."""
    if isinstance(e, MemoryError):
        return True
    return isinstance(e, RuntimeError) and not isinstance(e, DualscaleError) and (
        type(e).__name__ == "OutOfMemoryError" or "can't allocate memory" in str(e))


def available_memory() -> tuple[int, int | None]:
    """``(available, limit)`` in bytes: the memory this machine can give a new process now
    (``MemAvailable`` of /proc/meminfo; elsewhere ``SC_AVPHYS_PAGES``), and this process's
    address-space limit (``ulimit -v``; ``None`` when unlimited)."""
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for ln in f:
                if ln.startswith("MemAvailable:"):
                    avail = int(ln.split()[1]) * 1024
                    break
    except OSError:
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            avail = 0
    limit = None
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        limit = None if soft == resource.RLIM_INFINITY else int(soft)
    except (ImportError, OSError, ValueError):
        pass
    return avail, limit


def memory_text() -> str:
    """'this machine has N GiB available' (and the ``ulimit -v`` limit when one is set)."""
    avail, limit = available_memory()
    text = f"this machine has {avail / 2**30:.1f} GiB available"
    if limit is not None:
        text += f" and this process may use {limit / 2**30:.1f} GiB of address space (ulimit -v)"
    return text


def exit_code(e: BaseException) -> int:
    """The one mapping from errors to exit codes (the table is :data:`dualscale.errors.EXIT_CODES`):
    an error of the tree carries its own; Ctrl-C and a stop request (SIGTERM, SIGHUP:
    :class:`~dualscale.errors.StopRequest`) are ``interrupted``; a foreign ``ValueError``
    or a missing/unreadable file is bad ``input``; another ``OSError`` (disk full, no device)
    and running out of memory (:func:`out_of_memory`) are the environment (``tool``); anything
    else is ``internal``."""
    if isinstance(e, DualscaleError):
        return e.exit_code
    if isinstance(e, KeyboardInterrupt):
        return EXIT_CODES["interrupted"]
    if out_of_memory(e):
        return EXIT_CODES["tool"]
    if isinstance(e, (ValueError, FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError)):
        return EXIT_CODES["input"]
    if isinstance(e, OSError):
        return EXIT_CODES["tool"]
    return EXIT_CODES["internal"]


class _StopSignals:
    """While active (in the main thread): SIGTERM and SIGHUP raise
    :class:`~dualscale.errors.StopRequest` there, so a command stops, saves and cleans up as on
    Ctrl-C.  After the first, further stop requests are ignored (a job scheduler may repeat
    SIGTERM; the command's cleanup -- a checkpoint, the batch's summary -- is not cut short;
    SIGKILL still ends it).  ``received``: the name of the signal that came, else ``None``.
    The previous handlers come back on exit (``main`` runs in-process in tests)."""

    def __init__(self) -> None:
        self.received: str | None = None
        self._old: dict[int, object] = {}

    def _handler(self, signum, _frame) -> None:
        name = signal.Signals(signum).name
        if self.received is not None:
            return
        self.received = name
        raise StopRequest(name)

    def __enter__(self) -> "_StopSignals":
        import threading

        if threading.current_thread() is threading.main_thread():
            for name in STOP_SIGNALS:
                if hasattr(signal, name):
                    sig = getattr(signal, name)
                    self._old[sig] = signal.signal(sig, self._handler)
        return self

    def ignore(self) -> None:
        """Ignore further stop requests (while the last line is printed)."""
        for sig in self._old:
            signal.signal(sig, signal.SIG_IGN)

    def __exit__(self, *_) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


def main(argv: list[str] | None = None) -> int:
    """Run ``dualscale ARGV`` and return its exit code; every error becomes one line on stderr
    and the code of :func:`exit_code` (no traceback; ``DUALSCALE_DEBUG=1`` re-raises).
    SIGTERM and SIGHUP are a stop request, handled like Ctrl-C (:class:`_StopSignals`)."""
    with _StopSignals() as stops:
        return _main(argv, stops)


def _main(argv: list[str] | None, stops: _StopSignals) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2, already printed on one line)
        return e.code if isinstance(e.code, int) else EXIT_CODES["input"]
    except KeyboardInterrupt as e:  # Ctrl-C while the subcommands' modules load: nothing started yet
        if os.environ.get("DUALSCALE_DEBUG"):
            raise
        how = str(e) if isinstance(e, StopRequest) else "interrupted"
        print(f"dualscale: {how} before the command started; run the same command again", file=sys.stderr)
        return EXIT_CODES["interrupted"]
    cmd = " ".join(x for x in (args.cmd, getattr(args, "propagate_cmd", None), getattr(args, "study", None)) if x)
    import warnings

    seen: set[str] = set()

    def one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
        text = one_line(message) if isinstance(message, BaseException) else str(message)
        if text in seen:  # the same warning from another pass (the folds of the cross-validation, the final fit)
            return
        seen.add(text)
        print(f"dualscale {cmd}: warning: {text}", file=sys.stderr)

    shown, warnings.showwarning = warnings.showwarning, one_line_warning
    restore = None
    try:
        return args.fn(args)
    except (Exception, KeyboardInterrupt) as e:  # noqa: BLE001 -- the one place errors meet the user
        if os.environ.get("DUALSCALE_DEBUG"):
            raise
        with contextlib.suppress(ValueError):  # a second Ctrl-C must not cut the one line short
            restore = signal.signal(signal.SIGINT, signal.SIG_IGN)  # (ValueError: not the main thread)
            stops.ignore()  # nor a stop request
        code = exit_code(e)
        if code == EXIT_CODES["interrupted"]:
            msg = one_line(e) if str(e) else "interrupted"
            if stops.received is not None and not isinstance(e, StopRequest):
                msg = f"stopped by {stops.received}: {msg}"  # the command's own message (what it saved)
            how = getattr(args, "resume_hint", "run the same command again to resume")
            print(f"dualscale {cmd}: {msg}; {how}", file=sys.stderr)
        elif out_of_memory(e):
            import re

            what = one_line(e) if str(e) else "an allocation failed"
            m = re.search(r"tried to allocate (\d+) bytes", what)  # torch's allocator: one short clause
            what = f"could not allocate {int(m.group(1)) / 2**30:.2f} GiB" if m else what
            how = getattr(args, "memory_hint", "use smaller inputs, or fewer --threads/--workers")
            print(f"dualscale {cmd}: error: out of memory: {what}; {memory_text()}; {how}", file=sys.stderr)
        elif code == EXIT_CODES["internal"] and not isinstance(e, DualscaleError):
            print(f"dualscale {cmd}: internal error: {type(e).__name__}: {one_line(e)} "
                  "(rerun with DUALSCALE_DEBUG=1 for the traceback, and please report it)", file=sys.stderr)
        else:
            print(f"dualscale {cmd}: error: {one_line(e)}", file=sys.stderr)
        return code
    finally:
        warnings.showwarning = shown
        if restore is not None:
            signal.signal(signal.SIGINT, restore)


def run() -> None:
    """The ``dualscale`` console script: :func:`main`, then a prompt exit.

    The process ends with ``os._exit`` once the command has returned and both streams are
    flushed: OpenImageIO's nanobind bindings otherwise print a page of benign "leaked instance"
    warnings at interpreter shutdown after some commands (nanobind's documented shutdown-order
    effect; the wheel does not expose ``set_leak_warnings``).  Every artefact is closed by then:
    writers use context managers and atomic renames, never exit handlers.
    """
    import os

    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    run()
