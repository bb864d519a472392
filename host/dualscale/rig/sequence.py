"""Sequence steps, capture plans, the step-table encoding and the device-master schedule.

Units: times in microseconds, polarizer angles in centidegrees (P0 = 0, P90 = 9000).
The word layout and timing rules are PROTOCOL.md §3; the constants come from the generated
regmap, so this module cannot drift from the firmware.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from ..protocol import regmap as rm
from ..protocol.crc import crc16

KEEP = 0xFFFF  # POLARIZER word value: keep the current angle


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
        pol = KEEP if self.polarizer_cdeg is None else self.polarizer_cdeg
        return [
            (int(self.source) << 8) | self.index,
            self.intensity,
            pol,
            self.settle_us >> 16, self.settle_us & 0xFFFF,
            self.exposure_us >> 16, self.exposure_us & 0xFFFF,
            self.pulse_us,
            (self.ev_step << 8) | self.brackets,
            self.triggers,
        ]

    @classmethod
    def from_words(cls, w: Sequence[int]) -> Step:
        if len(w) != rm.STEP_WORDS:
            raise ValueError(f"a step is {rm.STEP_WORDS} words, got {len(w)}")
        return cls(
            source=rm.Source(w[0] >> 8), index=w[0] & 0xFF, intensity=w[1],
            polarizer_cdeg=None if w[2] == KEEP else w[2],
            settle_us=(w[3] << 16) | w[4], exposure_us=(w[5] << 16) | w[6], pulse_us=w[7],
            brackets=w[8] & 0xFF, ev_step=w[8] >> 8, triggers=w[9],
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
    triggers: int = 0b0001  # the micro camera
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
                raise ValueError(f"LED index {i} outside 0..{rm.N_LEDS - 1}")
        for i in self.backlights:
            if not 0 <= i < rm.N_BACKLIGHTS:
                raise ValueError(f"back-light index {i} outside 0..{rm.N_BACKLIGHTS - 1}")
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
            raise ValueError(f"plan has {len(steps)} steps; the device holds {rm.MAX_STEPS}")
        return steps
