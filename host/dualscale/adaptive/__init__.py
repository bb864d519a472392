"""Adaptive capture (issue 27): the micro capture chooses its lights round by round from the
fit's per-pixel uncertainty (:mod:`.loop`), by an optimal-design criterion (:mod:`.design`).
Above ``capture``, ``calib`` and ``fit`` in the layers (docs/ARCHITECTURE.md)."""
