"""Smoke test of the POSIX simulator (build/posix/dualscale-sim), standard library only.

Starts the simulator, talks Modbus over its pty (FC 11, FC 04), runs a two-step device-master
sequence while following the hardware side channel, and checks that every event lands exactly
on its schedule (virtual-time speeds) or within a tolerance (speed 1). Then a camera-master run
driven by edges sent on the side channel, and finally SIGTERM: exit 0, lights off, link gone.

    python3 tools/sim_check.py [--speed S] [--sim PATH]
"""
import argparse
import json
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import rtu  # noqa: E402

HR_COMMAND, HR_TRIGGER_MODE, HR_SEQ_LEN, HR_EVT_ACK, HR_CAMERA_TIMEOUT_MS = 0, 1, 2, 3, 11
STEP_TABLE = 0x1000
CMD_START = 1
EVT = {1: "SEQ_START", 2: "STEP_START", 3: "TRIGGER", 4: "STEP_END", 5: "SEQ_DONE",
       6: "SEQ_ABORT", 7: "FAULT", 8: "CAMERA_EDGE", 10: "POLARIZER"}


def step(kind, index, intensity, pol, settle, exposure, pulse, count, ev, triggers):
    return [kind << 8 | index, intensity, pol, settle >> 16, settle & 0xFFFF,
            exposure >> 16, exposure & 0xFFFF, pulse, ev << 8 | count, triggers]


class Side:
    def __init__(self, path):
        self.s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.s.connect(path)
        self.buf = b""
        self.lines = []

    def send(self, obj):
        self.s.sendall((json.dumps(obj) + "\n").encode())

    def read_until(self, pred, timeout=10.0):
        """Collect JSON lines until pred(obj) is true; returns everything collected."""
        deadline = time.monotonic() + timeout
        out = []
        while time.monotonic() < deadline:
            while b"\n" in self.buf:
                line, self.buf = self.buf.split(b"\n", 1)
                obj = json.loads(line)
                out.append(obj)
                if pred(obj):
                    return out
            r, _, _ = select.select([self.s], [], [], 0.1)
            if r:
                chunk = self.s.recv(65536)
                if not chunk:
                    break
                self.buf += chunk
        raise TimeoutError(f"side channel: condition not met; got {out[-5:]}")


def check(cond, what):
    print(("ok   " if cond else "FAIL ") + what)
    if not cond:
        raise SystemExit(1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--speed", default="10")
    ap.add_argument("--sim", default=os.path.join(os.path.dirname(__file__), "..", "build", "posix", "dualscale-sim"))
    a = ap.parse_args()
    speed = float(a.speed)
    tmp = tempfile.mkdtemp(prefix="ds-simcheck-")
    link, sock = os.path.join(tmp, "tty"), os.path.join(tmp, "hw.sock")
    p = subprocess.Popen([a.sim, "--speed", a.speed, "--link", link, "--hw-socket", sock],
                         stdout=subprocess.PIPE, text=True)
    try:
        pts = p.stdout.readline().strip()
        check(pts.startswith("/dev/"), f"first stdout line is the pty: {pts}")
        check(os.path.realpath(link) == pts, "--link points at it")
        side = Side(sock)
        hello = side.read_until(lambda o: o.get("ev") == "hello")
        check(hello[-1]["target"] == "posix", "side channel hello")

        port = rtu.Port(link)
        sid, run, text = port.report_server_id()
        check(sid == 1 and run == 0xFF and "target=posix" in text, f"FC11: {text}")
        ir = port.read_input(0, 8)
        check(ir[0] == 0x4453 and ir[4] == 127, f"FC04 IR0..7 = {ir}")

        # -- device-master: two steps --------------------------------------------------------
        steps = step(1, 5, 1000, 0xFFFF, 10000, 20000, 100, 1, 0, 0b0001) + \
                step(2, 2, 2000, 9000, 250000, 5000, 0, 2, 1, 0b0011)
        port.write_registers(STEP_TABLE, steps)
        port.write_register(HR_SEQ_LEN, 2)
        t_wall = time.monotonic()
        resp = port.write_register(HR_COMMAND, CMD_START)
        check(resp[0] == 0x06, f"START accepted ({resp.hex(' ')})")
        got = side.read_until(lambda o: o.get("ev") == "event" and o["kind"] == 5)
        wall = time.monotonic() - t_wall
        evs = [(o["t_us"], EVT.get(o["kind"], o["kind"]), o["arg"], o["step"]) for o in got if o["ev"] == "event"]
        t0 = evs[0][0]
        rel = [(t - t0, k, arg, st) for t, k, arg, st in evs]
        expect = [(0, "SEQ_START", 0, 0xFFFF), (0, "STEP_START", 0, 0), (10000, "TRIGGER", 0, 0),
                  (30000, "STEP_END", 0, 0), (30000, "POLARIZER", 0, 1), (30000, "STEP_START", 0, 1),
                  (280000, "TRIGGER", 0, 1), (285000, "TRIGGER", 1, 1), (295000, "STEP_END", 0, 1),
                  (295000, "SEQ_DONE", 0, 0xFFFF)]
        print("     events (t - t0):", rel)
        tol = 0 if speed != 1.0 else 3000
        same = len(rel) == len(expect) and all(
            abs(r[0] - e[0]) <= tol and r[1:] == e[1:] for r, e in zip(rel, expect))
        check(same, f"device-master events on schedule (tolerance {tol} us)")
        trig = [(o["t_us"] - t0, o["mask"]) for o in got if o["ev"] == "triggers" and o["t_us"] >= t0]
        print("     trigger edges:", trig)
        check([m for _, m in trig] == [1, 0, 3, 0, 3, 0], "trigger edges")
        if speed != 1.0:
            check(trig == [(10000, 1), (10100, 0), (280000, 3), (285000, 0), (285000, 3), (295000, 0)],
                  "trigger edges exactly on schedule")
        lights = [(o["t_us"] - t0, o["kind"], o["index"], o["intensity"]) for o in got
                  if o["ev"] == "light" and o["t_us"] >= t0]
        print("     lights:", lights)
        if speed != 1.0:
            check(lights == [(0, 1, 5, 1000), (30000, 1, 5, 0), (30000, 2, 2, 2000), (295000, 2, 2, 0)],
                  "light changes exactly on schedule")
        print(f"     sequence of 295 ms device time took {wall * 1000:.0f} ms wall at speed {a.speed}")
        last_seq = [o for o in got if o["ev"] == "event"][-1]["seq"]
        port.write_register(HR_EVT_ACK, last_seq)
        check(port.read_input(17, 1)[0] == 0, "EVT_ACK freed the events")

        # -- camera-master: edges from the side channel --------------------------------------
        if speed != 0.0:  # at speed 0 the camera timeout is the next deadline: jumped at once
            steps = step(1, 7, 500, 0xFFFF, 0, 1000, 0, 1, 0, 0) + step(1, 8, 600, 0xFFFF, 0, 1000, 0, 1, 0, 0)
            port.write_registers(STEP_TABLE, steps)
            port.write_register(HR_TRIGGER_MODE, 1)
            port.write_register(HR_CAMERA_TIMEOUT_MS, 60000)  # 60 s device time: slack at speed 100
            port.write_register(HR_COMMAND, CMD_START)
            for _ in range(3):
                side.send({"ev": "edge", "camera": 0})
                side.read_until(lambda o: o.get("ev") == "event" and o["kind"] in (2, 5))
            check(port.read_input(8, 1)[0] == 3, "camera-master sequence DONE after 3 edges")
            port.write_register(HR_TRIGGER_MODE, 0)

        # -- a manual light, then SIGTERM switches it off --------------------------------------
        port.write_coil(3, True)
        side.read_until(lambda o: o.get("ev") == "light" and o["index"] == 3 and o["intensity"] > 0)
        port.close()
        p.send_signal(signal.SIGTERM)
        rc = p.wait(5)
        check(rc == 0, "SIGTERM: exit 0")
        tail = side.read_until(lambda o: o.get("ev") == "light" and o["index"] == 3 and o["intensity"] == 0, 2)
        check(bool(tail), "lights off on exit")
        check(not os.path.lexists(link) and not os.path.exists(sock), "link and socket removed")
    finally:
        if p.poll() is None:
            p.kill()
    print("sim_check: all ok")


if __name__ == "__main__":
    main()
