"""The `dualscale` command line."""
from __future__ import annotations

import argparse
import signal
import sys
import time

from .rig.client import RigClient, RigError
from .rig.sim import SimError, SimulatedRig


def cmd_sim(a: argparse.Namespace) -> int:
    stop = {"now": False}

    def handler(signum, frame):
        stop["now"] = True

    # before the device line goes out: a caller may signal as soon as it has read it
    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    rig = SimulatedRig(a.target, link=a.link, speed=a.speed, hw_socket=a.hw_socket, icount=a.icount)
    rig.start()
    print(rig.port, flush=True)
    if a.link:
        print(f"linked {a.link} -> {rig.port}", file=sys.stderr)
    try:
        while not stop["now"] and rig.alive():
            time.sleep(0.1)
    finally:
        died = not rig.alive()
        rig.stop()
    if died and not stop["now"]:
        print("the simulator exited unexpectedly", file=sys.stderr)
        return 1
    return 0


def cmd_console(a: argparse.Namespace) -> int:
    from .rig.console import Console, run_script

    with RigClient(a.port, address=a.address) as rig:
        con = Console(rig)
        if a.c is not None:
            return run_script(con, a.c)
        con.cmdloop()
    return 0


def cmd_flash(a: argparse.Namespace) -> int:
    from .rig.flash import flash

    return flash(a.tool, dry_run=a.dry_run, port=a.port)


def cmd_demo(a: argparse.Namespace) -> int:
    from .rig.demo import run_demo

    rep = run_demo(a.target, speed=a.speed, on_event=print if a.events else None)
    return 0 if rep.state == "DONE" and rep.dropped == 0 else 1


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dualscale", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)

    s = sub.add_parser("sim", help="start the simulated rig (prints its serial device first)")
    s.add_argument("--target", choices=("posix", "qemu"), default="posix")
    s.add_argument("--link", help="make a symlink to the serial device at this path")
    s.add_argument("--speed", type=float, default=1.0,
                   help="posix: 1 = real time, >1 accelerated virtual time, 0 = as fast as possible")
    s.add_argument("--hw-socket", help="posix: Unix socket for the simulated hardware side channel")
    s.add_argument("--icount", help="qemu: -icount option, e.g. shift=4")
    s.set_defaults(fn=cmd_sim)

    c = sub.add_parser("console", help="interactive serial console")
    c.add_argument("--port", required=True, help="serial device or pyserial URL")
    c.add_argument("--address", type=int, default=1)
    c.add_argument("-c", metavar="CMDS", help='run ";"-separated commands and exit')
    c.set_defaults(fn=cmd_console)

    f = sub.add_parser("flash", help="build and flash the STM32F405 firmware")
    f.add_argument("--tool", choices=("auto", "pio", "openocd", "st-flash", "dfu-util"), default="auto")
    f.add_argument("--dry-run", action="store_true", help="print the exact commands only")
    f.add_argument("--port", help="serial port to check the firmware version on afterwards")
    f.set_defaults(fn=cmd_flash)

    d = sub.add_parser("demo", help="run the full micro-capture sequence on the simulated rig")
    d.add_argument("--target", choices=("posix", "qemu"), default="posix")
    d.add_argument("--speed", type=float, default=10.0, help="posix simulator speed (see sim)")
    d.add_argument("--events", action="store_true", help="print every event")
    d.set_defaults(fn=cmd_demo)

    from .cli_appearance import register as register_appearance

    register_appearance(sub)
    from .cli_calib import register as register_calib

    register_calib(sub)
    from .cli_fit import register as register_fit

    register_fit(sub)
    from .cli_propagate import register as register_propagate

    register_propagate(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.fn(args)
    except (RigError, SimError, ValueError, OSError) as e:
        print(f"dualscale {args.cmd}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
