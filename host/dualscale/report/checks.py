"""The run's own checks (docs/DIGITIZE.md, "The run's check"), computed from the fit stage's
record alone, so that the report stage (which runs before ``digitize`` ends) shows them and
:mod:`dualscale.pipeline` (``run.json`` ``checks``, the exit code) and ``dualscale batch`` (the
summary's ``check`` column) record the same ones.

A run that finished its fit with a cross-validation pass is checked twice, both on the fit's
cross-validated held-out relative L1 ``Σ|prediction − capture| / Σ capture`` (mean over the
lights; predicting black scores 1), from the fit stage summary:

1. **held-out error** (``heldout_relative_l1``): at most :data:`HELDOUT_L1_GOAL`;
2. **against the constant predictor** (``heldout_constant_relative_l1``): below
   :data:`CONSTANT_MARGIN` times the held-out relative L1 of the per-pixel constant predictor
   (each pixel's mean over the fold's training images, on the same folds, pixels and valid
   samples: a prediction that ignores the light; :func:`dualscale.fit.holdout.constant_prediction`).
   The check's ``value`` is the ratio of the two.

A fit without a cross-validation pass (too few lights), or a record made before the constant
predictor was measured, gives checks that are not measured (``ok`` ``None``); no fit record, no
checks.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

#: the run's check: the largest cross-validated held-out relative L1 of the fit a run passes with
#: (the figures of docs/DIGITIZE.md and docs/PHOTOS.md are 0.02-0.25, random noise gives 1.0 and
#: more when its level ignores the light)
HELDOUT_L1_GOAL = 0.5
#: the run's second check: the fit's held-out relative L1 must be below this fraction of the
#: per-pixel constant predictor's (docs/DIGITIZE.md measures it: the synthetic materials score
#: 0.005-0.1 of it, noise whose level ignores the light 2.5)
CONSTANT_MARGIN = 0.8

HELDOUT_CHECK = "fit held-out error"
CONSTANT_CHECK = "fit against the constant predictor"


@dataclass(frozen=True)
class Check:
    """One of the run's own checks: ``name``, the measured ``value`` (``None``: not measured), the
    ``goal`` as text, ``ok`` (``None`` when not measured) and ``text``: one line for the user."""

    name: str
    value: float | None
    goal: str
    ok: bool | None
    text: str

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @property
    def mark(self) -> str:
        """``✓`` passed, ``✗`` failed, ``""`` not measured."""
        return "" if self.ok is None else "✓" if self.ok else "✗"


_ADVICE = ("the fitted maps do not predict the lights they were not fitted on, so they do not describe the "
           "sample under other lights. Check that the images are one sample under the stated lights (directions, "
           "intensities, camera response), registered and unclipped")


def run_checks(fit_record: dict[str, Any] | None) -> list[Check]:
    """The run's own checks (module docstring) from the fit stage's record (its ``summary``;
    ``None``: the fit did not run, nothing is checked), in order: held-out error, then against
    the constant predictor."""
    if fit_record is None:
        return []
    s = fit_record.get("summary") or {}
    rel = s.get("heldout_relative_l1")
    method = s.get("heldout_method", "cross-validated")
    goal = f"at most {100 * HELDOUT_L1_GOAL:.0f} %"
    cgoal = f"below {CONSTANT_MARGIN:g}× the per-pixel constant predictor's"
    if not isinstance(rel, (int, float)):
        why = s.get("heldout_method", "no cross-validation")
        return [Check(HELDOUT_CHECK, None, goal, None, f"fit held-out relative L1 not measured ({why})"),
                Check(CONSTANT_CHECK, None, cgoal, None,
                      f"fit against the per-pixel constant predictor not measured ({why})")]
    ok = bool(rel <= HELDOUT_L1_GOAL)
    text = f"fit held-out relative L1 {100 * rel:.1f} % ({'within' if ok else 'above'} the goal of {goal}; {method})"
    if not ok:
        text += ": " + _ADVICE
    out = [Check(HELDOUT_CHECK, float(rel), goal, ok, text)]
    const = s.get("heldout_constant_relative_l1")
    if not isinstance(const, (int, float)) or not const > 0:
        out.append(Check(CONSTANT_CHECK, None, cgoal, None,
                         "fit against the per-pixel constant predictor not measured (the fit stage's record has no "
                         "constant predictor's held-out error: a fit from before it was measured)"))
        return out
    ratio = float(rel) / float(const)
    cok = bool(ratio < CONSTANT_MARGIN)
    goal_c = f"{cgoal} {100 * const:.1f} %"
    ctext = (f"fit held-out relative L1 {100 * rel:.1f} % is {ratio:.2f}× the per-pixel constant predictor's "
             f"{100 * const:.1f} % ({'meets' if cok else 'misses'} the goal of below {CONSTANT_MARGIN:g}×; same folds "
             "and pixels)")
    if not cok:
        ctext += (": the fitted maps predict the held-out lights no better than each pixel's mean over the other "
                  "lights, a prediction that ignores the light; real materials' shading changes with the light. "
                  "Check that the images are photographs of the sample under the lights the dataset states")
    out.append(Check(CONSTANT_CHECK, ratio, goal_c, cok, ctext))
    return out


def failed(checks: list[Check]) -> list[Check]:
    """The checks of ``checks`` that failed (``ok`` is ``False``)."""
    return [c for c in checks if c.ok is False]


__all__ = ["CONSTANT_CHECK", "CONSTANT_MARGIN", "HELDOUT_CHECK", "HELDOUT_L1_GOAL", "Check", "failed", "run_checks"]
