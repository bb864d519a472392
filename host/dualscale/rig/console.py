"""`dualscale console`: an interactive (or scripted, `-c "a; b"`) serial console for the rig.

The console turns the host watchdog on (PROTOCOL.md §5) and keeps it fed from a background
thread while the user is idle at the prompt, and says so: if the console dies (killed, cable
pulled), every light goes off within the watchdog period. `watchdog 0` turns it off.
"""
from __future__ import annotations

import cmd
import json
import threading
import time
from pathlib import Path

from dualscale.errors import FormatError, InputError

from ..protocol import regmap as rm
from .client import DEFAULT_WATCHDOG_MS, RigClient, RigError
from .sequence import CapturePlan, Step, schedule

SOURCES = {"led": rm.Source.LED, "back": rm.Source.BACKLIGHT, "diffuse": rm.Source.DIFFUSE}
POL_NAMES = {"p0": rm.POL_P0_CDEG, "p90": rm.POL_P90_CDEG}


def load_steps(path: Path) -> list[Step]:
    """A JSON list of step objects: {"source": "LED", "index": 3, "intensity": ..., ...}."""
    try:
        raw = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"no such sequence file: {path}") from None
    except OSError as e:
        raise InputError(f"cannot read sequence file {path}: {e.strerror}") from None
    except json.JSONDecodeError as e:
        raise FormatError(f"{path} is not valid JSON: {e}") from None
    if not isinstance(raw, list):
        raise FormatError(f"{path}: expected a JSON list of steps")
    steps = []
    for i, d in enumerate(raw):
        try:
            d = dict(d)
            d["source"] = rm.Source[str(d["source"]).upper()]
            steps.append(Step(**d))
        except (KeyError, TypeError, ValueError) as e:
            raise FormatError(f"{path}: step {i} is malformed ({e})") from None
    return steps


class Console(cmd.Cmd):
    intro = "dualscale console. Type help or ? to list commands."
    prompt = "rig> "

    def __init__(self, client: RigClient, out=None, watchdog_ms: int = DEFAULT_WATCHDOG_MS):
        super().__init__(stdout=out)
        self.rig = client
        self.failed = False
        self.watchdog_ms = watchdog_ms  # what `begin` sets; 0 leaves the watchdog off
        self._feeder: threading.Thread | None = None
        self._stop = threading.Event()
        self._say_lock = threading.Lock()

    def say(self, text: str) -> None:
        with self._say_lock:
            self.stdout.write(text + "\n")
            self.stdout.flush()

    # -- the host watchdog
    def begin(self) -> None:
        """Turn the host watchdog on (unless the device's own is on and shorter) and start
        feeding it while the user is idle. Idempotent."""
        if self._feeder is not None:
            return
        dev = self.rig.watchdog_ms()
        if self.watchdog_ms and not 0 < dev <= self.watchdog_ms:
            self.rig.set_watchdog(self.watchdog_ms)
            dev = self.watchdog_ms
        self.watchdog_ms = dev
        self._announce()
        self._stop.clear()
        self._feeder = threading.Thread(target=self._feed, name="watchdog-feeder", daemon=True)
        self._feeder.start()

    def _announce(self) -> None:
        if self.watchdog_ms:
            self.say(f"host watchdog: {self.watchdog_ms} ms. This console keeps it fed while you are idle; "
                     f"if the console stops, every light goes off {self.watchdog_ms} ms later "
                     f"('watchdog 0' turns it off).")
        else:
            self.say("host watchdog: off. Lights stay as they are if this console stops "
                     "('watchdog MS' turns it on).")

    def _feed(self) -> None:
        """Keep-alives: a one-register read whenever the line has been quiet for a quarter of
        the period (any valid frame feeds the watchdog)."""
        failing = False
        while not self._stop.is_set():
            period = self.watchdog_ms / 4e3 if self.watchdog_ms else 0.5
            if self.watchdog_ms and time.monotonic() - self.rig.last_reply >= period:
                try:
                    self.rig.keep_alive()
                    if failing:
                        self.say("watchdog keep-alive: the rig answers again")
                    failing = False
                except RigError as e:
                    if not failing:
                        self.say(f"watchdog keep-alive failed ({e}); the rig will switch its lights off")
                    failing = True
            self._stop.wait(max(0.01, period / 2))

    def end(self) -> None:
        """Stop feeding the watchdog (the lights go off one period later, if any is on)."""
        self._stop.set()
        if self._feeder is not None:
            self._feeder.join(2)
            self._feeder = None

    def preloop(self) -> None:
        self.begin()

    def postloop(self) -> None:
        self.end()

    def onecmd(self, line: str) -> bool:
        try:
            return super().onecmd(line)
        except (RigError, ValueError, KeyError, IndexError) as e:
            self.failed = True
            self.say(f"error: {e}")
            return False

    def default(self, line: str) -> None:
        self.failed = True
        self.say(f"error: unknown command {line.split()[0]!r} (try help)")

    def emptyline(self) -> None:
        pass

    # -- identity and state
    def do_id(self, arg: str) -> None:
        """id: the device's identity (FC 11 and 2B/0E)."""
        sid, running, text = self.rig.report_server_id()
        self.say(f"server {sid} run={'on' if running else 'off'}: {text}")
        for k, v in self.rig.device_identification().items():
            self.say(f"  object 0x{k:02X}: {v}")

    def do_status(self, arg: str) -> None:
        """status: sequencer state, errors, counters."""
        st = self.rig.status()
        for k, v in vars(st).items():
            self.say(f"{k:16s} {v.name if hasattr(v, 'name') else v}")

    # -- lights and polarizer
    def do_lights(self, arg: str) -> None:
        """lights: list the lights that are on."""
        on = self.rig.lights_on()
        self.say(", ".join(f"{s.name.lower()} {i}" for s, i in on) if on else "all lights off")

    def _light(self, kind: str, arg: str) -> None:
        a = arg.split()
        idx, state = (0, a[0]) if kind == "diffuse" else (int(a[0]), a[1])
        if state not in ("on", "off"):
            raise ValueError("say on or off")
        self.rig.set_light(SOURCES[kind], idx, state == "on")

    def do_led(self, arg: str) -> None:
        """led N on|off: switch directional LED N (0..126) at the manual intensity."""
        self._light("led", arg)

    def do_back(self, arg: str) -> None:
        """back N on|off: switch back light N."""
        self._light("back", arg)

    def do_diffuse(self, arg: str) -> None:
        """diffuse on|off: switch the diffuse group."""
        self._light("diffuse", arg)

    def do_intensity(self, arg: str) -> None:
        """intensity V: manual intensity, 0..65535."""
        self.rig.set_intensity(int(arg))

    def do_pol(self, arg: str) -> None:
        """pol p0|p90|CDEG: turn the analyzer (centidegrees)."""
        a = arg.strip().lower()
        self.rig.set_polarizer(POL_NAMES[a] if a in POL_NAMES else int(a))

    def do_alloff(self, arg: str) -> None:
        """alloff: every light off."""
        self.rig.all_off()

    def do_watchdog(self, arg: str) -> None:
        """watchdog [MS]: show, or set, the host watchdog timeout (0 disables); the console
        feeds it while you are idle."""
        if arg.strip():
            self.rig.set_watchdog(int(arg))
            self.watchdog_ms = int(arg)
        else:
            self.watchdog_ms = self.rig.watchdog_ms()
        self._announce()

    # -- sequences
    def do_upload(self, arg: str) -> None:
        """upload demo | upload FILE.json: upload the default micro-capture plan or a step list."""
        a = arg.strip()
        steps = CapturePlan().build(self.rig.status().polarizer_cdeg) if a in ("", "demo") \
            else load_steps(Path(a))
        dt = self.rig.upload(steps)
        dur = schedule(steps)[-1].end
        self.say(f"uploaded {len(steps)} steps in {dt * 1e3:.1f} ms, scheduled {dur / 1e6:.3f} s")

    def do_start(self, arg: str) -> None:
        """start [camera]: start the uploaded sequence (device-master unless 'camera')."""
        mode = rm.TriggerMode.CAMERA_MASTER if arg.strip() == "camera" else rm.TriggerMode.DEVICE_MASTER
        self.rig.start(mode)

    def do_run(self, arg: str) -> None:
        """run: start the uploaded sequence and follow it to the end (under the host watchdog)."""
        res = self.rig.run(on_event=lambda e: None, watchdog_ms=self.watchdog_ms or DEFAULT_WATCHDOG_MS)
        self.say(f"{res.state.name}: {len(res.events)} events in {res.wall_s:.2f} s"
                 + (f", error {res.error.name}" if res.error else ""))

    def do_abort(self, arg: str) -> None:
        """abort: stop the running sequence, all lights off."""
        self.rig.abort()

    def do_clear(self, arg: str) -> None:
        """clear: clear the error and leave FAULT."""
        self.rig.clear_error()

    def do_events(self, arg: str) -> None:
        """events: print (and acknowledge) the pending events."""
        evs = self.rig.poll_events()
        for e in evs:
            self.say(str(e))
        if not evs:
            self.say("no pending events")

    def do_quit(self, arg: str) -> bool:
        """quit: leave the console."""
        return True

    do_exit = do_quit
    do_EOF = do_quit


def run_script(console: Console, script: str) -> int:
    """Run `;`-separated commands (with the watchdog fed, see `Console.begin`); exit status 1
    if any failed."""
    console.begin()
    try:
        for line in script.split(";"):
            line = line.strip()
            if line:
                console.say(f"rig> {line}")
                if console.onecmd(line):
                    break
    finally:
        console.end()
    return 1 if console.failed else 0

