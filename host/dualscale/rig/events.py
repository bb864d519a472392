"""Decoding the device's event FIFO records (PROTOCOL.md §4).

An event is ``rm.EVENT_WORDS`` registers: SEQ, KIND | ARG << 8, STEP (``rm.STEP_NONE`` when
not step-related), TS_US (u48, big-endian by word): registers.toml's EVT_WINDOW.  The
generated map has no per-word offsets for events, so :data:`EVENT_FIELDS` names them here and
is checked against ``rm.EVENT_WORDS`` at import.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from dualscale.errors import RigError

from ..protocol import regmap as rm
from .sequence import BYTE, join_words

EVENT_FIELDS: dict[str, tuple[int, int]] = {"SEQ": (0, 1), "KIND": (1, 1), "STEP": (2, 1), "TS_US": (3, 3)}
"""``name -> (word offset, word count)`` inside one event record."""
if sum(n for _, n in EVENT_FIELDS.values()) != rm.EVENT_WORDS:  # pragma: no cover - a regenerated map
    raise ImportError(f"EVENT_FIELDS covers {sum(n for _, n in EVENT_FIELDS.values())} words; "
                      f"the register map says an event is {rm.EVENT_WORDS}")


def _field(w: Sequence[int], name: str) -> int:
    off, n = EVENT_FIELDS[name]
    return join_words(w[off:off + n])


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
        """Decode one record; an unknown kind is a :class:`~dualscale.errors.RigError`."""
        kind_arg = _field(w, "KIND")
        kind = kind_arg & ((1 << BYTE) - 1)
        try:
            k = rm.Event(kind)
        except ValueError as exc:
            raise RigError(f"unknown event kind {kind}") from exc
        return cls(_field(w, "SEQ"), k, kind_arg >> BYTE, _field(w, "STEP"), _field(w, "TS_US"))

    def __str__(self) -> str:
        step = "-" if self.step == rm.STEP_NONE else str(self.step)
        return f"#{self.seq:<5d} t={self.ts_us:>12d}us {self.kind.name:<12s} step={step} arg={self.arg}"


def decode_window(words: Sequence[int], count: int) -> list[Event]:
    """The first `count` events of an EVT_WINDOW read."""
    n = rm.EVENT_WORDS
    return [Event.from_words(words[i * n:(i + 1) * n]) for i in range(count)]
