"""Capture plans, the journal, frame-event matching and the bracket decision (no rig needed)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dualscale.capture.camera import Frame
from dualscale.capture.journal import Journal
from dualscale.capture.plan import ANALYZERS_CDEG, Shot, make_plan, micro_plan, select_leds
from dualscale.capture.session import CaptureSession, ShotPlan, _light_mismatch, stable_spec
from dualscale.errors import FormatError, InputError
from dualscale.geometry.dome import ring_layout
from dualscale.protocol import regmap as rm
from dualscale.rig.events import Event
from dualscale.rig.sequence import Step


def test_light_selections():
    assert select_leds("ALL") == list(range(rm.N_LEDS))
    assert select_leds("mod4") == list(range(0, rm.N_LEDS, 4))
    rows = [r for r, _, _ in ring_layout()]
    assert select_leds("ROW0+2") == [i for i, r in enumerate(rows) if r in (0, 2)]
    for bad in ("MOD0", "ROW99", "sometimes"):
        with pytest.raises(InputError):
            select_leds(bad)


def test_light_file(tmp_path):
    f = tmp_path / "leds.txt"
    f.write_text("# grazing\n3, 5 7\n")
    assert select_leds(str(f)) == [3, 5, 7]
    f.write_text(f"3 {rm.N_LEDS}\n")
    with pytest.raises(InputError, match="leds.txt:1"):
        select_leds(str(f))
    f.write_text("3 3\n")
    with pytest.raises(InputError, match="repeat"):
        select_leds(str(f))


def test_micro_plan_is_the_synth_dataset_shots():
    p = micro_plan("MOD8")
    leds = list(range(0, rm.N_LEDS, 8))
    assert len(p.shots) == 2 * len(leds) + 2 and p.roles == ("micro",)
    assert p.shots[0] == Shot("led", 0, ANALYZERS_CDEG[0]) and p.shots[-1] == Shot("backlight", 0, ANALYZERS_CDEG[1])
    assert p.shots[len(leds)] == Shot("backlight", 0, ANALYZERS_CDEG[0])
    assert len({s.key for s in p.shots}) == len(p.shots)
    assert make_plan("mid").shots == (Shot("diffuse", None, None),)
    with pytest.raises(InputError, match="unknown plan"):
        make_plan("white-paper")


def test_journal_survives_a_torn_last_line(tmp_path):
    j = Journal(tmp_path / "journal.jsonl")
    j.append("shot", key="a")
    with open(j.path, "ab") as f:
        f.write(b'{"kind": "shot", "key": "b"')  # killed inside the write
    j2 = Journal(j.path)
    assert [e["key"] for e in j2.of("shot")] == ["a"]
    j2.append("shot", key="c")
    assert [e["key"] for e in Journal(j.path).of("shot")] == ["a", "c"]
    lines = j.path.read_text().splitlines()
    assert json.loads(lines[-1])["key"] == "c"


def test_journal_damaged_in_the_middle_is_refused(tmp_path):
    p = tmp_path / "journal.jsonl"
    p.write_text('{"kind": "start"}\nnot json\n{"kind": "shot"}\n')
    with pytest.raises(FormatError, match="journal.jsonl:2"):
        Journal(p)


def test_stable_spec_drops_the_socket():
    assert stable_spec("sim:micro?material=twill&hw=/tmp/x/hw.sock&size=32") == "sim:micro?material=twill&size=32"
    assert stable_spec("uvc:0") == "uvc:0"


def _frame(t_us: int, lights=None, pol=None, index=0) -> Frame:
    meta = {"device_t_us": t_us}
    if lights is not None:
        meta["lights"] = lights
    if pol is not None:
        meta["polarizer_cdeg"] = pol
    return Frame(np.zeros((2, 2, 3), np.float32), index, t_us / 1e6, 0.001, meta)


def _events(steps, t0=1000):
    out, seq, t = [], 0, t0
    for k, s in enumerate(steps):
        out.append(Event(seq, rm.Event.STEP_START, 0, k, t))
        seq += 1
        for b in range(s.brackets):
            t += 100
            out.append(Event(seq, rm.Event.TRIGGER, b, k, t))
            seq += 1
        t += 1000
    return out


class _Bare(CaptureSession):
    def __init__(self):  # matching only: no rig, no cameras
        pass


def test_frames_match_their_trigger_events_by_device_time():
    steps = [Step(rm.Source.LED, 3, 100, 0, brackets=2, ev_step=1), Step(rm.Source.LED, 4, 100, None, brackets=2,
                                                                         ev_step=1)]
    ev = _events(steps)
    trig = [e for e in ev if e.kind == rm.Event.TRIGGER]
    lit = {0: [[1, 3, 100]], 1: [[1, 4, 100]]}
    frames = [_frame(e.ts_us, lit[e.step], 0 if e.step == 0 else None, i) for i, e in enumerate(trig)]
    ok, bad = _Bare()._match(steps, ev, frames[::-1])  # arrival order does not matter
    assert not bad and [f.metadata["device_t_us"] for f in ok[0]] == [trig[0].ts_us, trig[1].ts_us]
    # a dropped frame: only its step is taken again
    ok, bad = _Bare()._match(steps, ev, frames[:2] + frames[3:])
    assert set(ok) == {0} and bad == {1: "frame missing"}
    # a missing event (FIFO overflow): its frame is not kept
    ok, bad = _Bare()._match(steps, [e for e in ev if e is not trig[0]], frames)
    assert set(ok) == {1} and bad[0] == "trigger event missing"
    # the light seen is not the step's
    wrong = [_frame(f.metadata["device_t_us"], [[1, 9, 100]], None, f.index) if k == 2 else f for k, f in enumerate(frames)]
    ok, bad = _Bare()._match(steps, ev, wrong)
    assert set(ok) == {0} and bad[1].startswith("light state differs")


def test_frames_without_device_time_match_by_count_only():
    steps = [Step(rm.Source.LED, 3, 100, None, brackets=1)] * 3
    ev = _events(steps)
    frames = [Frame(np.zeros((2, 2), np.float32), i, float(i), 0.001, {}) for i in range(3)]
    ok, bad = _Bare()._match(steps, ev, frames)
    assert not bad and [ok[k][0].index for k in range(3)] == [0, 1, 2]
    ok, bad = _Bare()._match(steps, ev, frames[:2])  # which one is missing cannot be known: all again
    assert not ok and set(bad) == {0, 1, 2}


def test_light_mismatch_checks_the_analyser():
    s = Step(rm.Source.LED, 3, 100, 9000)
    assert _light_mismatch(s, [_frame(0, [[1, 3, 100]], 9000)]) is None
    assert "analyser" in _light_mismatch(s, [_frame(0, [[1, 3, 100]], 0)])
    assert "light state" in _light_mismatch(s, [_frame(0, [[1, 3, 100], [2, 0, 100]], 9000)])


def test_shot_plan_exposures_follow_the_firmware_rule():
    p = ShotPlan(1000, 3, 2)
    assert p.exposures_s() == [0.001, 0.004, 0.016]
    assert Step(rm.Source.LED, 0, 1, None, exposure_us=1000, brackets=3, ev_step=2).bracket_exposures() == [1000, 4000, 16000]
