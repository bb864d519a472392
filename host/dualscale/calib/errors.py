"""Errors of the calibration pipeline.  All are ``ValueError`` so the CLI reports them cleanly."""

from __future__ import annotations


class CalibrationError(ValueError):
    """A calibration input is unusable; nothing is written."""


class MissingBracketsError(CalibrationError):
    """An exposure bracket is missing, or the brackets do not cover every pixel."""


class SaturatedError(CalibrationError):
    """Every capture of a group is saturated."""


class ChartNotFoundError(CalibrationError):
    """No ColorChecker could be located in an image."""


class ImageSizeError(CalibrationError):
    """Images that must share a size do not."""


class RigMismatchError(CalibrationError):
    """A calibration file belongs to another rig."""
