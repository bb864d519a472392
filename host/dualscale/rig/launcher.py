"""Start the simulated rig: the POSIX build of the firmware core, or the ARM image in QEMU.

Both expose the Modbus RTU server on a pseudo-terminal; `SimulatedRig.port` is its path.
The binaries are built by `make -C firmware` into firmware/build/ (override the folder with
the DUALSCALE_FIRMWARE_BUILD environment variable).
"""
from __future__ import annotations

from dualscale.errors import InputError, RigError, ToolError

import os
import re
import select
import shutil
import signal
import struct
import subprocess
import termios
import time
import tty
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
TARGETS = ("posix", "qemu")
# QEMU's USART model takes one byte per turn of its main loop, so on a busy host a request's
# bytes reach the guest with gaps longer than t3.5 and the frame splits. The launcher raises the
# guest's FRAME_TIMEOUT_US to this (µs) by broadcast, which is neither answered nor counted.
QEMU_FRAME_TIMEOUT_US = 20000
BROADCAST_ADDRESS = 0  # Modbus: every server acts on it and none answers
FC_WRITE_REGISTER = 0x06  # Modbus function code "write single register"
FC_WRITE_REGISTERS = 0x10  # Modbus function code "write multiple registers"
PARITIES = {"E": "EVEN", "O": "ODD", "N": "NONE"}  # --parity letter -> regmap.Parity name


def line_format(parity: str | None, stop_bits: int | None) -> tuple[str, int]:
    """The serial-line format ``(parity letter, stop bits)`` a simulator is started with.

    ``parity`` is "E" (even), "O" (odd) or "N" (none), default the register map's reset value
    (rig.toml [serial], EVEN); ``stop_bits`` is 1 or 2, default 1 with parity and 2 without, as
    Modbus over Serial Line v1.02 section 2.5.1 requires. Raises InputError for anything else,
    8N1 included."""
    from ..protocol import regmap as rm

    if parity is None:
        parity = next(k for k, v in PARITIES.items() if rm.Parity[v] == rm.DEFAULT_PARITY)
    parity = str(parity).upper()
    if parity not in PARITIES:
        raise InputError(f"parity must be E, O or N, not {parity!r}")
    if stop_bits is None:
        stop_bits = 2 if parity == "N" else 1
    if stop_bits not in (1, 2):
        raise InputError(f"stop bits must be 1 or 2, not {stop_bits!r}")
    if parity == "N" and stop_bits != 2:
        raise InputError("no parity needs 2 stop bits (Modbus over Serial Line v1.02, 2.5.1)")
    return parity, stop_bits


def line_format_broadcast(parity: str, stop_bits: int) -> bytes:
    """The RTU frame that sets every server's SERIAL_PARITY and SERIAL_STOP_BITS: FC 10 to the
    broadcast address (executed, never answered), CRC appended."""
    from ..protocol.crc import rtu_frame
    from ..protocol.regmap import HR, Parity

    return rtu_frame(struct.pack(">BBHHBHH", BROADCAST_ADDRESS, FC_WRITE_REGISTERS, HR.SERIAL_PARITY,
                                 2, 4, Parity[PARITIES[parity]], stop_bits))


def frame_timeout_broadcast(us: int) -> bytes:
    """The RTU frame that sets every server's FRAME_TIMEOUT_US to ``us``: FC 06 (write single
    register) to the broadcast address, register address and value big-endian, CRC appended."""
    from ..protocol.crc import rtu_frame
    from ..protocol.regmap import HR

    return rtu_frame(struct.pack(">BBHH", BROADCAST_ADDRESS, FC_WRITE_REGISTER, HR.FRAME_TIMEOUT_US, us))


def build_dir() -> Path:
    return Path(os.environ.get("DUALSCALE_FIRMWARE_BUILD", REPO / "firmware" / "build"))


def sim_binary() -> Path:
    return build_dir() / "posix" / "dualscale-sim"


def firmware_elf() -> Path:
    return build_dir() / "stm32f405" / "dualscale.elf"


def _raise_priority() -> None:
    """Run QEMU ahead of other work when allowed (root): its USART model takes one byte per
    main-loop turn, so a starved QEMU shows the guest gaps longer than t3.5 inside a frame."""
    try:
        os.nice(-10)
    except OSError:
        pass


def _die_with_parent() -> None:
    """Linux: the simulator gets SIGTERM when the process that started it dies, even by
    ``kill -9`` (prctl PR_SET_PDEATHSIG), so no orphaned simulator keeps the pty.  Elsewhere a
    no-op."""
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass


def _qemu_preexec() -> None:
    _die_with_parent()
    _raise_priority()


class SimError(RigError):
    """The simulated rig could not be started, or died."""


class SimNotBuilt(ToolError):
    """The simulator's binary (or QEMU) is missing: an environment problem, exit code 4."""


def qemu_command(elf: Path, icount: str | None = None) -> list[str]:
    """qemu-system-arm on the netduinoplus2 board (an STM32F405), USART1 on a pty."""
    cmd = ["qemu-system-arm", "-M", "netduinoplus2", "-nographic", "-monitor", "none",
           "-serial", "pty", "-kernel", str(elf)]
    if icount:
        cmd += ["-icount", icount]
    return cmd


class SimulatedRig:
    """A running simulated rig. Use as a context manager; `port` is the serial device."""

    def __init__(self, target: str = "posix", link: str | os.PathLike | None = None,
                 speed: float = 1.0, hw_socket: str | os.PathLike | None = None,
                 icount: str | None = None, startup_s: float = 10.0,
                 frame_timeout_us: int | None = None, parity: str | None = None,
                 stop_bits: int | None = None):
        """``parity`` ("E", "O", "N") and ``stop_bits`` (1, 2): the serial-line format the rig
        starts with (see `line_format`; default 8E1). The POSIX simulator takes them on its
        command line; the QEMU image boots in its compiled-in 8E1 and is switched by a broadcast
        write of SERIAL_PARITY/SERIAL_STOP_BITS when another format is asked for."""
        if target not in TARGETS:
            raise InputError(f"target must be one of {TARGETS}, not {target!r}")
        self.parity, self.stop_bits = line_format(parity, stop_bits)
        self.target, self.speed = target, speed
        self.link = Path(link) if link else None
        self.hw_socket = Path(hw_socket) if hw_socket else None
        if icount is None and target == "qemu":
            icount = os.environ.get("DUALSCALE_QEMU_ICOUNT") or None
        self.icount, self.startup_s = icount, startup_s
        if frame_timeout_us is None and target == "qemu":
            frame_timeout_us = QEMU_FRAME_TIMEOUT_US
        self.frame_timeout_us = frame_timeout_us
        self.proc: subprocess.Popen | None = None
        self.port: str = ""
        self._hold: int | None = None

    def start(self) -> SimulatedRig:
        if self.target == "posix":
            exe = sim_binary()
            if not exe.exists():
                raise SimNotBuilt(f"{exe} is missing: build it with `make -C firmware posix`")
            cmd = [str(exe), "--speed", repr(float(self.speed)),
                   "--parity", self.parity, "--stop-bits", str(self.stop_bits)]
            if self.hw_socket:
                cmd += ["--hw-socket", str(self.hw_socket)]
            self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                         preexec_fn=_die_with_parent, start_new_session=True)
            line = self._read_line(self.proc.stdout, lambda s: s.startswith("/dev/"))
            self.port = line.strip()
        else:
            elf = firmware_elf()
            if not elf.exists():
                raise SimNotBuilt(f"{elf} is missing: build it with `make firmware`")
            if not shutil.which("qemu-system-arm"):
                raise SimNotBuilt("qemu-system-arm is not installed (apt-get install qemu-system-arm)")
            # QEMU 7.2 prints "char device redirected to /dev/pts/N" on stdout: read both
            self.proc = subprocess.Popen(qemu_command(elf, self.icount), stdin=subprocess.DEVNULL,
                                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                         preexec_fn=_qemu_preexec)
            line = self._read_line(self.proc.stdout, lambda s: "redirected to /dev/" in s)
            m = re.search(r"(/dev/\S+)", line)
            if not m:
                self.stop()
                raise SimError(f"cannot find the pty in QEMU's output: {line!r}")
            self.port = m.group(1)
            self._hold_open()
        if self.link:
            if self.link.is_symlink() or self.link.exists():
                self.link.unlink()
            self.link.symlink_to(self.port)
        return self

    def _hold_open(self) -> None:
        """Keep the pty open for QEMU's lifetime, and give QEMU time to notice.

        QEMU's pty backend polls for a connected peer on a 1 s timer and drops the guest's output
        while it thinks nobody is there, so a client that opened the port later would lose its
        first reply. Holding one descriptor open (and never reading it) keeps it connected. The
        only frames sent are the broadcasts that set FRAME_TIMEOUT_US and, when another line format than
        the default is asked for, SERIAL_PARITY/SERIAL_STOP_BITS (no answer, no counter).
        """
        self._hold = os.open(self.port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self._hold)
        time.sleep(1.2)
        termios.tcflush(self._hold, termios.TCIOFLUSH)
        if self.frame_timeout_us:
            # twice: under load QEMU's 1 s pty poll can still miss the first (found as a register
            # left at 0 in a clean-clone run); the write is idempotent and a broadcast has no answer
            for pause in (0.5, 0.1):
                os.write(self._hold, frame_timeout_broadcast(self.frame_timeout_us))
                time.sleep(pause)
        if (self.parity, self.stop_bits) != line_format(None, None):
            os.write(self._hold, line_format_broadcast(self.parity, self.stop_bits))
            time.sleep(0.1)

    def _read_line(self, stream, want) -> str:
        """The first line from `stream` satisfying `want`, within startup_s."""
        deadline = time.monotonic() + self.startup_s
        buf = b""
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                err = (self.proc.stderr or stream).read().decode(errors="replace")
                raise SimError(f"the {self.target} simulator exited with {self.proc.returncode}: {err}")
            r, _, _ = select.select([stream], [], [], 0.1)
            if r:
                chunk = os.read(stream.fileno(), 4096)
                buf += chunk
                for ln in buf.decode(errors="replace").splitlines():
                    if want(ln):
                        return ln
        self.stop()
        raise SimError(f"the {self.target} simulator did not report its serial device "
                       f"within {self.startup_s} s")

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self) -> int | None:
        rc = None
        if self._hold is not None:
            os.close(self._hold)
            self._hold = None
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.send_signal(signal.SIGTERM if self.target == "qemu" else signal.SIGINT)
                try:
                    self.proc.wait(5)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
            rc = self.proc.returncode
            for s in (self.proc.stdout, self.proc.stderr):
                if s:
                    s.close()
            self.proc = None
        if self.link and self.link.is_symlink():
            self.link.unlink()
        return rc

    def __enter__(self) -> SimulatedRig:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
