"""Building the propagation network from a model file (:mod:`dualscale.formats.model`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dualscale.errors import FormatError
from dualscale.formats.model import read_model_file, write_model_file

from .unet import PropagationUNet, UNetConfig


def save_model(path: str | Path, model: PropagationUNet, input_reference: list[float], train: dict[str, Any],
               half: bool = False) -> Path:
    """Write ``model`` (its config and weights) with the training record; ``half`` stores the
    weights as float16."""
    return write_model_file(path, model.config.to_json(), model.state_dict(), input_reference, train, half)


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
        raise FormatError(f"{path}: malformed model file ({e})") from e
    return model.eval(), doc
