"""The device layer: Modbus client, sequences, events, simulator launcher, console, flashing."""
