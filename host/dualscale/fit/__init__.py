"""Micro-scale SVBSDF fitting (supplementary Sec. 4-6 of Garces et al. 2023).

* :func:`fit_dataset` -- the whole fit of a dataset directory (what ``dualscale fit`` runs);
* :func:`fit_observations` -- one preset, one set of components, in memory;
* :func:`select_components` -- which components the data needs, with evidence;
* presets (:data:`PRESETS`), metrics, the light-subset study and fly-out detection.

See docs/FITTING.md.
"""

from .api import fit_dataset
from .checkpoint import FitInterrupted
from .core import FitResult, fit_observations, split_holdout
from .metrics import map_errors, normal_angle_deg, rerender_ssim, ssim_images
from .observations import Observations, load_observations
from .params import PAPER_BOUNDS, Bound, bounds_at, fit_components
from .presets import PRESETS, Preset, get_preset
from .select import select_components

__all__ = ["PAPER_BOUNDS", "PRESETS", "Bound", "FitInterrupted", "FitResult", "Observations", "Preset", "bounds_at",
           "fit_components", "fit_dataset", "fit_observations", "get_preset", "load_observations", "map_errors",
           "normal_angle_deg", "rerender_ssim", "select_components", "split_holdout", "ssim_images"]
