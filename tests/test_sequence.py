"""Step-table encoding, the device-master schedule and capture plans (no device needed)."""
import pytest
from hypothesis import given
from hypothesis import strategies as st

from dualscale.protocol import regmap as rm
from dualscale.protocol.crc import crc16, rtu_frame
from dualscale.rig.sequence import CapturePlan, Step, encode, schedule, seq_crc, servo_travel_us

steps_st = st.builds(
    Step,
    source=st.sampled_from(list(rm.Source)), index=st.integers(0, 255),
    intensity=st.integers(0, 65535), polarizer_cdeg=st.one_of(st.none(), st.integers(0, 18000)),
    settle_us=st.integers(0, 2**32 - 1), exposure_us=st.integers(0, 2**32 - 1),
    pulse_us=st.integers(0, 65535), brackets=st.integers(0, 255), ev_step=st.integers(0, 255),
    triggers=st.integers(0, 65535))


@given(steps_st)
def test_step_words_round_trip(s):
    w = s.to_words()
    assert len(w) == rm.STEP_WORDS and all(0 <= x <= 0xFFFF for x in w)
    assert Step.from_words(w) == s


def test_crc_matches_the_modbus_reference():
    # Modbus application protocol example: 01 03 00 00 00 01 -> CRC 84 0A
    assert rtu_frame(bytes.fromhex("010300000001")).hex() == "010300000001840a"
    assert crc16(b"123456789") == 0x4B37  # CRC-16/MODBUS check value


def test_schedule_chains_brackets_and_gaps():
    a = Step(rm.Source.LED, 0, 100, None, settle_us=10, exposure_us=5, brackets=3, ev_step=1, triggers=1)
    b = Step(rm.Source.OFF, settle_us=7, exposure_us=1, brackets=1, triggers=0)
    s = schedule([a, b], frame_gap_us=2)
    assert s[0].start == 0 and s[0].brackets == (10, 17, 29) and s[0].end == 29 + 20 + 2
    assert s[1].start == s[0].end and s[1].brackets == (s[0].end + 7,) and s[1].end == s[0].end + 10


def test_default_plan_covers_every_led_in_both_modes():
    steps = CapturePlan().build(start_cdeg=0)
    leds = [(s.index) for s in steps if s.source == rm.Source.LED]
    assert sorted(leds) == sorted(list(range(127)) * 2)
    assert sum(s.source == rm.Source.DIFFUSE for s in steps) == 2
    assert sum(s.source == rm.Source.BACKLIGHT for s in steps) == 2 * rm.N_BACKLIGHTS
    # the P90 switch gets a settle long enough for the servo, P0 needs none from 0
    pol = [s for s in steps if s.polarizer_cdeg is not None]
    assert [s.polarizer_cdeg for s in pol] == [rm.POL_P90_CDEG]
    assert pol[0].settle_us >= servo_travel_us(0, rm.POL_P90_CDEG)
    assert seq_crc(steps) == crc16(b"".join(w.to_bytes(2, "big") for w in encode(steps)))


def test_plan_rejects_bad_indices():
    with pytest.raises(ValueError, match="LED index 127"):
        CapturePlan(leds=[127]).build()
    with pytest.raises(ValueError, match="back-light"):
        CapturePlan(backlights=[9]).build()


def test_step_fields_follow_the_generated_offsets():
    """Each field lands at its rm.StepWord offset (u32 fields big-endian over two words), and
    'keep the analyzer' is rm.POL_KEEP."""
    from dualscale.rig.sequence import STEP_FIELDS

    s = Step(rm.Source.BACKLIGHT, 2, 40000, None, settle_us=0x12345678, exposure_us=0x0001_0002, pulse_us=7,
             brackets=3, ev_step=2, triggers=0b0101)
    w = s.to_words()
    assert set(STEP_FIELDS) == {k for k in vars(rm.StepWord) if k.isupper()}
    assert w[rm.StepWord.SOURCE] == (rm.Source.BACKLIGHT << 8) | 2
    assert w[rm.StepWord.POLARIZER] == rm.POL_KEEP
    assert w[rm.StepWord.SETTLE_US:rm.StepWord.SETTLE_US + 2] == [0x1234, 0x5678]
    assert w[rm.StepWord.EXPOSURE_US:rm.StepWord.EXPOSURE_US + 2] == [1, 2]
    assert w[rm.StepWord.BRACKETS] == (2 << 8) | 3 and w[rm.StepWord.TRIGGERS] == 0b0101
    assert sum(n for _, n in STEP_FIELDS.values()) == rm.STEP_WORDS


def test_plan_checks_brackets_ev_steps_and_triggers_against_the_map():
    from dualscale.errors import InputError
    from dualscale.rig.sequence import MICRO_TRIGGER

    assert CapturePlan().triggers == MICRO_TRIGGER == 1 << rm.TRIGGER_NAMES.index("micro")
    assert len(CapturePlan(brackets=rm.MAX_BRACKETS, ev_step=rm.MAX_EV_STEP).build()) > 0
    with pytest.raises(InputError, match=f"1..{rm.MAX_BRACKETS}"):
        CapturePlan(brackets=rm.MAX_BRACKETS + 1).build()
    with pytest.raises(InputError, match="brackets 0"):
        CapturePlan(brackets=0).build()
    with pytest.raises(InputError, match="ev_step"):
        CapturePlan(ev_step=rm.MAX_EV_STEP + 1).build()
    with pytest.raises(InputError, match="triggers"):
        CapturePlan(triggers=1 << rm.N_TRIGGERS).build()
