"""The virtual rig: renderer, sensor, shadows, synthetic materials and targets. No production stage imports it."""
