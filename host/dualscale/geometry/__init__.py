"""The physical rig in numbers: the dome (LED directions, polarisers) and the cameras, from
``protocol/rig.toml`` (through the generated register map) or a calibration file."""
