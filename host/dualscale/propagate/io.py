"""Model files: ``torch.save`` of a plain dict, versioned.

``{"format": "dualscale-propagate", "version": 2, "config": UNetConfig.to_json(),
"state_dict": {...}, "input_reference": [r, g, b], "train": {...}}``

``input_reference`` is the mean linear RGB of the training diffuse images; ``run`` uses it to
match the guidance exposure.  Weights may be stored as float16 (``half=True``) to keep
shipped models small; they are restored to float32 on load.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import torch

from .unet import PropagationUNet, UNetConfig

FORMAT = "dualscale-propagate"
VERSION = 2
COMPATIBLE = (2,)


def save_model(path: str | Path, model: PropagationUNet, input_reference: list[float], train: dict[str, Any],
               half: bool = False) -> Path:
    """Write a model file; ``half`` stores the weights as float16."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sd = {k: (v.detach().half() if half and v.is_floating_point() else v.detach()).cpu().clone()
          for k, v in model.state_dict().items()}
    torch.save({"format": FORMAT, "version": VERSION, "config": model.config.to_json(), "state_dict": sd,
                "input_reference": [float(x) for x in input_reference], "train": train}, path)
    return path


def read_model_file(path: str | Path) -> dict[str, Any]:
    """Load and validate the dict; clear ``ValueError`` for foreign or incompatible files."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file not found: {path}")
    try:
        doc = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, ValueError) as e:
        raise ValueError(f"{path}: not a dualscale propagation model ({e.__class__.__name__})") from e
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        fmt = doc.get("format") if isinstance(doc, dict) else None
        raise ValueError(f"{path}: not a dualscale propagation model (format {fmt!r})")
    ver = doc.get("version")
    if ver not in COMPATIBLE:
        raise ValueError(f"{path}: model file version {ver} is incompatible with this dualscale "
                         f"(reads version {', '.join(map(str, COMPATIBLE))}); retrain or convert it")
    return doc


def load_model(path: str | Path) -> tuple[PropagationUNet, dict[str, Any]]:
    """``(model in eval mode, float32, CPU; the file's dict)``."""
    doc = read_model_file(path)
    c = doc["config"]
    try:
        config = UNetConfig(maps=tuple(c["maps"]), width=int(c["width"]), decoder_ratio=float(c["decoder_ratio"]),
                            in_channels=int(c["in_channels"]))
        model = PropagationUNet(config)
        model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in doc["state_dict"].items()})
    except (KeyError, TypeError, RuntimeError) as e:
        raise ValueError(f"{path}: malformed model file ({e})") from e
    return model.eval(), doc
