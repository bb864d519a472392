"""Boot check of the STM32F405 image in QEMU (netduinoplus2), standard library only.

Launches qemu-system-arm with USART1 on a pty, finds the pty in QEMU's "char device
redirected to /dev/pts/N" line, then talks Modbus RTU to the firmware:
  FC 11 (target=stm32f405), FC 04 identity registers, the µs clock against wall time,
  a two-step device-master sequence whose event timestamps are read back from the FIFO window,
  and optionally mbpoll (the acceptance test's client) for FC 11 and FC 04.

    python3 tools/qemu_check.py [--elf build/stm32f405/dualscale.elf] [--icount shift=4] [--mbpoll]
"""
import argparse
import os
import re
import select
import shutil
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import rtu  # noqa: E402
from sim_check import STEP_TABLE, HR_COMMAND, HR_SEQ_LEN, CMD_START, EVT, step, check  # noqa: E402

IR_STATE, IR_UPTIME, IR_EVT_COUNT, IR_EVT_WINDOW = 8, 13, 17, 256


def start_qemu(elf, icount=None, timeout=10.0):
    """Start QEMU; returns (process, pty path). QEMU 7.2 prints the pty line on stdout (stderr is
    merged here in case another version differs)."""
    cmd = ["qemu-system-arm", "-M", "netduinoplus2", "-nographic", "-monitor", "none",
           "-serial", "pty", "-kernel", elf]
    if icount:
        cmd += ["-icount", icount]
    p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    buf = b""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        r, _, _ = select.select([p.stdout], [], [], 0.1)
        if r:
            chunk = os.read(p.stdout.fileno(), 4096)
            if not chunk:
                break
            buf += chunk
            m = re.search(rb"redirected to (/dev/pts/\d+)", buf)
            if m:
                return p, m.group(1).decode()
    p.kill()
    raise RuntimeError(f"QEMU did not report its pty: {buf.decode(errors='replace')}")


def u48(words):
    return words[0] << 32 | words[1] << 16 | words[2]


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser()
    ap.add_argument("--elf", default=os.path.join(here, "..", "build", "stm32f405", "dualscale.elf"))
    ap.add_argument("--icount", default=None, help="e.g. shift=4 (no sleep=off: the host is real)")
    ap.add_argument("--mbpoll", action="store_true", help="also run mbpoll -u and -t 3")
    a = ap.parse_args()

    p, pts = start_qemu(a.elf, a.icount)
    # QEMU's pty backend notices a client only by polling once a second, and drops back to
    # "disconnected" (discarding guest output) whenever the last client closes the slave. Hold
    # one descriptor for the whole run so clients (rtu.Port, then mbpoll) can come and go.
    keeper = os.open(pts, os.O_RDWR | os.O_NOCTTY)
    try:
        print(f"     QEMU pty: {pts}")
        port = rtu.Port(pts)
        for attempt in range(20):  # the guest may still be starting
            try:
                sid, run, text = port.report_server_id()
                break
            except TimeoutError:
                time.sleep(0.1)
        else:
            check(False, "FC11 answered")
        check(sid == 1 and run == 0xFF and "target=stm32f405" in text, f"FC11: {text}")
        ir = port.read_input(0, 8)
        check(ir[0] == 0x4453 and ir[4] == 127 and ir[5] == 4, f"FC04 IR0..7 = {ir}")

        # The µs clock: SysTick-based, must advance like wall time (QEMU without icount runs its
        # virtual clock in step with the host's).
        u0, w0 = u48(port.read_input(IR_UPTIME, 3)), time.monotonic()
        time.sleep(0.5)
        u1, w1 = u48(port.read_input(IR_UPTIME, 3)), time.monotonic()
        rate = (u1 - u0) / ((w1 - w0) * 1e6)
        print(f"     uptime advanced {u1 - u0} us in {(w1 - w0) * 1e6:.0f} us wall (ratio {rate:.3f})")
        if not a.icount:
            check(0.8 < rate < 1.2, "device clock runs at wall-clock rate")
        # Monotonic and fine-grained: many reads in a row never go backwards.
        last = 0
        for _ in range(50):
            u = u48(port.read_input(IR_UPTIME, 3))
            if u < last:
                check(False, f"uptime monotonic ({u} < {last})")
            last = u
        check(last % 1000 != 0 or u1 % 1000 != 0, "µs resolution (not only whole ms)")

        # Device-master sequence; timestamps come back through the FIFO window.
        steps = step(1, 5, 1000, 0xFFFF, 10000, 20000, 100, 1, 0, 0b0001) + \
            step(2, 2, 2000, 9000, 250000, 5000, 0, 2, 1, 0b0011)
        port.write_registers(STEP_TABLE, steps)
        port.write_register(HR_SEQ_LEN, 2)
        resp = port.write_register(HR_COMMAND, CMD_START)
        check(resp[0] == 0x06, f"START accepted ({resp.hex(' ')})")
        time.sleep(0.6)
        check(port.read_input(IR_STATE, 1)[0] == 3, "sequence DONE")
        n = port.read_input(IR_EVT_COUNT, 1)[0]
        w = port.read_input(IR_EVT_WINDOW, 6 * n)
        evs = [(u48(w[6 * i + 3:6 * i + 6]), EVT.get(w[6 * i + 1] & 0xFF), w[6 * i + 1] >> 8) for i in range(n)]
        t0 = evs[0][0]
        rel = [(t - t0, k, arg) for t, k, arg in evs]
        print("     events (t - t0):", rel)
        sched = [0, 0, 10000, 30000, 30000, 30000, 280000, 285000, 295000, 295000]
        lat = [r[0] - s for r, s in zip(rel, sched)]
        print(f"     lateness vs schedule (us): {lat}")
        check(len(rel) == 10 and all(0 <= x <= 200 for x in lat), "events on schedule within 200 us")

        if a.mbpoll and shutil.which("mbpoll"):
            port.close()
            for args in (["-u"], ["-t", "3", "-r", "1", "-c", "8", "-1"]):
                out = subprocess.run(["mbpoll", "-m", "rtu", "-a", "1", "-b", "115200", "-P", "none", *args, pts],
                                     capture_output=True, text=True, timeout=10)
                ok = out.returncode == 0 and ("target=stm32f405" in out.stdout or "[1]: \t17491" in out.stdout)
                check(ok, "mbpoll " + " ".join(args))
    finally:
        os.close(keeper)
        p.terminate()
        p.wait(5)
    print("qemu_check: all ok")


if __name__ == "__main__":
    main()
