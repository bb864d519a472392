"""Resumable fits: the whole optimiser state in one file, written atomically.

A checkpoint holds a ``fingerprint`` of what is being fitted (data, preset, components), the
position ``(step, iteration)`` of the next iteration to run, the parameters and the optimiser's
own state.  Resuming with a different fingerprint is refused.
"""

from __future__ import annotations

from dualscale.errors import FormatError, Interrupted
from dualscale.formats.torchfile import load_torch, save_torch

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch


class FitInterrupted(Interrupted):
    """Raised when a fit stops early on request (``stop_after``); the checkpoint is saved."""


def fingerprint(**parts: Any) -> str:
    """Stable hash of JSON-able parts and tensors."""
    h = hashlib.sha256()
    for k in sorted(parts):
        v = parts[k]
        h.update(k.encode())
        if isinstance(v, torch.Tensor):
            h.update(str(tuple(v.shape)).encode())
            h.update(v.detach().to(torch.float64).contiguous().cpu().numpy().tobytes())
        else:
            h.update(json.dumps(v, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


@dataclass
class Checkpointer:
    """Saves every ``every`` iterations to ``path`` (``None``: never)."""

    path: Path | None
    fingerprint: str
    every: int = 50

    def load(self) -> dict[str, Any] | None:
        """The saved state, ``None`` when there is no checkpoint; one-line
        :class:`~dualscale.errors.FormatError` naming the file for a damaged one, ``ValueError``
        for one of another fit."""
        if self.path is None or not Path(self.path).is_file():
            return None
        state = load_torch(self.path, "fit checkpoint", "delete it or pass --restart", weights_only=False)
        if not isinstance(state, dict):
            raise FormatError(f"{self.path}: not a fit checkpoint; delete it or pass --restart")
        if state.get("fingerprint") != self.fingerprint:
            raise ValueError(f"checkpoint {self.path} belongs to a different fit (data, preset or components "
                             "changed); delete it or pass --restart")
        return state

    def save(self, state: dict[str, Any]) -> None:
        if self.path is None:
            return
        save_torch(self.path, {**state, "fingerprint": self.fingerprint})

    def due(self, done: int) -> bool:
        return self.path is not None and self.every > 0 and done % self.every == 0
