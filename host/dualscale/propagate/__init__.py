"""Mesoscale propagation (seed Section 7): a multi-decoder U-Net trained on the micro capture
and its fitted maps, exported to ONNX and run tiled over the mid-range guidance image.

Modules: ``unet`` (model), ``data`` (training sources), ``augment``, ``losses``, ``train``,
``model`` (building the net from a model file, :mod:`dualscale.formats.model`), ``export`` (ONNX +
parity), ``guidance`` (reading and checking guidance images), ``infer`` (tiled inference),
``bridge`` (locating the micro field in the guidance), ``resample`` (micro data to the guidance
texel), ``stage`` (the pipeline entry point ``run_propagation``), ``metrics``.
See docs/PROPAGATION.md.
"""
