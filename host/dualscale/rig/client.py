"""Typed Modbus RTU client for the rig (pymodbus PDUs, pinned minor version; our own transaction).

The client checks the device's identity and protocol version on `open()`, uploads sequences
in chunks and verifies them by CRC, runs them, and follows the event FIFO with the idempotent
ack of PROTOCOL.md §4. Every request goes through `_call`, which reopens the serial port after
a drop and retries, so a run survives an unplugged cable without losing or repeating events.

RTU has no transaction id, so the client never takes a frame for the answer unless it fits
the request (PROTOCOL.md §10): the line is drained before every request, and a reply must
come from the addressed server, carry the request's function code (or its exception), the byte
count of the quantity asked for, and, for writes, echo the address and value/quantity. Any
other frame (a late reply to an earlier request) is discarded and counted in `LinkStats`, and
the client keeps listening until its timeout. Commands that change the state (START, ABORT,
CLEAR_ERROR) are retried only after reading the status to learn whether the first attempt took
effect. On a noisy line the request size shrinks on every failure and grows back on success,
and the timeout follows the measured round trip (Jacobson/Karn) with exponential backoff.
"""
from __future__ import annotations

from dualscale.errors import InputError, RigError

import logging
import os
import select
import struct
import termios
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path

import serial
from pymodbus import FramerType, ModbusException
from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ConnectionException, ModbusIOException
from pymodbus.framer.rtu import FramerRTU
from pymodbus.pdu import ModbusPDU

from ..protocol import regmap as rm
from .events import Event, decode_window
from .sequence import Step, encode, join_words, seq_crc

log = logging.getLogger(__name__)

PARITY_LETTERS = {rm.Parity.EVEN: "E", rm.Parity.ODD: "O", rm.Parity.NONE: "N"}
PARITIES = tuple(PARITY_LETTERS.values())
# the firmware's reset format (rig.toml [serial]; 8E1, the Modbus serial-line spec's default)
DEFAULT_PARITY = PARITY_LETTERS[rm.Parity(rm.DEFAULT_PARITY)]


def default_stopbits(parity: str) -> int:
    """Stop bits the Modbus serial-line spec (§2.5.1) pairs with ``parity``: the firmware's
    default (rig.toml, 1) with even or odd parity, 2 without, so a character is 11 bits."""
    return 2 if parity == "N" else rm.DEFAULT_STOP_BITS


def serial_settings(parity: str = DEFAULT_PARITY, stopbits: int | None = None) -> tuple[str, int]:
    """Checked (parity letter, stop bits). InputError names the bad value; 8N1 is refused as
    the firmware refuses it (PROTOCOL.md §1)."""
    letter = str(parity).upper()
    if letter not in PARITIES:
        raise InputError(f"parity must be one of {'/'.join(PARITIES)}, not {parity!r}")
    sb = default_stopbits(letter) if stopbits is None else int(stopbits)
    if sb not in (1, 2):
        raise InputError(f"stop bits must be 1 or 2, not {stopbits!r}")
    if letter == "N" and sb == 1:
        raise InputError("parity N needs 2 stop bits (Modbus serial line: 11 bits a character; "
                         "the rig refuses 8N1)")
    return letter, sb


class ExceptionCode(IntEnum):
    """Modbus exception codes the firmware answers (Modbus Application Protocol v1.1b3, §7)."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03  # also: START refused by the sequence validation (PROTOCOL.md §3)
    SERVER_DEVICE_FAILURE = 0x04
    SERVER_DEVICE_BUSY = 0x06


EXCEPTION_NAMES = {int(c): c.name.replace("_", " ") for c in ExceptionCode}
MAX_READ = 125
MAX_WRITE = 123
STEPS_PER_WRITE = MAX_WRITE // rm.STEP_WORDS  # 12 steps per FC 10
WORD_MAX = 0xFFFF  # a Modbus register holds 16 bits
_REGISTERS = {(r.space, r.name): r for r in rm.REGISTERS}


MIN_CHUNK_WORDS = rm.STEP_WORDS  # the adaptive request size never goes below one step
CHUNK_GROW_WORDS = rm.STEP_WORDS  # added back after every clean bulk request
DEFAULT_WATCHDOG_MS = 1000  # host watchdog during a run (PROTOCOL.md §5)
EXCEPTION_FRAME = 5  # address, FC | 0x80, exception code, CRC
FC_EXCEPTION_BIT = 0x80


class LinkError(RigError):
    """No reply that fits the request arrived, after every retry (a dead, noisy or busy link)."""


class _NoReply(ModbusIOException):
    """One attempt got no fitting reply: a timeout, or a reply that failed its CRC."""

    def __init__(self, message: str, corrupt: bool = False):
        super().__init__(message)
        self.corrupt = corrupt


@dataclass
class LinkStats:
    """What the link did since the client was made (PROTOCOL.md §10). Counts, not rates."""

    requests: int = 0  # frames sent (every attempt)
    replies: int = 0  # replies that fitted their request
    timeouts: int = 0  # attempts that got no fitting reply within the timeout
    bad_frames: int = 0  # replies that arrived but failed their CRC or framing (then retried)
    stale: int = 0  # CRC-valid frames that did not fit the request: discarded
    drained_bytes: int = 0  # bytes found on the line before a request: discarded
    retries: int = 0  # attempts after the first, over all requests
    confirmed_by_status: int = 0  # retried START/ABORT/CLEAR_ERROR that the status showed done
    chunk_shrinks: int = 0  # times the bulk request size was halved


def _crc_ok(frame: bytes) -> bool:
    return FramerRTU.compute_CRC(frame[:-2]) == int.from_bytes(frame[-2:], "big")


def reply_mismatch(request: bytes, frame: bytes) -> str | None:
    """Why the CRC-valid RTU ``frame`` is not the reply to the RTU ``request`` frame, or None.

    Checks the server address, the function code (or its exception), the byte count against
    the quantity requested (FC 01/02/03/04/17) and, for writes (FC 05/06/0F/10), the echoed
    address and value or quantity; for FC 2B the MEI type and read code. Modbus Application
    Protocol v1.1b3 §6 gives each reply's layout.
    """
    if frame[0] != request[0]:
        return f"from server {frame[0]}, not {request[0]}"
    fc = request[1]
    if frame[1] == fc | FC_EXCEPTION_BIT:
        return None if len(frame) == EXCEPTION_FRAME else f"exception frame of {len(frame)} bytes"
    if frame[1] != fc:
        return f"FC {frame[1]:02X}, not {fc:02X}"
    qty = int.from_bytes(request[4:6], "big")
    want = {0x01: (qty + 7) // 8, 0x02: (qty + 7) // 8, 0x03: 2 * qty, 0x04: 2 * qty,
            0x17: 2 * qty}.get(fc)
    if want is not None and frame[2] != want:
        return f"{frame[2]} data bytes, not the {want} of the {qty} asked for"
    if fc in (0x05, 0x06, 0x0F, 0x10) and frame[2:6] != request[2:6]:
        return (f"echo of address {int.from_bytes(frame[2:4], 'big')} / {int.from_bytes(frame[4:6], 'big')}, "
                f"not {int.from_bytes(request[2:4], 'big')} / {int.from_bytes(request[4:6], 'big')}")
    if fc == 0x2B and frame[2:4] != request[2:4]:
        return f"MEI {frame[2]:02X} read code {frame[3]:02X}, not {request[2]:02X} {request[3]:02X}"
    return None


class _RtuSerialClient(ModbusSerialClient):
    """pymodbus's serial client (its PDUs, request builders and decoder) with our transaction:
    every request goes through :meth:`RigClient._transact`."""

    def __init__(self, owner: RigClient, *args, **kw):
        super().__init__(*args, **kw)
        self._owner = owner

    def execute(self, no_response_expected: bool, request: ModbusPDU) -> ModbusPDU | None:  # noqa: D102
        return self._owner._transact(request, no_response_expected)

    def connect(self) -> bool:
        """Open the port once with every setting (non-blocking reads: select() waits).

        pymodbus's own connect() reconfigures the port after opening it, which a Linux pty
        refuses (EINVAL) once parity is on."""
        if self.socket:
            return True
        p = self.comm_params
        settings = [(p.parity, p.stopbits)]
        if is_pty(p.host) and p.parity != "N":
            settings.append(("N", 1))
        for parity, stopbits in settings:
            try:
                self.socket = serial.serial_for_url(p.host, baudrate=p.baudrate, bytesize=p.bytesize,
                                                    parity=parity, stopbits=stopbits, timeout=0,
                                                    write_timeout=p.timeout_connect, exclusive=True)
                if parity != p.parity:
                    log.info("%s is a pseudo-terminal that refuses parity %s; a pty carries bytes, "
                             "not characters, so it is opened without", p.host, p.parity)
                return True
            except (OSError, ValueError, termios.error, serial.SerialException) as e:
                log.debug("cannot open %s with parity %s: %s", p.host, parity, e)
                self.socket = None
        return False


def is_pty(port: str) -> bool:
    """Whether `port` is (a link to) a Unix pseudo-terminal: the simulators' serial lines.
    Characters on a pty have no bits on a wire, so parity and stop bits mean nothing there (and
    some kernels refuse PARENB on a pty with EINVAL)."""
    if "://" in port:
        return False
    try:
        real = os.path.realpath(port)
    except OSError:
        return False
    return real.startswith("/dev/pts/") or real == "/dev/ptmx"


def register(space: str, name: str) -> rm.Register:
    """The generated description of register ``name`` in ``space`` ("input" or "holding")."""
    return _REGISTERS[(space, name)]


class InputBlock:
    """Input registers ``first..last`` read in one request; values looked up by register name."""

    def __init__(self, client: RigClient, first: str, last: str) -> None:
        a, b = register("input", first), register("input", last)
        self.base = a.addr
        self.words = client.read_input(a.addr, b.addr + b.words - a.addr)

    def __getitem__(self, name: str) -> int:
        r = register("input", name)
        i = r.addr - self.base
        return join_words(self.words[i:i + r.words])


class DeviceException(RigError):
    """The device answered a Modbus exception."""

    def __init__(self, function: int, code: int, what: str = ""):
        self.function, self.code = function, code
        name = EXCEPTION_NAMES.get(code, "UNKNOWN")
        super().__init__(f"device answered exception {code:02X} ({name}) to FC {function:02X}"
                         + (f" while {what}" if what else ""))


class SequenceRejected(RigError):
    """START refused: the firmware's validation found `error` at `step`."""

    def __init__(self, error: rm.Error, step: int):
        self.error, self.step = error, step
        where = "" if step == rm.STEP_NONE else f" at step {step}"
        super().__init__(f"sequence rejected: {error.name}{where}")


class IncompatibleDevice(RigError):
    """Not a dualscale rig, or a protocol major version this host does not speak."""


class ReportServerIdResponse(ModbusPDU):
    """FC 11 response in the Modbus spec's order: count, server id, run indicator, data.

    pymodbus's own decoder expects the run indicator last; libmodbus/mbpoll and the spec put it
    second, and so does our firmware.
    """

    function_code = 0x11
    rtu_byte_count_pos = 2

    def __init__(self, payload: bytes = b"", dev_id: int = 1, transaction_id: int = 0, status: int = 0):
        super().__init__(transaction_id=transaction_id, dev_id=dev_id, status=status)
        self.payload = payload

    def encode(self) -> bytes:
        return struct.pack(">B", len(self.payload)) + self.payload

    def decode(self, data: bytes) -> None:
        n = data[0]
        if n < 2 or n > len(data) - 1:
            raise ModbusIOException(f"FC 11 byte count {n} does not fit {len(data)} bytes")
        self.payload = bytes(data[1:1 + n])


@dataclass(frozen=True)
class Identity:
    magic: int
    protocol: tuple[int, int]
    firmware: tuple[int, int, int]
    n_leds: int
    n_backlights: int
    max_steps: int
    fifo_depth: int
    server_id: int
    running: bool
    text: str

    @property
    def target(self) -> str:
        for tok in self.text.split():
            if tok.startswith("target="):
                return tok[len("target="):]
        return "?"


@dataclass(frozen=True)
class Status:
    state: rm.State
    error: rm.Error
    error_step: int
    cur_step: int
    seq_crc: int
    uptime_us: int
    polarizer_cdeg: int
    evt_count: int
    evt_first_seq: int
    evt_dropped: int
    frames_ok: int
    frames_bad_crc: int
    frames_bad: int
    watchdog_trips: int
    seq_duration_us: int


@dataclass
class RunResult:
    events: list[Event] = field(default_factory=list)
    state: rm.State = rm.State.IDLE
    error: rm.Error = rm.Error.NONE
    wall_s: float = 0.0
    reconnects: int = 0
    dropped: int = 0  # events the FIFO could not hold during this run (EVT_DROPPED delta)


class RigClient:
    """One Modbus RTU connection to a rig (real or simulated).

    `port` is a device path or any pyserial URL (`socket://host:port` too). `parity` is
    "E", "O" or "N" and `stopbits` 1 or 2 (default: 1 with parity, 2 without; PROTOCOL.md §1).
    `timeout` (s) is the longest wait for one reply; the wait actually used follows the
    measured round trip, never below `min_timeout`, and doubles on every failed attempt
    (up to `timeout`). `retries` bounds the attempts after the first of one request; the step
    table and the event window, which may be written or read again at no cost, get
    `bulk_retries` failures in a row (default 3 x `retries`), in requests that halve after a
    failure and grow back after a success (`chunk_words`). `gap_s` is the silence after
    which a partial or garbled reply counts as corrupt.
    """

    def __init__(self, port: str, address: int = rm.DEFAULT_ADDRESS, baudrate: int = rm.DEFAULT_BAUD,
                 timeout: float = 0.5, retries: int = 5, reconnect_s: float = 5.0,
                 parity: str = DEFAULT_PARITY, stopbits: int | None = None,
                 min_timeout: float = 0.1, gap_s: float = 0.02, bulk_retries: int | None = None):
        self.port, self.address = port, address
        self.parity, self.stopbits = serial_settings(parity, stopbits)
        self.timeout, self.min_timeout = float(timeout), min(float(min_timeout), float(timeout))
        self.retries, self.reconnect_s, self.gap_s = retries, reconnect_s, gap_s
        self.bulk_retries = 3 * retries if bulk_retries is None else bulk_retries
        self._mb = _RtuSerialClient(self, port, framer=FramerType.RTU, baudrate=baudrate,
                                    parity=self.parity, stopbits=self.stopbits,
                                    timeout=timeout, retries=0, reconnect_delay=0.05)
        self._mb.register(ReportServerIdResponse)
        self._decoder = self._mb.framer.decoder
        self._lock = threading.RLock()
        self._last_seq: int | None = None  # SEQ of the last event handed to the caller
        self.reconnects = 0
        self.identity: Identity | None = None
        self.format_mismatch: tuple[str, int] | None = None  # the device's format, when it differs
        self.stats = LinkStats()
        self.last_reply = 0.0  # time.monotonic() of the last reply that fitted its request
        self.chunk_words = STEPS_PER_WRITE * rm.STEP_WORDS  # adaptive bulk request size
        self._srtt: float | None = None  # smoothed round trip (s), Jacobson/Karn
        self._rttvar = 0.0
        self._backoff = 0  # failed attempts in a row: the timeout doubles with each
        self._first_attempt = True
        self._listen_first = False  # the last attempt timed out: its reply may still come

    # ---------------------------------------------------------------- connection
    def open(self) -> Identity:
        """Connect and negotiate (PROTOCOL.md §7). Raises IncompatibleDevice."""
        if not self._mb.connect():
            if "://" not in self.port and not Path(self.port).exists():
                raise InputError(f"cannot open serial port {self.port}: no such device")
            raise RigError(f"cannot open serial port {self.port}")
        self._flush()
        w = InputBlock(self, "MAGIC", "FIFO_DEPTH")
        if w["MAGIC"] != rm.MAGIC:
            raise IncompatibleDevice(f"{self.port}: MAGIC is 0x{w['MAGIC']:04X}, not a dualscale rig")
        major, minor = w["PROTO_VERSION"] >> 8, w["PROTO_VERSION"] & 0xFF
        if major != rm.PROTO_VERSION_MAJOR:
            raise IncompatibleDevice(f"device speaks protocol {major}.{minor}; this host speaks "
                                     f"{rm.PROTO_VERSION_MAJOR}.x")
        if (w["N_LEDS"], w["N_BACKLIGHTS"]) != (rm.N_LEDS, rm.N_BACKLIGHTS):
            raise IncompatibleDevice(f"device has {w['N_LEDS']} LEDs/{w['N_BACKLIGHTS']} back lights; rig.toml "
                                     f"says {rm.N_LEDS}/{rm.N_BACKLIGHTS}")
        self._check_serial_format()
        sid, running, text = self.report_server_id()
        fw = w["FW_VERSION"]
        self.identity = Identity(w["MAGIC"], (major, minor), (fw >> 8, fw & 0xFF, w["FW_PATCH"]), w["N_LEDS"],
                                 w["N_BACKLIGHTS"], w["MAX_STEPS"], w["FIFO_DEPTH"], sid, running, text)
        return self.identity

    def device_serial_format(self) -> tuple[str, int] | None:
        """The device's own (parity letter, stop bits) from SERIAL_PARITY/SERIAL_STOP_BITS, or
        None for firmware without them (exception 02)."""
        try:
            par, sb = self.read_holding(rm.HR.SERIAL_PARITY, 2)
        except DeviceException:
            return None
        return {int(k): v for k, v in PARITY_LETTERS.items()}.get(par, f"?{par}"), sb

    def _check_serial_format(self) -> None:
        """On a real line a format mismatch lets nothing through; on a pty (the simulators)
        everything passes, so say it there: the same settings would fail on the board."""
        dev = self.device_serial_format()
        if dev is not None and dev != (self.parity, self.stopbits):
            log.warning("%s: the rig is set to 8%s%d but this client opens 8%s%d; on a real serial line "
                        "they would not understand each other", self.port, dev[0], dev[1], self.parity,
                        self.stopbits)
            self.format_mismatch = dev

    def close(self) -> None:
        with self._lock:
            self._mb.close()

    def __enter__(self) -> RigClient:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _reconnect(self) -> None:
        self._mb.close()
        deadline = time.monotonic() + self.reconnect_s
        while time.monotonic() < deadline:
            try:
                if self._mb.connect():
                    self.reconnects += 1
                    log.warning("reconnected to %s", self.port)
                    return
            except (OSError, serial.SerialException):
                pass
            time.sleep(0.05)
        raise LinkError(f"lost the serial link to {self.port} and could not reopen it")

    def _flush(self) -> None:
        """Drop whatever late replies sit in the receive buffer."""
        time.sleep(0.01)
        self._drain(listen_s=0.0)

    # ---------------------------------------------------------------- the transaction
    def _serial(self) -> serial.Serial:
        ser = self._mb.socket
        if ser is None:
            raise ConnectionException(f"{self.port} is closed")
        return ser

    def _drain(self, listen_s: float) -> None:
        """Discard every byte on the line; with `listen_s`, until the line has been quiet that
        long (a reply to a timed-out request may still be on its way)."""
        ser = self._serial()
        quiet_since = time.monotonic()
        while True:
            n = ser.in_waiting
            if n:
                self.stats.drained_bytes += len(ser.read(n))
                quiet_since = time.monotonic()
                continue
            left = listen_s - (time.monotonic() - quiet_since)
            if left <= 0 or not select.select([ser.fileno()], [], [], left)[0]:
                return

    def rto(self) -> float:
        """The reply timeout of the next attempt (s): smoothed round trip + 4 deviations, at
        least `min_timeout`, doubled per failed attempt in a row, at most `timeout`."""
        base = self.timeout if self._srtt is None else self._srtt + 4.0 * self._rttvar
        return min(self.timeout, max(self.min_timeout, base) * (2 ** min(self._backoff, 16)))

    def _frame_size(self, buf: bytes, i: int) -> int:
        """The length of the RTU frame that would start at buf[i] (0 if unknown)."""
        try:
            cls = self._decoder.lookupPduClass(buf[i:])
            return int(cls.calculateRtuFrameSize(buf[i:])) if cls else 0
        except Exception:  # noqa: BLE001 - a garbled header: no frame starts here
            return 0

    def _transact(self, req: ModbusPDU, no_response_expected: bool = False) -> ModbusPDU | None:
        """Send one request and return the reply that fits it (see `reply_mismatch`)."""
        with self._lock:
            ser = self._serial()
            try:
                self._drain(self.gap_s * 2 if self._listen_first else 0.0)
                frame = self._mb.framer.buildFrame(req)
                self.stats.requests += 1
                if not self._first_attempt:
                    self.stats.retries += 1
                t0 = time.monotonic()
                ser.write(frame)
                if no_response_expected or frame[0] == 0:  # broadcast: never answered
                    return None
                return self._receive(ser, frame, t0)
            except (serial.SerialException, OSError) as e:
                raise ConnectionException(f"{self.port}: {e}") from e

    def _receive(self, ser: serial.Serial, request: bytes, t0: float) -> ModbusPDU:
        rto = self.rto()
        deadline, buf, last_rx = t0 + rto, b"", None
        fd = ser.fileno()
        while True:
            i = 0
            while i + 4 <= len(buf):
                size = self._frame_size(buf, i)
                if size and i + size > len(buf) and buf[i] == request[0]:
                    # a frame from our server is still arriving: wait for the rest rather than look
                    # for frames inside it (5 data bytes ff ff 00 00 00 pass as an exception frame
                    # with a valid CRC, and cutting the buffer there broke every status read)
                    break
                if not size or i + size > len(buf) or not _crc_ok(buf[i:i + size]):
                    i += 1
                    continue
                frame = buf[i:i + size]
                why = reply_mismatch(request, frame)
                if why is None:
                    pdu = self._decoder.decode(frame[1:-2])
                    if pdu is None:
                        raise ModbusIOException(f"undecodable reply {frame.hex()}")
                    pdu.dev_id = frame[0]
                    self._on_reply(time.monotonic() - t0)
                    return pdu
                self.stats.stale += 1
                log.info("discarded a frame that is not the reply (%s): %s", why, frame.hex())
                buf, i = buf[i + size:], 0
            now = time.monotonic()
            if now >= deadline:
                self._listen_first = True
                self.stats.timeouts += 1
                raise _NoReply(f"no reply within {rto * 1e3:.0f} ms"
                               + (f" ({len(buf)} bytes that are no frame)" if buf else ""))
            wait = deadline - now
            if buf and last_rx is not None:
                quiet = now - last_rx
                # a frame whose own header says more bytes are coming is slow, not corrupted: QEMU's
                # USART model stalls mid-frame on a loaded host (a CI run saw 27 of 43 bytes, then
                # a gap); it waits on, up to the deadline
                head = self._frame_size(buf, 0) if len(buf) >= 3 and buf[0] == request[0] else 0
                if quiet >= self.gap_s and not (head and len(buf) < head):  # silence, no valid frame: corrupted
                    self.stats.bad_frames += 1
                    self._listen_first = True
                    raise _NoReply(f"a corrupted reply ({len(buf)} bytes, bad CRC or framing)", corrupt=True)
                if quiet < self.gap_s:
                    wait = min(wait, self.gap_s - quiet)
            if select.select([fd], [], [], max(wait, 0.0))[0]:
                chunk = ser.read(max(1, ser.in_waiting))
                if chunk:
                    buf, last_rx = buf + chunk, time.monotonic()
                elif not ser.in_waiting and "://" not in self.port:
                    # readable with nothing to read: the other end is gone
                    raise ConnectionException(f"{self.port}: the line hung up")

    def _on_reply(self, rtt: float) -> None:
        self.stats.replies += 1
        self.last_reply = time.monotonic()
        self._listen_first = False
        if self._first_attempt:  # Karn: a retried request's round trip is ambiguous
            if self._srtt is None:
                self._srtt, self._rttvar = rtt, rtt / 2
            else:
                self._rttvar = 0.75 * self._rttvar + 0.25 * abs(self._srtt - rtt)
                self._srtt = 0.875 * self._srtt + 0.125 * rtt

    def _call(self, what: str, fn: Callable[..., ModbusPDU], *args, retries: int | None = None,
              **kw) -> ModbusPDU:
        """One request with at most `retries` (default `self.retries`) more attempts; a dead port
        is reopened. A Modbus exception reply becomes DeviceException; no fitting reply after
        every attempt, LinkError."""
        n = self.retries if retries is None else retries
        last: Exception | None = None
        with self._lock:
            for attempt in range(n + 1):
                self._first_attempt = attempt == 0
                try:
                    if not self._mb.connected:
                        self._reconnect()
                    rr = fn(*args, device_id=self.address, **kw)
                except _NoReply as e:
                    last = e
                    self._backoff += 1
                    log.debug("%s failed (attempt %d): %s", what, attempt + 1, e)
                    continue
                except (ConnectionException, OSError, serial.SerialException) as e:
                    last = e
                    log.debug("%s failed (attempt %d): %s", what, attempt + 1, e)
                    try:
                        self._reconnect()
                    except RigError as e2:
                        last = e2
                    continue
                except ModbusException as e:
                    raise RigError(f"{what}: {e}") from e
                finally:
                    self._first_attempt = True
                self._backoff = 0
                if rr is not None and rr.isError():
                    raise DeviceException(rr.function_code & 0x7F, getattr(rr, "exception_code", 0), what)
                return rr
        raise LinkError(f"no answer from the rig at {self.port} while {what} "
                        f"({n + 1} attempt{'s' if n else ''}): {last}")

    def _shrink(self) -> None:
        if self.chunk_words > MIN_CHUNK_WORDS:
            self.chunk_words = max(MIN_CHUNK_WORDS, self.chunk_words // 2)
            self.stats.chunk_shrinks += 1

    def _grow(self) -> None:
        self.chunk_words = min(STEPS_PER_WRITE * rm.STEP_WORDS, self.chunk_words + CHUNK_GROW_WORDS)

    def _repeatable(self, what: str, attempt: Callable[[], object]) -> object:
        """`attempt()` (one request, no retries of its own) repeated until it succeeds, at most
        `bulk_retries` failures in a row; the bulk request size (`chunk_words`, which
        `attempt` reads) is halved after each failure and grows by CHUNK_GROW_WORDS after
        a success. Only for requests that may be repeated at no cost (step-table writes, event
        window reads)."""
        for fails in range(self.bulk_retries + 1):
            try:
                out = attempt()
            except LinkError:
                if fails == self.bulk_retries:
                    raise
                self._shrink()
                log.debug("%s: attempt failed, bulk size now %d words", what, self.chunk_words)
                continue
            self._grow()
            return out
        raise LinkError(f"{what}: no attempt left")  # pragma: no cover - the loop returns or raises

    # ---------------------------------------------------------------- raw access
    def _read_registers(self, space: str, fn: Callable[..., ModbusPDU], addr: int, count: int) -> list[int]:
        """Read `count` registers, in requests of at most 125 (each one a consistent snapshot)."""
        out: list[int] = []
        for a in range(addr, addr + count, MAX_READ):
            n = min(MAX_READ, addr + count - a)
            regs = self._call(f"reading {space} registers {a}+{n}", fn, a, count=n).registers
            if len(regs) != n:  # reply_mismatch checked the byte count: cannot happen
                raise RigError(f"reading {space} registers {a}+{n}: got {len(regs)} registers")
            out += regs
        return out

    def read_input(self, addr: int, count: int) -> list[int]:
        return self._read_registers("input", self._mb.read_input_registers, addr, count)

    def read_holding(self, addr: int, count: int) -> list[int]:
        return self._read_registers("holding", self._mb.read_holding_registers, addr, count)

    @staticmethod
    def _check_words(values: Sequence[int]) -> None:
        bad = [v for v in values if not 0 <= int(v) <= WORD_MAX]
        if bad:
            raise InputError(f"register values must be 0..{WORD_MAX}, got {bad[0]}")

    def write_register(self, addr: int, value: int, retries: int | None = None) -> None:
        self._check_words([value])
        self._call(f"writing holding register {addr}", self._mb.write_register, addr, value, retries=retries)

    def write_registers(self, addr: int, values: Sequence[int], retries: int | None = None) -> None:
        self._check_words(values)
        self._call(f"writing holding registers {addr}+{len(values)}", self._mb.write_registers,
                   addr, list(values), retries=retries)

    def read_coils(self, addr: int, count: int) -> list[bool]:
        return list(self._call(f"reading coils {addr}+{count}", self._mb.read_coils,
                               addr, count=count).bits[:count])

    def write_coil(self, addr: int, on: bool) -> None:
        self._call(f"writing coil {addr}", self._mb.write_coil, addr, bool(on))

    def report_server_id(self) -> tuple[int, bool, str]:
        """FC 11: (server id, run indicator, identification string)."""
        p = self._call("reporting the server id", self._mb.report_device_id).payload
        return p[0], p[1] == 0xFF, p[2:].decode("ascii", "replace")

    def device_identification(self, read_code: int = 2) -> dict[int, str]:
        """FC 2B/0E objects, by object id."""
        rr = self._call("reading device identification", self._mb.read_device_information,
                        read_code=read_code, object_id=0)
        return {k: (v.decode() if isinstance(v, bytes) else v) for k, v in rr.information.items()}

    def keep_alive(self) -> None:
        """One short request (STATE): any valid frame feeds the host watchdog (PROTOCOL.md §5)."""
        self.read_input(rm.IR.STATE, 1)

    # ---------------------------------------------------------------- state
    def status(self) -> Status:
        w = InputBlock(self, "STATE", "SEQ_DURATION_US")
        return Status(rm.State(w["STATE"]), rm.Error(w["ERROR"]), w["ERROR_STEP"], w["CUR_STEP"], w["SEQ_CRC"],
                      w["UPTIME_US"], w["POLARIZER_NOW"], w["EVT_COUNT"], w["EVT_FIRST_SEQ"], w["EVT_DROPPED"],
                      w["FRAMES_OK"], w["FRAMES_BAD_CRC"], w["FRAMES_BAD"], w["WATCHDOG_TRIPS"],
                      w["SEQ_DURATION_US"])

    def _change_state(self, cmd: rm.Command, took_effect: Callable[[Status], bool]) -> None:
        """Write COMMAND = `cmd`; when an attempt's reply is lost, read the status before trying
        again, and stop as soon as `took_effect(status)` says the earlier attempt worked. A
        refusal (exception) after a lost reply is checked the same way (START answers BUSY
        when the lost START is running)."""
        what = f"writing COMMAND = {cmd.name}"
        lost: Exception | None = None
        for _attempt in range(self.retries + 1):
            try:
                self.write_register(rm.HR.COMMAND, int(cmd), retries=0)
                return
            except DeviceException:
                if lost is None:
                    raise
                if took_effect(self.status()):
                    self.stats.confirmed_by_status += 1
                    log.info("%s: the reply was lost, but the status shows it took effect", what)
                    return
                raise
            except LinkError as e:
                lost = e
                if took_effect(self.status()):
                    self.stats.confirmed_by_status += 1
                    log.info("%s: the reply was lost, but the status shows it took effect", what)
                    return
        raise LinkError(f"no answer from the rig at {self.port} while {what} "
                        f"({self.retries + 1} attempts): {lost}")

    def command(self, cmd: rm.Command) -> None:
        """Write COMMAND; START, ABORT and CLEAR_ERROR are retried only after the status shows
        that a lost attempt did not take effect (see `start`, `abort`, `clear_error`)."""
        cmd = rm.Command(cmd)
        if cmd == rm.Command.START:
            self._start_command()
        elif cmd == rm.Command.ABORT:
            self.abort()
        elif cmd == rm.Command.CLEAR_ERROR:
            self.clear_error()
        else:  # NONE, ALL_OFF, CLEAR_EVENTS: repeating them changes nothing more
            self.write_register(rm.HR.COMMAND, int(cmd))

    def all_off(self) -> None:
        self.command(rm.Command.ALL_OFF)

    def abort(self) -> None:
        """ABORT (always accepted). Done when the state is neither ARMED nor RUNNING."""
        self._change_state(rm.Command.ABORT, lambda st: st.state not in ACTIVE)

    def clear_error(self) -> None:
        """CLEAR_ERROR. Done when ERROR is NONE and the state is not FAULT."""
        self._change_state(rm.Command.CLEAR_ERROR,
                           lambda st: st.error == rm.Error.NONE and st.state != rm.State.FAULT)

    def set_watchdog(self, ms: int) -> None:
        self.write_register(rm.HR.WATCHDOG_MS, ms)

    def watchdog_ms(self) -> int:
        """The device's WATCHDOG_MS (0 = off)."""
        return self.read_holding(rm.HR.WATCHDOG_MS, 1)[0]

    def set_polarizer(self, cdeg: int) -> None:
        self.write_register(rm.HR.POLARIZER_CDEG, cdeg)

    def set_intensity(self, value: int) -> None:
        self.write_register(rm.HR.MANUAL_INTENSITY, value)

    @staticmethod
    def coil_address(source: rm.Source, index: int = 0) -> int:
        base, n = {rm.Source.LED: (rm.Coil.LED, rm.N_LEDS),
                   rm.Source.BACKLIGHT: (rm.Coil.BACKLIGHT, rm.N_BACKLIGHTS),
                   rm.Source.DIFFUSE: (rm.Coil.DIFFUSE, rm.N_DIFFUSE)}[rm.Source(source)]
        if not 0 <= index < n:
            raise InputError(f"{rm.Source(source).name} index {index} outside 0..{n - 1}")
        return base + index

    def set_light(self, source: rm.Source, index: int, on: bool) -> None:
        self.write_coil(self.coil_address(source, index), on)

    def lights_on(self) -> list[tuple[rm.Source, int]]:
        """Every light that is on now (manual or sequencer)."""
        leds = self.read_coils(rm.Coil.LED, rm.N_LEDS)
        back = self.read_coils(rm.Coil.BACKLIGHT, rm.N_BACKLIGHTS)
        diff = self.read_coils(rm.Coil.DIFFUSE, rm.N_DIFFUSE)
        return ([(rm.Source.LED, i) for i, b in enumerate(leds) if b]
                + [(rm.Source.BACKLIGHT, i) for i, b in enumerate(back) if b]
                + [(rm.Source.DIFFUSE, i) for i, b in enumerate(diff) if b])

    # ---------------------------------------------------------------- sequences
    def upload(self, steps: Sequence[Step]) -> float:
        """Write the step table in FC 10 chunks (adaptive: see `_repeatable`), set SEQ_LEN and verify
        SEQ_CRC. Returns seconds."""
        if len(steps) > rm.MAX_STEPS:
            raise InputError(f"{len(steps)} steps; the device holds {rm.MAX_STEPS}")
        t0 = time.perf_counter()
        words = encode(steps)

        off = 0
        while off < len(words):
            def write() -> int:
                n = min(len(words) - off, max(1, self.chunk_words // rm.STEP_WORDS) * rm.STEP_WORDS)
                self.write_registers(rm.STEP_TABLE_ADDR + off, words[off:off + n], retries=0)
                return n

            off += self._repeatable("uploading the step table", write)
        self.write_register(rm.HR.SEQ_LEN, len(steps))
        crc = self.read_input(rm.IR.SEQ_CRC, 1)[0]
        if crc != seq_crc(steps):
            raise RigError(f"upload verification failed: device CRC 0x{crc:04X}, "
                           f"expected 0x{seq_crc(steps):04X}")
        return time.perf_counter() - t0

    def _next_seq(self, st: Status) -> int:
        return (st.evt_first_seq + st.evt_count) & WORD_MAX

    def _start_command(self) -> None:
        """COMMAND = START, retried only when the status shows the lost attempt did not start
        the sequence: the state is ARMED/RUNNING, or a SEQ_START event (or a dropped event)
        came after the snapshot taken before the first attempt."""
        before = self.status()
        n0, d0 = self._next_seq(before), before.evt_dropped

        def started(st: Status) -> bool:
            if st.state in ACTIVE or st.evt_dropped != d0:
                return True
            new = (self._next_seq(st) - n0) & WORD_MAX
            if not new:
                return False
            k = min(st.evt_count, rm.EVT_WINDOW_COUNT)
            window = decode_window(self.read_input(rm.IR.EVT_WINDOW, k * rm.EVENT_WORDS), k) if k else []
            return any(e.kind == rm.Event.SEQ_START and ((e.seq - n0) & WORD_MAX) < new for e in window)

        self._change_state(rm.Command.START, started)

    def start(self, mode: rm.TriggerMode = rm.TriggerMode.DEVICE_MASTER) -> None:
        """Select the trigger mode and START. Raises SequenceRejected with the firmware's reason.

        A START whose reply is lost is not simply repeated (a repeat would answer BUSY, or run a
        short sequence twice): the status says whether it took effect (see `_start_command`)."""
        self.write_register(rm.HR.TRIGGER_MODE, int(mode))
        try:
            self._start_command()
        except DeviceException as e:
            if e.code != ExceptionCode.ILLEGAL_DATA_VALUE:  # the validation's refusal (PROTOCOL.md §3)
                raise
            st = self.status()
            raise SequenceRejected(st.error, st.error_step) from e

    def sync_events(self) -> None:
        """Forget events already pending (e.g. from before this session): ack them all."""
        self.command(rm.Command.CLEAR_EVENTS)
        self._last_seq = None

    def poll_events(self) -> list[Event]:
        """Every event pending since the last call, oldest first; acks what was handed over.

        Each round writes EVT_ACK (the last SEQ we kept), then reads the window (as many events as
        the adaptive request size allows); rounds repeat while a read came back full, so a small
        request size on a noisy link never leaves pending events for a later call.  A lost
        response only means the same events come back; they are dropped by SEQ.
        """
        fresh: list[Event] = []
        for _round in range(rm.FIFO_DEPTH + 1):
            batch, full = self._poll_round()
            fresh += batch
            if not full or not batch:
                break
        return fresh

    def _poll_round(self) -> tuple[list[Event], bool]:
        """One ack + window read: ``(fresh events, whether the window read was full)``."""
        if self._last_seq is not None:
            self.write_register(rm.HR.EVT_ACK, self._last_seq)
        asked = [0]

        def read() -> list[int]:
            k = max(1, min(rm.EVT_WINDOW_COUNT, self.chunk_words // rm.EVENT_WORDS))
            asked[0] = k
            return self._call(f"reading the event window ({k} events)", self._mb.read_input_registers,
                              rm.IR.EVT_WINDOW, count=k * rm.EVENT_WORDS, retries=0).registers

        words = self._repeatable("reading the event window", read)
        events = [e for e in decode_window(words, len(words) // rm.EVENT_WORDS) if e.kind != rm.Event.NONE]
        fresh = []
        for e in events:
            if self._last_seq is None or 0 < ((e.seq - self._last_seq) & WORD_MAX) <= WORD_MAX // 2:
                fresh.append(e)
                self._last_seq = e.seq
        return fresh, len(events) >= asked[0] and asked[0] < rm.EVT_WINDOW_COUNT

    def _arm_watchdog(self, watchdog_ms: int | None) -> tuple[int, int]:
        """Set WATCHDOG_MS for a run: `watchdog_ms`, or the device's own value when that is
        shorter and on. Returns (previous, used)."""
        prev = self.watchdog_ms()
        if not watchdog_ms:
            return prev, prev
        use = prev if 0 < prev <= watchdog_ms else max(rm.WATCHDOG_MS_MIN, min(rm.WATCHDOG_MS_MAX, watchdog_ms))
        if use != prev:
            self.set_watchdog(use)
        return prev, use

    def _after_link_error(self, err: Exception, watchdog_ms: int) -> RigError:
        """The link failed during a run: abort the sequence if the rig can be reached within
        the watchdog period; otherwise the watchdog has stopped it. Returns the error to raise."""
        deadline = time.monotonic() + max(watchdog_ms, 0) / 1e3
        while True:
            try:
                self.abort()
                st = self.status()
                return LinkError(f"{err}; the sequence was aborted (state {st.state.name})")
            except RigError as e2:
                if time.monotonic() >= deadline:
                    if watchdog_ms:
                        return LinkError(f"{err}; the rig is unreachable, and its host watchdog "
                                         f"({watchdog_ms} ms) has switched every light off and stopped "
                                         f"the sequence (state FAULT, ERROR WATCHDOG): {e2}")
                    return LinkError(f"{err}; the rig is unreachable and its watchdog is off: the "
                                     f"sequence may still be running: {e2}")

    def run(self, steps: Sequence[Step] | None = None, mode: rm.TriggerMode = rm.TriggerMode.DEVICE_MASTER,
            on_event: Callable[[Event], None] | None = None, timeout_s: float = 600.0,
            poll_s: float = 0.01, state_check_s: float = 0.25,
            watchdog_ms: int | None = DEFAULT_WATCHDOG_MS) -> RunResult:
        """Upload (if `steps`), START, and follow the FIFO until the sequence ends.

        The end is the terminal event (SEQ_DONE, SEQ_ABORT, FAULT), or, should that event have
        been dropped by a full FIFO, the device's STATE leaving ARMED/RUNNING with nothing
        pending; `RunResult.dropped` then says how many events were lost.

        The host watchdog guards the run: WATCHDOG_MS is set to `watchdog_ms` (device ms; None
        or 0 leaves the device's setting) unless the device's own is shorter, the polling feeds
        it (`on_event` must return well within it), and the earlier value is restored when the
        run ends. If this host dies, every light is off within `watchdog_ms`. On a link error
        the sequence is aborted (or, the rig unreachable, left to the watchdog) and LinkError
        says which; Ctrl-C aborts it too.
        """
        if steps is not None:
            self.upload(steps)
        prev, wd = self._arm_watchdog(watchdog_ms)
        res = self._follow(mode, on_event, timeout_s, poll_s, state_check_s, wd)
        if wd != prev:
            self.set_watchdog(prev)
        return res

    def _follow(self, mode: rm.TriggerMode, on_event: Callable[[Event], None] | None, timeout_s: float,
                poll_s: float, state_check_s: float, wd: int) -> RunResult:
        self.sync_events()
        res = RunResult()
        r0, d0 = self.reconnects, self.status().evt_dropped
        t0 = last_check = time.monotonic()
        self.start(mode)
        ended = {rm.Event.SEQ_DONE, rm.Event.SEQ_ABORT, rm.Event.FAULT}
        try:
            while True:
                batch = self.poll_events()
                for e in batch:
                    res.events.append(e)
                    if on_event:
                        on_event(e)
                if any(e.kind in ended for e in batch):
                    res.events += self.poll_events()  # what follows the terminal event, then ack it
                    self.poll_events()
                    break
                now = time.monotonic()
                if not batch and now - last_check > state_check_s:
                    last_check = now
                    st = self.status()
                    if st.state not in ACTIVE and st.evt_count == 0:
                        log.warning("sequence ended without its terminal event (%d events dropped)", st.evt_dropped)
                        break
                if now - t0 > timeout_s:
                    self.abort()
                    raise RigError(f"sequence did not finish within {timeout_s} s (aborted)")
                if not batch:
                    time.sleep(poll_s)
        except LinkError as e:
            raise self._after_link_error(e, wd) from e
        except KeyboardInterrupt:
            try:
                self.abort()
            except RigError:
                pass
            raise
        st = self.status()
        res.state, res.error, res.dropped = st.state, st.error, st.evt_dropped - d0
        res.wall_s = time.monotonic() - t0
        res.reconnects = self.reconnects - r0
        return res


ACTIVE = frozenset({rm.State.ARMED, rm.State.RUNNING})
