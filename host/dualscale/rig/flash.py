"""`dualscale flash`: build and flash the STM32F405 image, then check its version over Modbus.

Tools, in the order `--tool auto` tries them: PlatformIO (`pio run -t upload`, same sources
and flags as the Makefile), openocd and st-flash (ST-LINK/SWD), dfu-util (the F405's built-in
USB DFU bootloader: hold BOOT0 high and reset).
"""
from __future__ import annotations

from dualscale.errors import ToolError

import shlex
import shutil
import subprocess
from pathlib import Path

from ..protocol import regmap as rm
from .client import RigClient
from .launcher import REPO, build_dir

TOOLS = ("pio", "openocd", "st-flash", "dfu-util")
FLASH_BASE = 0x08000000
DFU_ID = "0483:df11"  # STMicroelectronics DFU bootloader


class FlashError(ToolError):
    """No flashing tool, no firmware image, or the tool failed."""


def flash_command(tool: str, elf: Path, binary: Path) -> list[str]:
    fw = REPO / "firmware"
    if tool == "pio":
        return ["pio", "run", "-d", str(fw), "-e", "stm32f405", "-t", "upload"]
    if tool == "openocd":
        return ["openocd", "-f", "interface/stlink.cfg", "-f", "target/stm32f4x.cfg",
                "-c", f"program {elf} verify reset exit"]
    if tool == "st-flash":
        return ["st-flash", "--reset", "write", str(binary), f"0x{FLASH_BASE:08x}"]
    if tool == "dfu-util":
        return ["dfu-util", "-d", DFU_ID, "-a", "0", "-s", f"0x{FLASH_BASE:08x}:leave", "-D", str(binary)]
    raise FlashError(f"unknown tool {tool!r}; choose from {', '.join(TOOLS)}")


def pick_tool(tool: str) -> str:
    if tool != "auto":
        return tool
    for t in TOOLS:
        if shutil.which(t):
            return t
    raise FlashError("no flashing tool found: install PlatformIO, openocd, stlink-tools or dfu-util")


def build_command(tool: str) -> list[str] | None:
    """PlatformIO builds as part of upload; the others flash what `make` built."""
    return None if tool == "pio" else ["make", "-C", str(REPO / "firmware"), "stm32"]


def verify_version(port: str, address: int = rm.DEFAULT_ADDRESS) -> str:
    """Read Report Server ID and check that the firmware is the version just built."""
    with RigClient(port, address=address) as rig:
        ident = rig.identity
    want = "fw={}.{}.{}".format(*rm.FIRMWARE_VERSION)
    if want not in ident.text:
        raise FlashError(f"device reports {ident.text!r}; expected {want} after flashing")
    return ident.text


def flash(tool: str = "auto", dry_run: bool = False, port: str | None = None, out=print) -> int:
    try:
        t = pick_tool(tool)
    except FlashError:
        if not dry_run:
            raise
        t = "dfu-util"  # needs no probe: show the bootloader route
    elf = build_dir() / "stm32f405" / "dualscale.elf"
    binary = elf.with_suffix(".bin")
    cmds = [c for c in (build_command(t), flash_command(t, elf, binary)) if c]
    missing = [c[0] for c in cmds if not shutil.which(c[0])]
    if dry_run:
        for c in cmds:
            out(shlex.join(c))
        if missing:
            out(f"# not installed here: {', '.join(missing)}")
        return 0
    if missing:  # before building anything
        raise FlashError(f"{', '.join(missing)} is not installed")
    for c in cmds:
        r = subprocess.run(c)
        if r.returncode != 0:
            raise FlashError(f"`{shlex.join(c)}` failed with exit code {r.returncode}")
    if port:
        out("flashed; device reports: " + verify_version(port))
    else:
        out("flashed; pass --port to check the version over Modbus")
    return 0
