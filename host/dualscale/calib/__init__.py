"""Calibration and device evaluation of the dual-scale rig (supplementary Sec. 2-4): HDR,
radiometric calibration and white balance against a transmissive white sheet, CIEDE2000 colour
correction, and sharpness / polarisation / collimation evaluation.  See docs/CALIBRATION.md."""

from dualscale.errors import (CalibrationError, ChartNotFoundError, ImageSizeError, MissingBracketsError,  # noqa: F401
                     RigMismatchError, SaturatedError)
