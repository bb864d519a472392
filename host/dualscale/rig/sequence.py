"""Sequence steps, capture plans, the step-table encoding and the device-master schedule.

Units: times in microseconds, polarizer angles in centidegrees (P0 = 0, P90 = 9000).
The word layout and timing rules are PROTOCOL.md §3; the constants (word offsets
``rm.StepWord``, ``rm.POL_KEEP``, ``rm.MAX_BRACKETS``...) come from the generated regmap, so
this module cannot drift from the firmware.  A field's width is the distance to the next
offset (u32 fields span two words, big-endian by word).
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from dualscale.errors import InputError

from ..protocol import regmap as rm
from ..protocol.crc import crc16

_OFFSETS = sorted((v, k) for k, v in vars(rm.StepWord).items() if k.isupper())
STEP_FIELDS: dict[str, tuple[int, int]] = {
    name: (off, (_OFFSETS[i + 1][0] if i + 1 < len(_OFFSETS) else rm.STEP_WORDS) - off)
    for i, (off, name) in enumerate(_OFFSETS)}
"""``name -> (word offset, word count)`` of each field of a step (from ``rm.StepWord``)."""
BYTE = 8  # SOURCE = kind << 8 | index, BRACKETS = ev_step << 8 | count (PROTOCOL.md §3)
MICRO_TRIGGER = 1 << rm.TRIGGER_NAMES.index("micro")  # the TRIGGERS bit of the micro camera


WORD_BITS = 16


def split_words(value: int, n: int) -> list[int]:
    """``value`` as ``n`` register words, big-endian by word (registers.toml conventions)."""
    mask = (1 << WORD_BITS) - 1
    return [(value >> (WORD_BITS * (n - 1 - i))) & mask for i in range(n)]


def join_words(words: Sequence[int]) -> int:
    """The value of a multi-word field, big-endian by word."""
    v = 0
    for x in words:
        v = (v << WORD_BITS) | int(x)
    return v


def _put(words: list[int], name: str, value: int) -> None:
    off, n = STEP_FIELDS[name]
    words[off:off + n] = split_words(value, n)


def _get(words: Sequence[int], name: str) -> int:
    off, n = STEP_FIELDS[name]
    return join_words(words[off:off + n])


@dataclass(frozen=True)
class Step:
    """One step of the sequence table (PROTOCOL.md §3)."""

    source: rm.Source
    index: int = 0
    intensity: int = 0
    polarizer_cdeg: int | None = None  # None = keep
    settle_us: int = 0
    exposure_us: int = 1000
    pulse_us: int = 0  # 0 = gate mode
    brackets: int = 1
    ev_step: int = 0
    triggers: int = 0

    def bracket_exposures(self) -> list[int]:
        """Exposure of each HDR bracket in µs: exposure << (k * ev_step)."""
        return [self.exposure_us << (k * self.ev_step) for k in range(self.brackets)]

    def to_words(self) -> list[int]:
        """The step's ``rm.STEP_WORDS`` register words.  Encodes any value that fits its field,
        valid or not: validation is the firmware's (START) or :meth:`CapturePlan.build`'s."""
        w = [0] * rm.STEP_WORDS
        _put(w, "SOURCE", (int(self.source) << BYTE) | self.index)
        _put(w, "INTENSITY", self.intensity)
        _put(w, "POLARIZER", rm.POL_KEEP if self.polarizer_cdeg is None else self.polarizer_cdeg)
        _put(w, "SETTLE_US", self.settle_us)
        _put(w, "EXPOSURE_US", self.exposure_us)
        _put(w, "PULSE_US", self.pulse_us)
        _put(w, "BRACKETS", (self.ev_step << BYTE) | self.brackets)
        _put(w, "TRIGGERS", self.triggers)
        return w

    @classmethod
    def from_words(cls, w: Sequence[int]) -> Step:
        if len(w) != rm.STEP_WORDS:
            raise InputError(f"a step is {rm.STEP_WORDS} words, got {len(w)}")
        low = (1 << BYTE) - 1
        src, pol, br = _get(w, "SOURCE"), _get(w, "POLARIZER"), _get(w, "BRACKETS")
        return cls(
            source=rm.Source(src >> BYTE), index=src & low, intensity=_get(w, "INTENSITY"),
            polarizer_cdeg=None if pol == rm.POL_KEEP else pol,
            settle_us=_get(w, "SETTLE_US"), exposure_us=_get(w, "EXPOSURE_US"), pulse_us=_get(w, "PULSE_US"),
            brackets=br & low, ev_step=br >> BYTE, triggers=_get(w, "TRIGGERS"),
        )


def encode(steps: Iterable[Step]) -> list[int]:
    """The step table as a flat list of register words."""
    return [word for s in steps for word in s.to_words()]


def seq_crc(steps: Iterable[Step]) -> int:
    """CRC-16/MODBUS over the table, each word big-endian (input register SEQ_CRC)."""
    return crc16(b"".join(w.to_bytes(2, "big") for w in encode(steps)))


@dataclass(frozen=True)
class StepTiming:
    """Scheduled times of one step, µs relative to the sequence start."""

    start: int
    brackets: tuple[int, ...]
    end: int


def schedule(steps: Sequence[Step], frame_gap_us: int = 0) -> list[StepTiming]:
    """Device-master schedule (PROTOCOL.md §3.1): what the firmware must hit exactly."""
    out, t = [], 0
    for s in steps:
        starts, tb = [], t + s.settle_us
        for e in s.bracket_exposures():
            starts.append(tb)
            tb += e + frame_gap_us
        out.append(StepTiming(t, tuple(starts), tb))
        t = tb
    return out


def servo_travel_us(from_cdeg: int, to_cdeg: int) -> int:
    """Worst-case servo travel time, from rig.toml's slew rate, rounded up to whole µs."""
    d = abs(to_cdeg - from_cdeg)
    return -(-d * 1000 // rm.POL_SLEW_CDEG_PER_MS)


@dataclass
class CapturePlan:
    """What a micro capture takes: lights × analyzer modes × HDR brackets.

    Each analyzer mode runs every directional LED in `leds`, then the diffuse group and each
    back light in `backlights` (transmission). The first step after an analyzer change gets a
    settle long enough for the servo.
    """

    leds: list[int] = field(default_factory=lambda: list(range(rm.N_LEDS)))
    modes_cdeg: list[int] = field(default_factory=lambda: [rm.POL_P0_CDEG, rm.POL_P90_CDEG])
    diffuse: bool = True
    backlights: list[int] = field(default_factory=lambda: list(range(rm.N_BACKLIGHTS)))
    intensity: int = 40000
    settle_us: int = 2000
    exposure_us: int = 8000
    brackets: int = 3
    ev_step: int = 1
    pulse_us: int = 100
    triggers: int = MICRO_TRIGGER
    servo_margin_us: int = 20000

    def lights(self) -> list[tuple[rm.Source, int]]:
        out = [(rm.Source.LED, i) for i in self.leds]
        if self.diffuse:
            out.append((rm.Source.DIFFUSE, 0))
        out += [(rm.Source.BACKLIGHT, i) for i in self.backlights]
        return out

    def build(self, start_cdeg: int = 0) -> list[Step]:
        """The step list. `start_cdeg` is the analyzer angle before the sequence."""
        for i in self.leds:
            if not 0 <= i < rm.N_LEDS:
                raise InputError(f"LED index {i} outside 0..{rm.N_LEDS - 1}")
        for i in self.backlights:
            if not 0 <= i < rm.N_BACKLIGHTS:
                raise InputError(f"back-light index {i} outside 0..{rm.N_BACKLIGHTS - 1}")
        if not 1 <= self.brackets <= rm.MAX_BRACKETS:
            raise InputError(f"brackets {self.brackets} outside 1..{rm.MAX_BRACKETS}")
        if not 0 <= self.ev_step <= rm.MAX_EV_STEP:
            raise InputError(f"ev_step {self.ev_step} outside 0..{rm.MAX_EV_STEP}")
        if not 0 < self.triggers < (1 << rm.N_TRIGGERS):
            raise InputError(f"triggers mask 0x{self.triggers:X}: needs one of the {rm.N_TRIGGERS} trigger "
                             f"outputs {rm.TRIGGER_NAMES} (bit i = output i)")
        steps, angle = [], start_cdeg
        for mode in self.modes_cdeg:
            for j, (src, idx) in enumerate(self.lights()):
                settle = self.settle_us
                pol = None
                if j == 0 and mode != angle:
                    settle = max(settle, servo_travel_us(angle, mode) + self.servo_margin_us)
                    pol, angle = mode, mode
                steps.append(Step(src, idx, self.intensity, pol, settle, self.exposure_us,
                                  self.pulse_us, self.brackets, self.ev_step, self.triggers))
        if len(steps) > rm.MAX_STEPS:
            raise InputError(f"plan has {len(steps)} steps; the device holds {rm.MAX_STEPS}")
        return steps
