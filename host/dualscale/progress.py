"""Progress of long library steps, reported without printing from library code.

A long library function takes ``progress: Progress = None`` and reports through
:func:`tracker`.  What the caller passes decides what happens:

- ``None`` or ``False``: nothing;
- ``True``: a ``tqdm`` bar on stderr (what the command line passes when asked, or when stderr
  is a terminal: ``dualscale ... --progress/--no-progress``);
- a callable ``fn(done: int, total: int | None, what: str)``: called after each unit of work
  (a pipeline that shows one view over its stages passes its own);
- a :class:`Tracker` already open: the work adds to it (nested steps share one bar).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar, Union

T = TypeVar("T")
ProgressFn = Callable[[int, Union[int, None], str], None]


class Tracker:
    """Counts units of work towards ``total`` (``None`` = unknown) and reports each update."""

    def __init__(self, progress: "Progress", total: int | None, desc: str, unit: str = "step") -> None:
        self.total, self.desc, self.done = total, desc, 0
        self._fn: ProgressFn | None = progress if callable(progress) and not isinstance(progress, bool) else None
        self._bar = None
        if progress is True:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True, leave=False)

    def update(self, n: int = 1, what: str | None = None) -> None:
        """``n`` more units done; ``what`` names the last one (shown beside the bar)."""
        self.done += n
        if self._bar is not None:
            if what:
                self._bar.set_postfix_str(what, refresh=False)
            self._bar.update(n)
            if self.total is not None and self.done >= self.total:
                self._bar.refresh()  # drawn full even when the last units came within tqdm's redraw interval
        if self._fn is not None:
            self._fn(self.done, self.total, what or self.desc)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> "Tracker":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


Progress = Union[None, bool, ProgressFn, Tracker]


class _Shared(Tracker):
    """A caller's open tracker, lent to a nested step: closing it is the caller's business."""

    def __init__(self, outer: Tracker) -> None:  # noqa: D107 - shares the outer state
        self.__dict__ = outer.__dict__

    def close(self) -> None:
        pass


def tracker(progress: Progress, total: int | None, desc: str, unit: str = "step") -> Tracker:
    """A :class:`Tracker` for ``progress`` (see the module doc); use it as a context manager."""
    if isinstance(progress, Tracker):
        return _Shared(progress)
    return Tracker(progress, total, desc, unit)


def iterate(progress: Progress, items: Iterable[T], desc: str, total: int | None = None,
            unit: str = "step") -> Iterator[T]:
    """Yield ``items`` and count each one done after the consumer has handled it."""
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    with tracker(progress, total, desc, unit) as t:
        for item in items:
            yield item
            t.update()
