"""Self-contained HTML reports: the run report of ``dualscale digitize``
(:func:`dualscale.report.run.write_run_report`) and the device evaluation
(:func:`dualscale.report.device.write_report`).

Shared parts: :mod:`.html` (Jinja2 templates shipped as package data, atomic writes, the
assets folder), :mod:`.plots` (matplotlib figures with labelled units and colour scales that do
not saturate silently), :mod:`.format` (numbers with units and goals, durations).
"""

from __future__ import annotations


def write_run_report(run_dir, out=None):
    """See :func:`dualscale.report.run.write_run_report` (imported lazily: matplotlib, torch)."""
    from .run import write_run_report as _w

    return _w(run_dir, out)


__all__ = ["write_run_report"]

