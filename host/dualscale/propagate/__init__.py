"""Mesoscale propagation (seed Section 7): a multi-decoder U-Net trained on the micro capture
and its fitted maps, exported to ONNX and run tiled over the mid-range guidance image.

Modules: ``unet`` (model), ``data`` (training sources), ``augment``, ``losses``, ``train``,
``io`` (model files), ``export`` (ONNX + parity), ``infer`` (tiled inference), ``metrics``.
See docs/PROPAGATION.md.
"""
