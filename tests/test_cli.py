"""The `dualscale` command line: sim, console, flash --dry-run."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from dualscale.rig import flash as fl

DUALSCALE = [sys.executable, "-m", "dualscale.cli"]


@pytest.fixture
def sim_link(tmp_path):
    link = tmp_path / "rig"
    p = subprocess.Popen([*DUALSCALE, "sim", "--target", "posix", "--link", str(link)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = p.stdout.readline().strip()
    yield p, first, link
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        p.wait(10)


def test_sim_prints_its_device_first_and_links_it(sim_link):
    p, first, link = sim_link
    assert first.startswith("/dev/pts/")
    assert link.is_symlink() and os.readlink(link) == first
    p.send_signal(signal.SIGINT)
    assert p.wait(10) == 0
    assert not link.exists()


def test_console_script(sim_link):
    _, _, link = sim_link
    r = subprocess.run([*DUALSCALE, "console", "--port", str(link), "-c",
                        "id; intensity 500; led 3 on; diffuse on; lights; alloff; lights; pol p90; status"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "dualscale fw=0.1.0" in r.stdout
    assert "led 3, diffuse 0" in r.stdout and "all lights off" in r.stdout
    assert "polarizer_cdeg   9000" in r.stdout


def test_console_uploads_runs_and_follows_a_sequence(sim_link, tmp_path):
    _, _, link = sim_link
    seq = tmp_path / "seq.json"
    seq.write_text(json.dumps([
        {"source": "led", "index": i, "intensity": 900, "settle_us": 500, "exposure_us": 1000,
         "pulse_us": 100, "brackets": 2, "ev_step": 1, "triggers": 1} for i in range(3)]))
    r = subprocess.run([*DUALSCALE, "console", "--port", str(link), "-c",
                        f"watchdog 2000; upload {seq}; run; events; start; abort; events; watchdog 0"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "uploaded 3 steps" in r.stdout and "DONE: 14 events" in r.stdout
    assert "SEQ_ABORT" in r.stdout


def test_console_rejects_a_malformed_sequence_file(sim_link, tmp_path):
    _, _, link = sim_link
    bad = tmp_path / "bad.json"
    bad.write_text('[{"source": "laser", "index": 1}]')
    r = subprocess.run([*DUALSCALE, "console", "--port", str(link), "-c",
                        f"upload {bad}; upload {tmp_path / 'missing.json'}; upload {tmp_path}"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1
    assert "step 0 is malformed" in r.stdout and "no such sequence file" in r.stdout
    assert "cannot read sequence file" in r.stdout


def test_console_reports_errors_and_fails(sim_link):
    _, _, link = sim_link
    r = subprocess.run([*DUALSCALE, "console", "--port", str(link), "-c", "led 300 on; pol 20000; pol 99999; frobnicate"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1
    assert r.stdout.count("error:") == 4
    assert "must be 0..65535" in r.stdout
    assert "ILLEGAL DATA VALUE" in r.stdout


def test_console_on_a_missing_port_is_a_clear_error(tmp_path):
    r = subprocess.run([*DUALSCALE, "console", "--port", str(tmp_path / "nope"), "-c", "id"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "cannot open serial port" in r.stderr


@pytest.mark.parametrize("tool,needle", [
    ("pio", "pio run -d"), ("openocd", "program"), ("st-flash", "write"), ("dfu-util", "0483:df11")])
def test_flash_dry_run_prints_the_exact_command(tool, needle):
    r = subprocess.run([*DUALSCALE, "flash", "--tool", tool, "--dry-run"], capture_output=True, text=True)
    assert r.returncode == 0 and needle in r.stdout
    if tool != "pio":
        lines = r.stdout.strip().splitlines()
        assert lines[0].startswith("make -C") and lines[0].endswith("stm32")
        assert str(fl.build_dir() / "stm32f405") in lines[1]


def test_flash_without_tools_says_what_to_install(monkeypatch):
    monkeypatch.setattr(fl.shutil, "which", lambda name: None)
    with pytest.raises(fl.FlashError, match="no flashing tool found"):
        fl.flash("auto")


def test_flash_verifies_the_version_over_modbus(sim_link):
    _, _, link = sim_link
    assert "fw=0.1.0" in fl.verify_version(str(link))


def test_sim_reports_a_missing_binary(tmp_path):
    env = dict(os.environ, DUALSCALE_FIRMWARE_BUILD=str(tmp_path))
    r = subprocess.run([*DUALSCALE, "sim"], capture_output=True, text=True, env=env, timeout=30)
    assert r.returncode == 2 and "make -C firmware posix" in r.stderr


def test_pio_builds_the_same_sources_and_flags_as_make():
    """PlatformIO's extra script and the Makefile both read firmware/sources.mk: same build."""
    fw = Path(__file__).resolve().parents[1] / "firmware"

    def stm32(cmd):
        out = subprocess.run(cmd, cwd=fw, capture_output=True, text=True, check=True).stdout
        return {k: v.split() for k, _, v in (ln.partition(" = ") for ln in out.splitlines())
                if k.startswith("stm32.")}

    make = stm32(["make", "-s", "--no-print-directory", "flags"])
    pio = stm32([sys.executable, "pio_sources.py", "--print"])
    assert set(make) == {"stm32.srcs", "stm32.cflags", "stm32.incs", "stm32.ldflags", "stm32.libs"}
    assert make == pio
    assert "core/src/seq.c" in make["stm32.srcs"] and "-mcpu=cortex-m4" in make["stm32.cflags"]
