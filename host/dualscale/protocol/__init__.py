"""The rig protocol as seen from the host. `regmap` is generated from protocol/*.toml."""

from . import regmap
from .crc import crc16, rtu_frame

__all__ = ["regmap", "crc16", "rtu_frame"]
