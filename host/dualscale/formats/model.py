"""Propagation model files: ``torch.save`` of a plain dict, versioned.  The one reader
(:func:`read_model_file`) and writer (:func:`write_model_file`); building the network from it
is :func:`dualscale.propagate.model.load_model`.

``{"format": "dualscale-propagate", "version": 2, "config": UNetConfig.to_json(),
"state_dict": {...}, "input_reference": [r, g, b], "train": {...}}``

``input_reference`` is the mean linear RGB of the training diffuse images; ``run`` uses it to
match the guidance exposure.  Weights may be stored as float16 (``half=True``) to keep
shipped models small; they are restored to float32 on load.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from dualscale.errors import FormatError

from .torchfile import load_torch, save_torch

FORMAT = "dualscale-propagate"
VERSION = 2
COMPATIBLE = (2,)


def write_model_file(path: str | Path, config: dict[str, Any], state_dict: dict[str, torch.Tensor],
                     input_reference: list[float], train: dict[str, Any], half: bool = False) -> Path:
    """Write a model file atomically; ``half`` stores the floating-point weights as float16."""
    path = Path(path)
    sd = {k: (v.detach().half() if half and v.is_floating_point() else v.detach()).cpu().clone()
          for k, v in state_dict.items()}
    return save_torch(path, {"format": FORMAT, "version": VERSION, "config": config, "state_dict": sd,
                             "input_reference": [float(x) for x in input_reference], "train": train})


def read_model_file(path: str | Path) -> dict[str, Any]:
    """Load and validate the dict; ``FileNotFoundError`` when missing, one-line
    :class:`FormatError` naming the file for a damaged (empty, truncated, checksum), foreign or
    incompatible file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file not found: {path}")
    doc = load_torch(path, "dualscale propagation model", "train it again (propagate train --resume finishes it from its "
                     "checkpoint)")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        fmt = doc.get("format") if isinstance(doc, dict) else None
        raise FormatError(f"{path}: not a dualscale propagation model (format {fmt!r})")
    ver = doc.get("version")
    if ver not in COMPATIBLE:
        raise FormatError(f"{path}: model file version {ver} is incompatible with this dualscale "
                         f"(reads version {', '.join(map(str, COMPATIBLE))}); retrain or convert it")
    return doc
