"""`dualscale view` on a stop request (issue 24, fresh-user trial): SIGTERM and SIGHUP end it
like Ctrl-C -- exit 130, one line naming the signal, and its PNG cache folder
(``$TMPDIR/dualscale-view-*``) removed; it died with 143/129 and left the folder behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import urllib.request

import pytest

from .folders import run_folder


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_view_stops_on_a_stop_request_and_removes_its_cache(tmp_path, sig):
    from dualscale.view import vendor_missing

    if vendor_missing():
        pytest.skip("three.js is not in static/vendor (make node)")
    run = run_folder(tmp_path / "RUN")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "TMPDIR": str(tmp)}
    env.pop("DUALSCALE_DEBUG", None)
    p = subprocess.Popen([sys.executable, "-m", "dualscale.cli", "view", str(run), "--no-browser", "--led", "3"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = p.stdout.readline()
        assert "dualscale view: serving" in line, (line, p.stderr.read() if p.poll() is not None else "")
        base = line.split(" at ")[1].split()[0].split("?")[0]
        with urllib.request.urlopen(base + "api/led/3/captured.png", timeout=60) as r:  # fills the cache
            assert r.status == 200
        assert [d.name for d in tmp.iterdir() if d.name.startswith("dualscale-view-")], "no cache folder"
        p.send_signal(sig)
        _, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130, (p.returncode, err)
    assert "Traceback" not in err and err.count("\n") == 1, err
    assert err.startswith(f"dualscale view: stopped by {sig.name}; run the same command again"), err
    assert not [d for d in tmp.iterdir() if d.name.startswith("dualscale-view-")], "the cache folder was left behind"
