"""`dualscale batch` (issue 16 §3): samples as chains of stage tasks on a local Dask cluster or in
this process, a failing sample reported without stopping the others, reruns that skip finished
stages, the LIST checked before anything is written, and the summary (CSV, JSON, HTML)."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import re
import time
from pathlib import Path

import pytest

from dualscale.cli import main
from dualscale.pipeline import STAGES

GOOD = ("a", "b")


def _run(*argv: str) -> tuple[int, str, str, float]:
    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(["batch", *argv])
    return rc, out.getvalue(), err.getvalue(), time.perf_counter() - t0


@pytest.fixture(scope="module")
def batch_list(sample, tmp_path_factory) -> Path:
    """Two good samples of the tiny twill (draft, no guidance) and one whose guidance is far too
    coarse to propagate to (refused before any stage: digitize checks every input up front, issue 24).
    The inputs are given relative to the list's folder."""
    folder = tmp_path_factory.mktemp("lists")
    micro = os.path.relpath(sample / "micro", folder)
    mid = os.path.relpath(sample / "mid", folder)
    path = folder / "samples.csv"
    path.write_text("name,input,quality,export,seed,guidance,guidance_texel_mm\n"
                    f"a,{micro},draft,\"exr,gltf\",0,,\n"
                    f"# a comment row\n"
                    f"b,{micro},draft,glb,1,,\n"
                    f"coarse,{micro},draft,exr,0,{mid},0.2\n")
    return path


@pytest.fixture(scope="module")
def cluster_run(batch_list, tmp_path_factory):
    """The batch on a local cluster of 2 workers, into a folder whose name needs escaping in HTML."""
    pytest.importorskip("distributed", reason="the dask extra is not installed")
    out = tmp_path_factory.mktemp("batch") / "out<i>&"
    rc, stdout, stderr, secs = _run(str(batch_list), "-o", str(out), "--workers", "2", "--no-progress")
    print(f"batch on 2 workers: {secs:.1f} s (load {os.getloadavg()[0]:.2f})")
    return {"rc": rc, "out": out, "stdout": stdout, "stderr": stderr, "seconds": secs}


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def _rows(doc: dict) -> dict[str, dict]:
    return {r["name"]: r for r in doc["samples"]}


def _record(out: Path, name: str, stage: str) -> dict | None:
    p = out / name / "stages" / f"{stage}.json"
    return json.loads(p.read_text()) if p.is_file() else None


def test_batch_on_a_local_cluster_runs_every_sample_and_reports_the_failing_one(cluster_run):
    out, rc = cluster_run["out"], cluster_run["rc"]
    assert rc == 1, cluster_run["stderr"]  # finished, but one sample failed
    # the good samples: every stage recorded, their exports and reports written
    for name in GOOD:
        assert all(_record(out, name, s) is not None for s in STAGES), name
        assert (out / name / "report" / "index.html").is_file()
    assert (out / "a" / "export" / "micro" / "gltf" / "a_micro.gltf").is_file()
    assert (out / "b" / "export" / "micro" / "glb" / "b_micro.glb").is_file()
    assert _record(out, "a", "fit")["params"]["seed"] == 0 and _record(out, "b", "fit")["params"]["seed"] == 1
    # the failing one: its stages before propagate finished, the later ones never ran
    assert [s for s in STAGES if _record(out, "coarse", s) is not None] == []  # refused before any work
    doc = _summary(out)
    assert doc["format"] == "dualscale-batch-summary" and doc["engine"].startswith("local (2 workers")
    rows = _rows(doc)
    assert list(rows) == ["a", "b", "coarse"]
    assert [rows[n]["status"] for n in rows] == ["done", "done", "failed"]
    bad = rows["coarse"]
    assert bad["failed_stage"] == "calibrate" and bad["error"].startswith("InputError: ")
    assert "guidance pixels" in bad["error"] and "InputError" in bad["traceback"]
    assert [bad["stages"][s]["status"] for s in STAGES] == ["failed"] + ["not run"] * (len(STAGES) - 1)
    for name in GOOD:
        r, fit = rows[name], _record(out, name, "fit")["summary"]
        assert all(r["stages"][s]["status"] == "done" and r["stages"][s]["seconds"] > 0 for s in STAGES)
        assert r["heldout_relative_l1"] == fit["heldout_relative_l1"] is not None
        assert r["heldout_baseline_relative_l1"] == fit["heldout_baseline_relative_l1"] is not None
        assert "heldout_ssim" not in r and "cross-validation" in r["heldout_method"]
        comps = fit["components"]
        assert r["components"] == comps and r["components_text"] == ", ".join(
            ["opaque" if comps["opaque"] else "transmissive", "isotropic" if comps["isotropic"] else "anisotropic",
             "tinted" if comps["tinted"] else "untinted"])
        assert r["propagate"] is None and "no guidance" in r["propagate_skipped"]
        assert all((out / f).exists() for e in r["exports"].values() for f in e["files"].values())
        assert (out / r["report"]).is_file()
    assert set(rows["a"]["exports"]["micro"]["files"]) == {"exr", "gltf"}
    assert rows["b"]["exports"]["micro"]["files"] == {"glb": "b/export/micro/glb/b_micro.glb"}
    # the CSV says the same
    table = list(csv.DictReader(io.StringIO((out / "summary.csv").read_text())))
    assert [(t["name"], t["status"], t["failed_stage"]) for t in table] == [
        ("a", "done", ""), ("b", "done", ""), ("coarse", "failed", "calibrate")]
    assert "guidance pixels" in table[2]["error"] and table[2]["seconds_export"] == ""
    assert float(table[0]["seconds_fit"]) > 0 and float(table[0]["heldout_relative_l1"]) == pytest.approx(rows["a"]["heldout_relative_l1"])
    assert table[1]["exports"] == "b/export/micro/glb/b_micro.glb" and table[0]["up_to_date"] == ""
    # the HTML escapes what it shows (the folder's name holds '<i>&')
    html = (out / "summary.html").read_text()
    assert "out&lt;i&gt;&amp;" in html and "out<i>" not in html and "guidance pixels" in html
    # the terminal: one line per sample as it ends, the table, the failure on stderr
    assert "coarse: FAILED at calibrate: InputError" in cluster_run["stdout"]
    assert "a: done in" in cluster_run["stdout"] and "summary.html" in cluster_run["stdout"]
    assert "1 of 3 sample(s) failed: coarse" in cluster_run["stderr"]


def test_a_rerun_skips_every_finished_stage(cluster_run, batch_list):
    out = cluster_run["out"]
    before = {(n, s): _record(out, n, s)["finished"] for n in GOOD for s in STAGES}
    rc, stdout, stderr, secs = _run(str(batch_list), "-o", str(out), "--workers", "2", "--no-progress")
    print(f"rerun on 2 workers: {secs:.1f} s, first run {cluster_run['seconds']:.1f} s (load {os.getloadavg()[0]:.2f})")
    assert rc == 1, stderr
    rows = _rows(_summary(out))
    for name in GOOD:
        assert [rows[name]["stages"][s]["status"] for s in STAGES] == ["up to date"] * len(STAGES)
        assert f"{name}: done in" in stdout and "6 stage(s) up to date" in stdout
    assert {(n, s): _record(out, n, s)["finished"] for n in GOOD for s in STAGES} == before  # nothing redone
    bad = rows["coarse"]
    assert [bad["stages"][s]["status"] for s in STAGES] == ["failed"] + ["not run"] * (len(STAGES) - 1)
    table = list(csv.DictReader(io.StringIO((out / "summary.csv").read_text())))
    assert table[0]["up_to_date"] == ";".join(STAGES)


def test_in_process_gives_the_same_results(cluster_run, batch_list, sample, tmp_path, capsys):
    """``--workers 1``: no Dask; the same stages, records and maps (bit for bit), the same summary
    figures; ``--progress`` counts samples x stages; and a sample's folder is the run folder of
    ``digitize`` with the row's options."""
    import torch

    from dualscale.formats.maps import load_maps

    out = tmp_path / "one"
    rc, stdout, stderr, secs = _run(str(batch_list), "-o", str(out), "--workers", "1", "--progress")
    print(f"batch in-process: {secs:.1f} s (load {os.getloadavg()[0]:.2f})")
    assert rc == 1 and "in this process" in stdout
    assert re.findall(r"\b(\d+)/(\d+) \[", stderr)[-1][1] == "18"  # the bar: 3 samples x 6 stages
    one, two = _rows(_summary(out)), _rows(_summary(cluster_run["out"]))
    assert _summary(out)["engine"] == "in-process"
    for name in ("a", "b", "coarse"):
        for key in ("status", "failed_stage", "components", "heldout_relative_l1", "heldout_baseline_relative_l1", "exports", "report"):
            assert one[name][key] == two[name][key], (name, key)
        ran = {"up to date": "done"}  # the cluster's summary may be its rerun's
        assert [one[name]["stages"][s]["status"] for s in STAGES] == \
            [ran.get(two[name]["stages"][s]["status"], two[name]["stages"][s]["status"]) for s in STAGES]
        for s in STAGES:
            r1, r2 = _record(out, name, s), _record(cluster_run["out"], name, s)
            assert (r1 is None) == (r2 is None), (name, s)
            if r1 is not None:
                assert r1["params"] == r2["params"] and r1["outputs"] == r2["outputs"]
    assert one["coarse"]["error"].split(":")[0] == two["coarse"]["error"].split(":")[0] == "InputError"
    # a sample's run folder is digitize's: the same command finds every stage up to date
    capsys.readouterr()
    assert main(["digitize", str(sample / "micro"), "-o", str(out / "a"), "--quality", "draft", "--export", "exr,gltf",
                 "--seed", "0", "--name", "a", "--threads", "1", "--no-progress"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines()
             if ln.startswith("  ") and ln.split(None, 1)[0] in STAGES]  # the stage lines, not their warnings
    assert len(lines) == len(STAGES) and all(ln.split(None, 1)[1].startswith("up to date") for ln in lines), lines
    for name in GOOD:
        m1, _ = load_maps(out / name / "fit" / "maps")
        m2, _ = load_maps(cluster_run["out"] / name / "fit" / "maps")
        a1, a2 = dict(m1.items()), dict(m2.items())
        assert a1.keys() == a2.keys() and all(torch.equal(a1[k], a2[k]) for k in a1), name


def test_batch_runs_on_a_local_cluster_by_default():
    """``--workers`` unset: the usable cores (a cluster when more than one), at most one worker per
    sample; ``--workers 1`` or a single sample: in this process; ``--threads N``: per worker."""
    import argparse

    pytest.importorskip("distributed", reason="the dask extra is not installed")
    from dualscale.cli.batch import choose_engine
    from dualscale.threads import usable_cores

    def spec(samples, **kw):
        a = argparse.Namespace(**{"workers": None, "scheduler": None, "cluster": "local", "cluster_config": None,
                                  "threads": None, **kw})
        return choose_engine(a, samples)

    n = usable_cores()
    s = spec(50)
    assert (s is None) if n == 1 else (s.workers == n and s.threads_per_worker == 1 and s.cluster == "local")
    assert spec(50, workers=1) is None and spec(1, workers=4) is None
    assert spec(3, workers=8).workers == 3 and spec(3, workers=2, threads=2).threads_per_worker == 2
    from distributed import Scheduler  # noqa: F401 - the address must answer (engine.check_scheduler)
    import asyncio
    import threading

    ready, stop = threading.Event(), None
    box = {}

    async def serve():
        nonlocal stop
        stop = asyncio.Event()
        async with Scheduler(host="127.0.0.1", port=0, dashboard_address=":0") as sched:
            box["address"] = sched.address
            ready.set()
            await stop.wait()

    loop = asyncio.new_event_loop()
    t = threading.Thread(target=loop.run_until_complete, args=(serve(),), daemon=True)
    t.start()
    assert ready.wait(30)
    try:
        assert spec(3, scheduler=box["address"]).scheduler == box["address"]
    finally:
        loop.call_soon_threadsafe(stop.set)
        t.join(30)


def test_run_batch_reports_progress_and_each_sample_as_it_ends(cluster_run, batch_list):
    """The library call in this process on the finished batch: the progress callable sees every
    stage of every sample once, ``on_sample`` each sample once, in list order here."""
    from dualscale.batch import read_list, run_batch

    samples = read_list(batch_list)
    calls, ended = [], []
    res = run_batch(samples, cluster_run["out"], threads=1, progress=lambda d, t, what: calls.append((d, t, what)),
                    on_sample=lambda r: ended.append((r.name, r.status)))
    assert [(d, t) for d, t, _ in calls] == [(i, 18) for i in range(1, 19)]
    assert calls[0][2] == "a calibrate" and calls[-1][2] == "coarse report not run"
    assert ended == [("a", "done"), ("b", "done"), ("coarse", "failed")] == [(r.name, r.status) for r in res]
    assert res[2].failure["stage"] == "calibrate" and res[2].failure["error_type"] == "InputError"


BAD_LISTS = {
    "unknown column": ("samples.csv", "name,input,qualty\na,{micro},draft\n", ["row 0", "column 'qualty'", "unknown column"]),
    "duplicate name": ("samples.csv", "name,input\nA,{micro}\na,{micro}\n", ["row 2 (line 3)", "column 'name'", "row 1 too"]),
    "no input column": ("samples.csv", "name,quality\na,draft\n", ["column 'input'", "missing column"]),
    "bad quality": ("samples.csv", "name,input,quality\na,{micro},best\n", ["row 1 (line 2)", "column 'quality'", "'best'"]),
    "missing input": ("samples.csv", "name,input\na,{micro}\nb,nowhere/micro\n", ["row 2", "column 'input'", "not found"]),
    "unsafe name": ("samples.csv", "name,input\n../up,{micro}\n", ["row 1", "column 'name'", "'../up'"]),
    "reserved name": ("samples.csv", "name,input\nsummary.csv,{micro}\n", ["column 'name'", "the batch's own files"]),
    "bad export": ("samples.csv", "name,input,export\na,{micro},\"gltf,fbx\"\n", ["column 'export'", "fbx"]),
    "bad seed": ("samples.csv", "name,input,seed\na,{micro},-1\n", ["column 'seed'", ">= 0"]),
    "bad tile": ("samples.csv", "name,input,tile\na,{micro},maybe\n", ["column 'tile'", "true or false"]),
    "png guidance without transfer": ("samples.csv", "name,input,guidance\na,{micro},guide.png\n",
                                      ["column 'transfer'", "display-encoded"]),
    "transfer without guidance": ("samples.csv", "name,input,transfer\na,{micro},srgb\n",
                                  ["row 1", "column 'transfer'", "no guidance"]),
    "yaml unknown key": ("samples.yaml", "- name: a\n  input: {micro}\n  colour: red\n", ["row 1", "column 'colour'"]),
    "yaml number as name": ("samples.yaml", "samples:\n  - name: 2024\n    input: {micro}\n",
                            ["row 1", "column 'name'", "quote it"]),
    "yaml not a list": ("samples.yaml", "name: a\n", ["expected a list of samples"]),
    "empty": ("samples.csv", "name,input\n", ["no samples"]),
    "not a list file": ("samples.txt", "a\n", ["a .csv or a .yaml"]),
}


@pytest.mark.parametrize("case", list(BAD_LISTS))
def test_a_bad_list_is_refused_before_anything_is_written(case, sample, tmp_path):
    """Exit 2, one line naming the file, the row and the column; no output folder."""
    fname, text, words = BAD_LISTS[case]
    (tmp_path / "guide.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    path = tmp_path / fname
    path.write_text(text.format(micro=sample / "micro"))
    out = tmp_path / "out"
    rc, stdout, stderr, _ = _run(str(path), "-o", str(out), "--workers", "1", "--no-progress")
    assert rc == 2, (case, stderr)
    line = stderr.strip()
    assert len(line.splitlines()) == 1 and line.startswith("dualscale batch: error: ") and stdout == "", stderr
    assert all(w in line for w in words), (case, line)
    if case != "not a list file":
        assert str(path) in line
    assert not out.exists()


def test_a_yaml_list_with_every_field(sample, tmp_path):
    """The YAML form, relative paths resolved against the list's folder, every field typed."""
    from dualscale.batch import read_list

    (tmp_path / "cal.json").write_text("{}")
    path = tmp_path / "sub" / "samples.yml"
    path.parent.mkdir()
    micro = os.path.relpath(sample / "micro", path.parent)
    path.write_text(f"samples:\n"
                    f"  - name: twill-1\n    input: {micro}\n    calibration: ../cal.json\n"
                    f"    guidance: {sample / 'mid'}\n    guidance_texel_mm: 0.00625\n    quality: paper\n"
                    f"    export: [gltf, u3m]\n    tile: yes\n    seed: 7\n"
                    f"  - name: twill-2\n    input: {micro}\n    export: all\n    tile: 'false'\n")
    s1, s2 = read_list(path, quality="draft", export=("exr",))
    assert s1.input == sample / "micro" and s1.calibration == tmp_path / "cal.json" and s1.guidance == sample / "mid"
    assert (s1.guidance_texel_mm, s1.quality, s1.export, s1.tile, s1.seed) == (0.00625, "paper", ("gltf", "u3m"), True, 7)
    assert (s2.quality, s2.tile, s2.seed, s2.calibration) == ("draft", False, 0, None) and "glb" in s2.export
    opts = s1.options(tmp_path / "out", threads=1)
    assert opts.run == tmp_path / "out" / "twill-1" and opts.name == "twill-1" and opts.progress is False


def test_the_summary_page_shows_one_row_per_sample_in_a_browser(cluster_run, tmp_path):
    """summary.html in headless Chromium: one table row per sample, the failure's error shown as
    text (escaped, no markup from the data), links to the reports, nothing fetched from outside."""
    from tests.cdp import Browser

    out = cluster_run["out"]
    url = (out / "summary.html").as_uri()
    with Browser(tmp_path / "profile", vendor=False) as page:
        page.send("Page.navigate", {"url": url})
        page.wait_event("Page.loadEventFired", 60)
        names = page.evaluate("[...document.querySelectorAll('tbody tr.sample')].map(r => r.dataset.name)")
        assert names == ["a", "b", "coarse"]
        status = page.evaluate("[...document.querySelectorAll('tbody tr.sample')].map(r => r.cells[1].innerText)")
        assert status[:2] == ["done", "done"] and status[2].startswith("failed") and "guidance pixels" in status[2]
        assert page.evaluate("document.querySelectorAll('main i').length") == 0  # '<i>' of the path stayed text
        assert "out<i>&" in page.evaluate("document.body.innerText")
        links = page.evaluate("[...document.querySelectorAll('tbody tr.sample td:first-child a')]"
                              ".map(a => a.getAttribute('href'))")
        assert links == ["a/report/index.html", "b/report/index.html"]
        assert all((out / h).is_file() for h in links)
        problems = page.problems(out.as_uri())
        assert not problems["errors"] and not problems["failed"] and not problems["external"], problems


def test_a_sample_that_fails_the_runs_check_is_a_failed_sample(sample, tmp_path, figures_not_drawn):
    """Issue 24 trial: a sample whose fit failed the run's check was "done" and the batch exited
    0, with no check column in the summary.  Now its status is "check failed: <check>", the
    summary (CSV, JSON, HTML) has a check column, and the batch exits 1; a good sample's check
    says passed.  (In this process, the run reports' figures not drawn: most of the time; the
    batch's reports are drawn by cluster_run and test_in_process_gives_the_same_results.)"""
    from .noise import make_noise_dataset

    noise = make_noise_dataset(tmp_path / "noise")
    lst = tmp_path / "samples.csv"
    lst.write_text("name,input,quality,export\n"
                   f"good,{sample / 'micro'},draft,exr\n"
                   f"noise,{noise},draft,exr\n")
    out = tmp_path / "out"
    rc, stdout, stderr, _ = _run(str(lst), "-o", str(out), "--workers", "1", "--threads", "1", "--no-progress")
    assert rc == 1, (stdout, stderr)
    rows = _rows(_summary(out))
    assert rows["good"]["status"] == "done" and rows["good"]["check"] == "passed"
    assert rows["noise"]["status"] == "check failed: fit against the constant predictor", rows["noise"]
    assert rows["noise"]["check"].startswith("failed: fit held-out relative L1")
    assert rows["noise"]["check_ok"] is False and rows["good"]["check_ok"] is True
    assert "noise: FAILED check failed: fit against the constant predictor" in stdout, stdout
    assert "1 of 2 sample(s) failed: noise" in stderr, stderr
    with open(out / "summary.csv", newline="") as f:
        csv_rows = {r["name"]: r for r in csv.DictReader(f)}
    assert csv_rows["good"]["check"] == "passed" and csv_rows["noise"]["check"].startswith("failed: ")
    assert csv_rows["noise"]["status"].startswith("check failed")
    page = (out / "summary.html").read_text()
    assert "<th title=\"the run's own checks (docs/DIGITIZE.md)\">check</th>" in page
    assert "✗" in page and "check failed: fit against the constant predictor" in page
    assert json.loads((out / "noise" / "run.json").read_text())["checks"][1]["ok"] is False
