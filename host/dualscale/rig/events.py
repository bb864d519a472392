"""Decoding the device's event FIFO records (PROTOCOL.md §4)."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from ..protocol import regmap as rm


@dataclass(frozen=True)
class Event:
    """One FIFO event; `ts_us` is the device clock (µs since boot)."""

    seq: int
    kind: rm.Event
    arg: int
    step: int
    ts_us: int

    @classmethod
    def from_words(cls, w: Sequence[int]) -> Event:
        kind = w[1] & 0xFF
        try:
            k = rm.Event(kind)
        except ValueError as exc:
            raise ValueError(f"unknown event kind {kind}") from exc
        return cls(w[0], k, w[1] >> 8, w[2], (w[3] << 32) | (w[4] << 16) | w[5])

    def __str__(self) -> str:
        step = "-" if self.step == 0xFFFF else str(self.step)
        return f"#{self.seq:<5d} t={self.ts_us:>12d}us {self.kind.name:<12s} step={step} arg={self.arg}"


def decode_window(words: Sequence[int], count: int) -> list[Event]:
    """The first `count` events of an EVT_WINDOW read."""
    n = rm.EVENT_WORDS
    return [Event.from_words(words[i * n:(i + 1) * n]) for i in range(count)]
