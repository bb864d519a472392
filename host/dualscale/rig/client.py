"""Typed Modbus RTU client for the rig (pymodbus, pinned minor version).

The client checks the device's identity and protocol version on `open()`, uploads sequences
in chunks and verifies them by CRC, runs them, and follows the event FIFO with the idempotent
ack of PROTOCOL.md §4. Every request goes through `_call`, which reopens the serial port after
a drop and retries, so a run survives an unplugged cable without losing or repeating events.
"""
from __future__ import annotations

from dualscale.errors import InputError, RigError

import logging
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path

import serial
from pymodbus import FramerType, ModbusException
from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ConnectionException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from ..protocol import regmap as rm
from .events import Event, decode_window
from .sequence import Step, encode, join_words, seq_crc

log = logging.getLogger(__name__)



class ExceptionCode(IntEnum):
    """Modbus exception codes the firmware answers (Modbus Application Protocol v1.1b3, §7)."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03  # also: START refused by the sequence validation (PROTOCOL.md §3)
    SERVER_DEVICE_FAILURE = 0x04
    SERVER_DEVICE_BUSY = 0x06


EXCEPTION_NAMES = {int(c): c.name.replace("_", " ") for c in ExceptionCode}
# Function code of each pymodbus call: RTU has no transaction id, so a reply that arrives after
# its request timed out would otherwise be taken as the answer to the next request.
FC_OF = {"read_coils": 0x01, "read_discrete_inputs": 0x02, "read_holding_registers": 0x03,
         "read_input_registers": 0x04, "write_coil": 0x05, "write_register": 0x06, "write_coils": 0x0F,
         "write_registers": 0x10, "report_device_id": 0x11, "readwrite_registers": 0x17,
         "read_device_information": 0x2B}
MAX_READ = 125
MAX_WRITE = 123
STEPS_PER_WRITE = MAX_WRITE // rm.STEP_WORDS  # 12 steps per FC 10
WORD_MAX = 0xFFFF  # a Modbus register holds 16 bits
_REGISTERS = {(r.space, r.name): r for r in rm.REGISTERS}


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

    `port` is a device path or any pyserial URL (`socket://host:port` too).
    """

    def __init__(self, port: str, address: int = rm.DEFAULT_ADDRESS, baudrate: int = rm.DEFAULT_BAUD,
                 timeout: float = 0.5, retries: int = 3, reconnect_s: float = 5.0):
        self.port, self.address = port, address
        self.retries, self.reconnect_s = retries, reconnect_s
        self._mb = ModbusSerialClient(port, framer=FramerType.RTU, baudrate=baudrate,
                                      timeout=timeout, retries=0, reconnect_delay=0.05)
        self._mb.register(ReportServerIdResponse)
        self._last_seq: int | None = None  # SEQ of the last event handed to the caller
        self.reconnects = 0
        self.identity: Identity | None = None

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
        sid, running, text = self.report_server_id()
        fw = w["FW_VERSION"]
        self.identity = Identity(w["MAGIC"], (major, minor), (fw >> 8, fw & 0xFF, w["FW_PATCH"]), w["N_LEDS"],
                                 w["N_BACKLIGHTS"], w["MAX_STEPS"], w["FIFO_DEPTH"], sid, running, text)
        return self.identity

    def close(self) -> None:
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
        raise RigError(f"lost the serial link to {self.port} and could not reopen it")

    def _flush(self) -> None:
        """Drop whatever late replies sit in the receive buffer."""
        time.sleep(0.01)
        sock = getattr(self._mb, "socket", None)
        if sock is not None and hasattr(sock, "reset_input_buffer"):
            sock.reset_input_buffer()

    def _call(self, what: str, fn: Callable[..., ModbusPDU], *args, **kw) -> ModbusPDU:
        """One request with retries; a dead port is reopened. Exceptions become DeviceException."""
        last: Exception | None = None
        for attempt in range(self.retries + 1):
            try:
                if not self._mb.connected:
                    self._reconnect()
                rr = fn(*args, device_id=self.address, **kw)
            except (ModbusIOException, ConnectionException, OSError, serial.SerialException) as e:
                last = e
                log.debug("%s failed (attempt %d): %s", what, attempt + 1, e)
                if isinstance(e, ModbusIOException):
                    self._flush()
                if isinstance(e, (ConnectionException, OSError, serial.SerialException)) or \
                        "closed" in str(e).lower():
                    try:
                        self._reconnect()
                    except RigError as e2:
                        last = e2
                continue
            except ModbusException as e:
                raise RigError(f"{what}: {e}") from e
            if (rr.function_code & 0x7F) != FC_OF.get(fn.__name__, rr.function_code & 0x7F):
                last = RigError(f"stale reply FC {rr.function_code:02X} while {what}")
                self._flush()
                continue
            if rr.isError():
                raise DeviceException(rr.function_code & 0x7F, getattr(rr, "exception_code", 0), what)
            return rr
        raise RigError(f"no answer from the rig at {self.port} while {what}: {last}")

    # ---------------------------------------------------------------- raw access
    def _read_registers(self, space: str, fn: Callable[..., ModbusPDU], addr: int, count: int) -> list[int]:
        """Read `count` registers, in requests of at most 125."""
        out: list[int] = []
        for a in range(addr, addr + count, MAX_READ):
            n = min(MAX_READ, addr + count - a)
            out += self._call(f"reading {space} registers {a}+{n}", fn, a, count=n).registers
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

    def write_register(self, addr: int, value: int) -> None:
        self._check_words([value])
        self._call(f"writing holding register {addr}", self._mb.write_register, addr, value)

    def write_registers(self, addr: int, values: Sequence[int]) -> None:
        self._check_words(values)
        self._call(f"writing holding registers {addr}+{len(values)}", self._mb.write_registers,
                   addr, list(values))

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

    # ---------------------------------------------------------------- state
    def status(self) -> Status:
        w = InputBlock(self, "STATE", "SEQ_DURATION_US")
        return Status(rm.State(w["STATE"]), rm.Error(w["ERROR"]), w["ERROR_STEP"], w["CUR_STEP"], w["SEQ_CRC"],
                      w["UPTIME_US"], w["POLARIZER_NOW"], w["EVT_COUNT"], w["EVT_FIRST_SEQ"], w["EVT_DROPPED"],
                      w["FRAMES_OK"], w["FRAMES_BAD_CRC"], w["FRAMES_BAD"], w["WATCHDOG_TRIPS"],
                      w["SEQ_DURATION_US"])

    def command(self, cmd: rm.Command) -> None:
        self.write_register(rm.HR.COMMAND, int(cmd))

    def all_off(self) -> None:
        self.command(rm.Command.ALL_OFF)

    def abort(self) -> None:
        self.command(rm.Command.ABORT)

    def clear_error(self) -> None:
        self.command(rm.Command.CLEAR_ERROR)

    def set_watchdog(self, ms: int) -> None:
        self.write_register(rm.HR.WATCHDOG_MS, ms)

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
        """Write the step table in FC 10 chunks, set SEQ_LEN and verify SEQ_CRC. Returns seconds."""
        if len(steps) > rm.MAX_STEPS:
            raise InputError(f"{len(steps)} steps; the device holds {rm.MAX_STEPS}")
        t0 = time.perf_counter()
        words = encode(steps)
        per = STEPS_PER_WRITE * rm.STEP_WORDS
        for off in range(0, len(words), per):
            self.write_registers(rm.STEP_TABLE_ADDR + off, words[off:off + per])
        self.write_register(rm.HR.SEQ_LEN, len(steps))
        crc = self.read_input(rm.IR.SEQ_CRC, 1)[0]
        if crc != seq_crc(steps):
            raise RigError(f"upload verification failed: device CRC 0x{crc:04X}, "
                           f"expected 0x{seq_crc(steps):04X}")
        return time.perf_counter() - t0

    def start(self, mode: rm.TriggerMode = rm.TriggerMode.DEVICE_MASTER) -> None:
        """Select the trigger mode and START. Raises SequenceRejected with the firmware's reason."""
        self.write_register(rm.HR.TRIGGER_MODE, int(mode))
        try:
            self.command(rm.Command.START)
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
        """New events since the last call, oldest first; acks what was handed over.

        Write EVT_ACK (the last SEQ we kept), then read the window. A lost response only means
        the same events come back next time; they are dropped by SEQ.
        """
        n = rm.EVT_WINDOW_COUNT * rm.EVENT_WORDS
        if self._last_seq is not None:
            self.write_register(rm.HR.EVT_ACK, self._last_seq)
        words = self.read_input(rm.IR.EVT_WINDOW, n)
        events = [e for e in decode_window(words, rm.EVT_WINDOW_COUNT) if e.kind != rm.Event.NONE]
        fresh = []
        for e in events:
            if self._last_seq is None or 0 < ((e.seq - self._last_seq) & WORD_MAX) <= WORD_MAX // 2:
                fresh.append(e)
                self._last_seq = e.seq
        return fresh

    def run(self, steps: Sequence[Step] | None = None, mode: rm.TriggerMode = rm.TriggerMode.DEVICE_MASTER,
            on_event: Callable[[Event], None] | None = None, timeout_s: float = 600.0,
            poll_s: float = 0.01, state_check_s: float = 0.25) -> RunResult:
        """Upload (if `steps`), START, and follow the FIFO until the sequence ends.

        The end is the terminal event (SEQ_DONE, SEQ_ABORT, FAULT), or, should that event have
        been dropped by a full FIFO, the device's STATE leaving ARMED/RUNNING with nothing
        pending; `RunResult.dropped` then says how many events were lost.
        """
        if steps is not None:
            self.upload(steps)
        self.sync_events()
        res = RunResult()
        r0, d0 = self.reconnects, self.status().evt_dropped
        t0 = last_check = time.monotonic()
        self.start(mode)
        ended = {rm.Event.SEQ_DONE, rm.Event.SEQ_ABORT, rm.Event.FAULT}
        active = {rm.State.ARMED, rm.State.RUNNING}
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
                if st.state not in active and st.evt_count == 0:
                    log.warning("sequence ended without its terminal event (%d events dropped)", st.evt_dropped)
                    break
            if now - t0 > timeout_s:
                self.abort()
                raise RigError(f"sequence did not finish within {timeout_s} s (aborted)")
            if not batch:
                time.sleep(poll_s)
        st = self.status()
        res.state, res.error, res.dropped = st.state, st.error, st.evt_dropped - d0
        res.wall_s = time.monotonic() - t0
        res.reconnects = self.reconnects - r0
        return res
