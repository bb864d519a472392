"""Check that PlatformIO (pio_sources.py) and the Makefile build the STM32 image from the same
sources with the same flags. Both read sources.mk; this catches either side drifting.

    python3 tools/check_pio_flags.py        exit 0 when identical
"""
import os
import subprocess
import sys

FW = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def lines(cmd):
    out = subprocess.run(cmd, cwd=FW, capture_output=True, text=True, check=True).stdout
    return {ln.split(" = ", 1)[0]: ln.split(" = ", 1)[1].split()
            for ln in out.splitlines() if ln.startswith("stm32.")}


def main():
    make = lines(["make", "-s", "--no-print-directory", "flags"])
    pio = lines([sys.executable, "pio_sources.py", "--print"])
    ok = make == pio and set(make) == {"stm32.srcs", "stm32.cflags", "stm32.incs", "stm32.ldflags", "stm32.libs"}
    for key in sorted(set(make) | set(pio)):
        same = make.get(key) == pio.get(key)
        print(("same " if same else "DIFF ") + key)
        if not same:
            print("  make:", make.get(key))
            print("  pio: ", pio.get(key))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
