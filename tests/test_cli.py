"""The `dualscale` command line: sim, console, flash --dry-run."""
from __future__ import annotations

import argparse
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
    """A simulator that was never built is the environment's problem: exit 4 (ToolError)."""
    env = dict(os.environ, DUALSCALE_FIRMWARE_BUILD=str(tmp_path))
    r = subprocess.run([*DUALSCALE, "sim"], capture_output=True, text=True, env=env, timeout=30)
    assert r.returncode == 4 and "make -C firmware posix" in r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr


# ---- errors meet the user in one place: cli.main -> one line on stderr, one exit code -------------

def _bad_inputs(tmp_path: Path) -> dict[str, tuple[list[str], int, str]]:
    """Each subcommand's typical bad input: (argv, exit code, what the line must say)."""
    missing = str(tmp_path / "missing")
    (tmp_path / "maps").mkdir()
    return {
        "usage": (["fit"], 2, "required: dataset"),
        "sim": (["sim", "--target", "posix"], 4, "make -C firmware posix"),
        "demo": (["demo"], 4, "make -C firmware posix"),
        "console": (["console", "--port", missing, "-c", "id"], 2, "cannot open serial port"),
        "flash": (["flash"], 4, "no flashing tool found"),
        "synth": (["synth", "twill", "-o", str(tmp_path / "s"), "--size", "16", "--lights", "every3"], 2, "--lights"),
        "render": (["render", missing, "-o", str(tmp_path / "r"), "--led", "3"], 2, "missing"),
        "render-led": (["render", str(tmp_path / "maps"), "-o", str(tmp_path / "r"), "--led", "500"], 2,
                       "out of range"),
        "synth-targets": (["synth-targets", "-o", str(tmp_path / "t"), "--parts", "chart,rainbow"], 2, "rainbow"),
        "calibrate": (["calibrate", missing, "-o", str(tmp_path / "c.json")], 2, "missing"),
        "evaluate-device": (["evaluate-device", missing, "--calibration", missing, "-o", str(tmp_path / "e")],
                            2, "missing"),
        "fit": (["fit", missing, "-o", str(tmp_path / "f")], 2, "missing"),
        "fit-threads": (["fit", missing, "-o", str(tmp_path / "f"), "--threads", "0"], 2, "--threads"),
        "study": (["study", "lights", missing, "-o", str(tmp_path / "st")], 2, "missing"),
        "flyouts": (["flyouts", missing, "-o", str(tmp_path / "fo")], 2, "missing"),
        "propagate-train": (["propagate", "train", missing, missing, "--maps", missing, "-o", str(tmp_path / "m")],
                            2, "--maps"),
        "propagate-export": (["propagate", "export", missing], 2, "missing"),
        "propagate-run": (["propagate", "run", missing, missing, "-o", str(tmp_path / "pr")], 2, "missing"),
        "digitize": (["digitize", missing, "-o", str(tmp_path / "run")], 2, "missing"),
    }


BAD = ["usage", "sim", "demo", "console", "flash", "synth", "render", "render-led", "synth-targets", "calibrate",
       "evaluate-device", "fit", "fit-threads", "study", "flyouts", "propagate-train", "propagate-export",
       "propagate-run", "digitize"]


@pytest.mark.parametrize("case", BAD)
def test_bad_input_is_one_line_and_an_exit_code(case, tmp_path, monkeypatch, capsys):
    from dualscale.cli import main

    monkeypatch.setenv("DUALSCALE_FIRMWARE_BUILD", str(tmp_path / "no-build"))
    monkeypatch.setenv("PATH", "")  # no flashing tool (nor anything else) on the PATH
    monkeypatch.delenv("DUALSCALE_DEBUG", raising=False)
    argv, code, needle = _bad_inputs(tmp_path)[case]
    assert main(argv) == code
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.endswith("\n"), err
    assert err.startswith("dualscale ") and "error: " in err and needle in err, err
    assert "Traceback" not in err


def test_flash_without_a_tool_ends_in_one_line_not_a_traceback(tmp_path):
    env = dict(os.environ, PATH="", DUALSCALE_FIRMWARE_BUILD=str(tmp_path))
    env.pop("DUALSCALE_DEBUG", None)
    r = subprocess.run([*DUALSCALE, "flash"], capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 4, r.stderr
    assert r.stderr == ("dualscale flash: error: no flashing tool found: install PlatformIO, openocd, "
                        "stlink-tools or dfu-util\n")


def test_interrupt_and_internal_errors_are_one_line(monkeypatch, capsys):
    from dualscale import cli
    from dualscale.errors import EXIT_CODES, Interrupted

    def raising(exc):
        def fn(_args):
            raise exc
        return fn

    cases = [(KeyboardInterrupt(), EXIT_CODES["interrupted"], "interrupted; run the same command again"),
             (Interrupted("stopped at iteration 4"), 130, "stopped at iteration 4; run the same command again"),
             (ZeroDivisionError("x"), EXIT_CODES["internal"], "internal error: ZeroDivisionError: x"),
             (OSError(28, "No space left on device", "/out/x.exr"), EXIT_CODES["tool"],
              "error: No space left on device: /out/x.exr"),
             (ValueError("line one\nline two"), EXIT_CODES["input"], "error: line one; line two")]
    for exc, code, needle in cases:
        monkeypatch.setattr(cli, "cmd_flash", raising(exc))  # build_parser binds it at each main()
        assert cli.main(["flash"]) == code
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and needle in err and "Traceback" not in err, err


def test_the_same_output_and_work_options_everywhere():
    """Every command that writes takes -o/--output (dest output); the long ones take --threads
    and --progress/--no-progress."""
    from dualscale.cli import build_parser

    long_ones = {"synth", "render", "synth-targets", "calibrate", "evaluate-device", "fit", "study lights",
                 "flyouts", "propagate train", "propagate run"}
    seen = set()

    def walk(parser, name):
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if subs:
            for n, p in subs[0].choices.items():
                walk(p, f"{name} {n}".strip())
            return
        opts = {o: a for a in parser._actions for o in a.option_strings}
        if "-o" in opts:
            assert opts["-o"] is opts.get("--output") and opts["-o"].dest == "output", name
            seen.add(name)
        if name in long_ones:
            assert "--threads" in opts and "--progress" in opts and "--no-progress" in opts, name
            assert opts["--progress"].default is None, name  # None = on when stderr is a terminal

    walk(build_parser(), "")
    assert long_ones <= seen


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


def test_flash_with_a_missing_tool_refuses_before_building(monkeypatch, capsys):
    """`--tool openocd` without openocd: exit 4 at once, no firmware build first."""
    import subprocess

    from dualscale.cli import main

    monkeypatch.setattr(fl.shutil, "which", lambda name: None)
    ran = []
    monkeypatch.setattr(subprocess, "run", lambda *a, **k: ran.append(a))
    assert main(["flash", "--tool", "openocd"]) == 4
    assert "openocd is not installed" in capsys.readouterr().err and ran == []


def test_every_option_has_help():
    """Issue 24 §5: every option of every command says what it does in --help, and an option
    that takes a value and has a default (not None, not an empty list) says that default."""
    import argparse

    from dualscale.cli import build_parser

    missing, no_default = [], []

    def walk(p, path):
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for n, sp in a.choices.items():
                    walk(sp, path + [n])
            elif a.option_strings and a.dest != "help" and not a.help:  # SUPPRESS: hidden on purpose
                missing.append(f"{' '.join(path)} {'/'.join(a.option_strings)}")
            elif (a.option_strings and a.help is not argparse.SUPPRESS and a.nargs != 0  # flags take no value
                  and a.default not in (None, [], argparse.SUPPRESS) and "default" not in a.help.lower()):
                no_default.append(f"{' '.join(path)} {a.option_strings[-1]}")

    walk(build_parser(), [])
    assert not missing, missing
    assert not no_default, sorted(no_default)


def test_digitize_names_the_command_line_the_user_can_run(monkeypatch, tmp_path):
    """Issue 24 §5: after `make demo`, `dualscale` is not on PATH; the last lines name
    `.venv/bin/dualscale` (the script that ran), or `dualscale` when that is on PATH."""
    import os
    import sys

    from dualscale.cli.digitize import _cli_name

    script = tmp_path / ".venv" / "bin" / "dualscale"
    script.parent.mkdir(parents=True)
    script.write_text("#!/bin/sh\n")
    script.chmod(0o755)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [str(script)])
    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    assert _cli_name() == os.path.join(".venv", "bin", "dualscale")
    monkeypatch.setenv("PATH", f"{script.parent}:/usr/bin")
    assert _cli_name() == "dualscale"
    monkeypatch.setattr(sys, "argv", ["-c"])
    assert _cli_name().endswith("-m dualscale.cli")


def test_digitize_takes_tile_px_and_checks_it_before_work(tmp_path, capsys):
    """`digitize --tile-px` (issue 24 §8): the fit's tile side, checked before any work."""
    from dualscale.cli import build_parser, main

    a = build_parser().parse_args(["digitize", "x", "-o", str(tmp_path / "r"), "--workers", "2", "--tile-px", "32"])
    assert a.tile_px == 32
    assert main(["digitize", str(tmp_path / "nope"), "-o", str(tmp_path / "r"), "--tile-px", "0"]) == 2
    assert "--tile-px" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
