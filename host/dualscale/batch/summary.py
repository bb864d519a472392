"""The batch's summary: ``summary.csv``, ``summary.json``, ``summary.html`` and the terminal
table (:func:`write_summary`, :func:`table`; see :mod:`dualscale.batch`)."""

from __future__ import annotations

import csv
import io
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from dualscale.pipeline import STAGES

from .run import SampleResult
from .samples import SUMMARY_FORMAT, SUMMARY_VERSION


def components_text(components: dict[str, Any] | None) -> str | None:
    """The fit's component decision in words: ``opaque, anisotropic, tinted`` (from the fit
    record's ``components``: :class:`dualscale.bsdf.maps.Components`)."""
    if not components:
        return None
    return ", ".join(["opaque" if components.get("opaque", True) else "transmissive",
                      "isotropic" if components.get("isotropic", True) else "anisotropic",
                      "tinted" if components.get("tinted") else "untinted"])


def _main_file(files: list[str]) -> str | None:
    """The file a user opens of one export format (``.gltf``, ``.glb``, ``.mtlx``, ``.u3ma``),
    else the format's folder (EXR and map sets)."""
    for f in files:
        if Path(f).suffix.lower() in (".gltf", ".glb", ".mtlx", ".u3ma", ".u3m"):
            return f
    return str(Path(files[0]).parent) + "/" if files else None


def check_text(checks: list) -> str:
    """The run's checks in one word or line: ``passed``, ``failed: <check> (<line>)``, ``not
    measured`` (a fit without a cross-validation pass) or ``not run`` (the fit did not finish)."""
    if not checks:
        return "not run"
    bad = [c for c in checks if c.ok is False]
    if bad:
        return "failed: " + "; ".join(c.text for c in bad)
    return "passed" if any(c.ok for c in checks) else "not measured"


def sample_row(r: SampleResult) -> dict[str, Any]:
    """One sample's entry of ``summary.json`` (paths relative to OUTDIR)."""
    fail = r.failure
    checks = r.checks
    fit, prop, exp = r.summary("fit"), r.summary("propagate"), r.summary("export")
    in_field = prop.get("in_field_l1") or {}
    reg = prop.get("registration") or {}
    exports = {}
    for scale, e in (exp.get("exports") or {}).items():
        folder = f"{r.name}/export/{scale}"
        exports[scale] = {"name": e.get("name"), "folder": folder, "tiled": e.get("tiled"),
                          "files": {fmt: f"{folder}/{_main_file(files)}"
                                    for fmt, files in (e.get("files") or {}).items() if fmt != "maps" and files}}
    report = r.summary("report").get("index")
    return {
        "name": r.name, "input": str(r.sample.input), "quality": r.sample.quality, "status": r.status,
        "failed_stage": None if fail is None else fail["stage"], "interrupted_stage": r.interrupted_stage,
        "error": None if fail is None else f"{fail.get('error_type')}: {fail.get('error')}",
        "traceback": None if fail is None else fail.get("traceback"),
        "seconds": round(sum(x["seconds"] or 0.0 for x in r.stages.values()), 3),
        "stages": {s: {"status": x.get("status"), "seconds": x.get("seconds"),
                       "record_seconds": x.get("record_seconds"), "warnings": len(x.get("warnings") or [])}
                   for s, x in r.stages.items()},
        "components": fit.get("components"), "components_text": components_text(fit.get("components")),
        "heldout_relative_l1": fit.get("heldout_relative_l1"),
        "heldout_baseline_relative_l1": fit.get("heldout_baseline_relative_l1"),
        "heldout_constant_relative_l1": fit.get("heldout_constant_relative_l1"),
        "heldout_method": fit.get("heldout_method"),
        "check": check_text(checks), "check_ok": (None if not any(c.ok is not None for c in checks)
                                                  else not any(c.ok is False for c in checks)),
        "checks": [c.to_json() for c in checks],
        "propagate": None if not prop or "skipped" in prop else {
            "in_field_l1_mean": (sum(in_field.values()) / len(in_field)) if in_field else None,
            "registration_ncc": reg.get("score"), "registration_method": reg.get("method")},
        "propagate_skipped": prop.get("skipped"),
        "exports": exports, "report": None if report is None else f"{r.name}/{report}",
    }


CSV_COLUMNS = ("name", "status", "failed_stage", "error", "seconds", *(f"seconds_{s}" for s in STAGES), "up_to_date",
               "components", "check", "heldout_relative_l1", "heldout_baseline_relative_l1",
               "heldout_constant_relative_l1", "propagate_in_field_l1",
               "registration_ncc",
               "exports", "report")


def _csv(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO(newline="")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)

    def num(x):
        return "" if x is None else (f"{x:.6g}" if isinstance(x, float) else x)

    for r in rows:
        p = r["propagate"] or {}
        w.writerow([r["name"], r["status"], r["failed_stage"] or "", r["error"] or "", num(r["seconds"]),
                    *(num(r["stages"][s]["seconds"]) for s in STAGES),
                    ";".join(s for s in STAGES if r["stages"][s]["status"] == "up to date"),
                    r["components_text"] or "", r["check"], num(r["heldout_relative_l1"]),
                    num(r["heldout_baseline_relative_l1"]), num(r["heldout_constant_relative_l1"]),
                    num(p.get("in_field_l1_mean")), num(p.get("registration_ncc")),
                    ";".join(f for e in r["exports"].values() for f in e["files"].values()), r["report"] or ""])
    return buf.getvalue()


_HTML = """{% extends "base.html" %}
{% block content %}
<style>
table.batch { font-size: 0.82rem; }
table.batch td.num { white-space: nowrap; }
table.batch .error { min-width: 22em; max-width: 40em; overflow-wrap: anywhere; font-size: 0.85em; }
pre.mono { white-space: pre-wrap; overflow-wrap: anywhere; background: var(--panel); padding: 8px; }
</style>
<section id="samples">
<h2>Samples</h2>
{% if interrupted %}<p class="bad">The batch was interrupted (Ctrl-C) before {{ interrupted }} sample(s) ended: this
is the summary of what finished; run the same command again to resume.</p>{% endif %}
<p>{{ done }} done, {{ failed }} failed{% if interrupted %}, {{ interrupted }} interrupted{% endif %}{% if up_to_date %}; {{ up_to_date }} stage(s) were up to date{% endif %}.
Times are each stage's wall time in this batch; an up-to-date stage was skipped (its record matched: hover for
the time it took when it ran).</p>
<table class="batch">
<thead><tr><th>sample</th><th>status</th><th>quality</th>{% for s in stages %}<th class="num">{{ s }}</th>{% endfor %}
<th class="num">total</th><th>components</th><th title="the run's own checks (docs/DIGITIZE.md)">check</th>
<th class="num" title="cross-validated over the lights">held-out rel. L1</th>
<th class="num" title="Lambertian photometric stereo on the same folds and pixels">baseline rel. L1</th>
<th class="num" title="each pixel's mean over the training lights, on the same folds and pixels">constant rel. L1</th>
<th class="num">propagation in-field L1</th><th>exports</th></tr></thead>
<tbody>
{% for r in rows %}
<tr class="sample {{ r.status.split(':')[0] | replace(' ', '-') }}" data-name="{{ r.name }}">
<td>{% if r.report %}<a href="{{ r.report }}">{{ r.name }}</a>{% else %}{{ r.name }}{% endif %}</td>
<td>{% if r.status == "done" %}<span class="ok">done</span>{% elif r.status == "interrupted" %}<span class="bad">interrupted</span>
<div class="error">at {{ r.interrupted_stage }}: the batch was stopped; run it again to resume</div>{% elif r.status.startswith("check failed") %}<span class="bad">{{ r.status }}</span>
<div class="error">every stage ran, but the fit failed the run's check (docs/DIGITIZE.md, “The run's check”)</div>{% else %}<span class="bad">failed</span>
<div class="error">{{ r.failed_stage }}: {{ r.error }}</div>{% endif %}</td>
<td>{{ r.quality }}</td>
{% for s in stages %}{% set st = r.stages[s] %}<td class="num {{ st.status | replace(' ', '-') }}">
{% if st.status == "not run" %}
<span class="muted">not run</span>
{% elif st.status == "interrupted" %}
<span class="bad">interrupted</span>
{% elif st.status == "failed" %}
<span class="bad">failed</span> {{ st.seconds | dur }}
{% elif st.status == "up to date" %}
<span class="muted" title="checked in {{ st.seconds | dur }}; ran in {{ st.record_seconds | dur }} when it was done">up to date</span>
{% else %}
{{ st.seconds | dur }}
{% endif %}
</td>
{% endfor %}
<td class="num">{{ r.seconds | dur }}</td>
<td>{{ r.components_text or "—" }}</td>
<td>{% if r.check_ok is true %}<span class="ok">✓</span> passed{% elif r.check_ok is false %}<span class="bad">✗</span> <span class="error">{{ r.check }}</span>{% else %}<span class="muted">{{ r.check }}</span>{% endif %}</td>
<td class="num" title="{{ r.heldout_method or '' }}">{{ r.heldout_relative_l1 | num }}</td>
<td class="num">{{ r.heldout_baseline_relative_l1 | num }}</td>
<td class="num">{{ r.heldout_constant_relative_l1 | num }}</td>
<td class="num">{% if r.propagate %}{{ r.propagate.in_field_l1_mean | num }}{% else %}
<span class="muted">{{ "skipped" if r.propagate_skipped else "—" }}</span>{% endif %}</td>
<td>{% for scale, e in r.exports.items() %}
<div><b>{{ scale }}</b>:
{% for fmt, f in e.files.items() %}<a href="{{ f }}">{{ fmt }}</a>{% if not loop.last %}, {% endif %}{% endfor %}
</div>
{% endfor %}</td>
</tr>
{% endfor %}
</tbody>
</table>
</section>
{% if failures %}
<section id="failures">
<h2>Failures</h2>
{% for r in failures %}<h3>{{ r.name }}: {{ r.failed_stage or r.status }}</h3><pre class="mono">{{ r.traceback or r.error or r.check }}</pre>
{% endfor %}
</section>
{% endif %}
{% endblock %}
"""


def _html(doc: dict[str, Any]) -> str:
    from dualscale.report.html import environment

    rows = doc["samples"]
    failures = [r for r in rows if r["status"] == "failed" or r["status"].startswith("check failed")]
    stopped = sum(1 for r in rows if r["status"] == "interrupted")
    up = sum(1 for r in rows for s in r["stages"].values() if s["status"] == "up to date")
    sub = (f"{doc['list']} → {doc['outdir']} · {doc['engine']} · finished {doc['finished']} · "
           f"{sum(1 for r in rows if r['status'] == 'done')}/{len(rows)} done"
           + (" · interrupted" if doc.get("interrupted") else ""))
    return environment().from_string(_HTML).render(
        title="dualscale batch", subtitle=sub,
        toc=[("samples", "samples")] + ([("failures", "failures")] if failures else []),
        footer=f"dualscale batch summary (format {SUMMARY_FORMAT} v{SUMMARY_VERSION}); per-sample reports: "
               "OUTDIR/<name>/report/index.html",
        stages=STAGES, rows=rows, failures=failures, done=len(rows) - len(failures) - stopped, failed=len(failures),
        interrupted=stopped, up_to_date=up)


def write_summary(results: list[SampleResult], outdir: str | Path, *, list_path: str | Path, engine: str,
                  seconds: float, interrupted: bool = False) -> dict[str, Any]:
    """Write ``OUTDIR/summary.json``, ``summary.csv`` and ``summary.html`` atomically
    (module docstring); returns the JSON document (``{"format", "version", "list", "outdir",
    "engine", "finished", "seconds", "interrupted", "samples": [sample_row ...]}``).
    ``interrupted``: the batch was stopped (Ctrl-C) and this is the summary of what finished
    (samples not ended have the status ``interrupted``)."""
    from dualscale.formats.atomic import write_json, write_text

    outdir = Path(outdir)
    doc = {"format": SUMMARY_FORMAT, "version": SUMMARY_VERSION, "list": str(Path(list_path).absolute()),
           "outdir": str(outdir.absolute()), "engine": engine,
           "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"), "seconds": round(seconds, 3),
           "interrupted": bool(interrupted), "samples": [sample_row(r) for r in results]}
    write_json(outdir / "summary.json", doc)
    write_text(outdir / "summary.csv", _csv(doc["samples"]))
    write_text(outdir / "summary.html", _html(doc))
    return doc


def table(doc: dict[str, Any]) -> str:
    """The short text table of a summary document, for the terminal."""
    rows = doc["samples"]
    w = max([6] + [len(r["name"]) for r in rows])
    out = [f"{'sample':<{w}s}  {'status':<6s}  {'time':>10s}  {'components':<30s}  {'CV L1':>7s}  {'PS L1':>7s}  "
           "exports"]
    for r in rows:
        t = f"{r['seconds']:.1f} s"
        if r["status"] == "interrupted":
            out.append(f"{r['name']:<{w}s}  {'STOPPED':<6s}  {t:>10s}  interrupted at {r['interrupted_stage']} "
                       "(run the same command again to resume)")
            continue
        if r["status"] == "failed":
            out.append(f"{r['name']:<{w}s}  {'FAILED':<6s}  {t:>10s}  {r['failed_stage']}: {r['error']}")
            continue
        if r["status"] != "done":  # every stage ran, the run's check failed
            out.append(f"{r['name']:<{w}s}  {'FAILED':<6s}  {t:>10s}  {r['status']}: {r['check']}")
            continue
        up = sum(1 for s in r["stages"].values() if s["status"] == "up to date")
        if up == len(STAGES):
            t = "up to date"
        rel, base = r["heldout_relative_l1"], r["heldout_baseline_relative_l1"]
        exports = "; ".join(f"{e['folder']} ({', '.join(e['files'])})" for e in r["exports"].values())
        out.append(f"{r['name']:<{w}s}  {'done':<6s}  {t:>10s}  {(r['components_text'] or '-'):<30s}  "
                   f"{'-' if rel is None else f'{rel:.4f}':>7s}  {'-' if base is None else f'{base:.4f}':>7s}  "
                   f"{exports}")
    return "\n".join(out)

