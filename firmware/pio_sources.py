"""PlatformIO extra_script: build exactly the sources and flags that the Makefile builds.

Both builds read firmware/sources.mk (plain `NAME = words` lines); nothing about the STM32
image is restated in platformio.ini. platformio.ini lists this script twice:

  pre:  sets the source filter (only CORE_SRCS + STM32_SRCS are compiled) and the linker script;
  post: replaces the flags that the ststm32 platform's bare-metal builder adds (-Os, -nostdlib,
        --specs=nosys.specs, its own CPPDEFINES, ...) with CORE_CFLAGS + STM32_CFLAGS,
        STM32_LDFLAGS and STM32_LIBS, in the global and the project environment alike.

Outside SCons it is a plain program:
  python3 pio_sources.py --print   prints what PlatformIO would use, in the same format as
                                   `make -s -C firmware flags` (stm32.* lines), so a test can
                                   compare the two (tests/test_cli.py does).
"""
import os
import re
import shlex
import sys

_ASSIGN = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)\s*(\+?=|:=)\s*(.*)$")


def firmware_dir():
    try:
        here = os.path.dirname(os.path.abspath(__file__))
    except NameError:  # SCons executes extra scripts without __file__
        here = os.getcwd()
    if not os.path.exists(os.path.join(here, "sources.mk")):
        # SCons: the project dir is the firmware folder
        here = os.getcwd()
    return here


def parse_sources_mk(path):
    """The variables of sources.mk as lists of words. Only `NAME = words` (and `+=`, `:=`)
    lines, comments and blank lines are allowed; anything else is an error, so the file cannot
    grow make-isms this parser would silently misread."""
    out = {}
    with open(path, encoding="utf-8") as f:
        for n, raw in enumerate(f, 1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            m = _ASSIGN.match(line)
            if not m or "$" in m.group(3):
                raise ValueError(f"{path}:{n}: not a plain `NAME = words` line: {raw.rstrip()}")
            name, op, value = m.groups()
            words = shlex.split(value)
            out[name] = out.get(name, []) + words if op == "+=" else words
    return out


def stm32_config(fw_dir=None):
    fw_dir = fw_dir or firmware_dir()
    v = parse_sources_mk(os.path.join(fw_dir, "sources.mk"))
    return {
        "srcs": v["CORE_SRCS"] + v["STM32_SRCS"],
        "cflags": v["CORE_CFLAGS"] + v["STM32_CFLAGS"],
        "incs": v["CORE_INCS"] + v["STM32_INCS"],
        "ldflags": v["STM32_LDFLAGS"] + ["-T" + v["STM32_LDSCRIPT"][0]],
        "ldscript": v["STM32_LDSCRIPT"][0],
        "libs": v["STM32_LIBS"],
    }


def print_config(cfg):
    for key in ("srcs", "cflags", "incs", "ldflags", "libs"):
        print(f"stm32.{key} = {' '.join(cfg[key])}")


# ---- SCons side ---------------------------------------------------------------------------------

def _apply_pre(env, cfg, fw_dir):
    # Sources are given relative to the firmware folder, which platformio.ini makes src_dir.
    env.Replace(SRC_FILTER=["-<*>"] + [f"+<{s}>" for s in cfg["srcs"]])
    env.Replace(LDSCRIPT_PATH=os.path.join(fw_dir, cfg["ldscript"]))


def _apply_post(envs, cfg, fw_dir):
    libs = [w[2:] for w in cfg["libs"] if w.startswith("-l")]
    for e in envs:
        e.Replace(
            CCFLAGS=list(cfg["cflags"]),
            CFLAGS=[],
            CXXFLAGS=[],
            ASFLAGS=[f for f in cfg["cflags"] if f.startswith(("-m", "-g"))],
            CPPDEFINES=[],
            CPPPATH=[os.path.join(fw_dir, d) for d in cfg["incs"]],
            # -T with an absolute path: the Replace drops the -T that PlatformIO prepended from
            # LDSCRIPT_PATH while building the program, so it is given here once, explicitly.
            LINKFLAGS=[f for f in cfg["ldflags"] if not f.startswith("-T")]
            + ["-T" + os.path.join(fw_dir, cfg["ldscript"])],
            LIBS=libs,
            LDSCRIPT_PATH=os.path.join(fw_dir, cfg["ldscript"]),
        )


def _scons_main():
    Import = globals()["Import"]  # noqa: N806 (provided by SCons)
    Import("env")
    env = globals()["env"]
    fw_dir = env.subst("$PROJECT_DIR")
    cfg = stm32_config(fw_dir)
    try:
        Import("projenv")
        projenv = globals()["projenv"]
    except Exception:  # pre: phase, projenv does not exist yet
        _apply_pre(env, cfg, fw_dir)
        return
    _apply_post([env, projenv], cfg, fw_dir)


if __name__ == "__main__":
    if "--print" in sys.argv[1:]:
        print_config(stm32_config())
        sys.exit(0)
    print(__doc__)
    sys.exit(2)
elif "Import" in globals():
    _scons_main()
