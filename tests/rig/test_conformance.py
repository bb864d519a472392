"""Protocol conformance with pymodbus, against the POSIX simulator and the ARM image in QEMU."""
from __future__ import annotations

import time

import pytest

from dualscale.protocol import regmap as rm
from dualscale.rig.client import DeviceException, SequenceRejected
from dualscale.rig.sequence import Step

LED = rm.Source.LED


def lit(index=0, **kw) -> Step:
    d = dict(source=LED, index=index, intensity=1000, settle_us=1000, exposure_us=2000,
             pulse_us=100, brackets=1, triggers=1)
    d.update(kw)
    return Step(**d)


def test_identity_and_version(rig, sim):
    ident = rig.identity
    assert ident.protocol == rm.PROTOCOL_VERSION and ident.firmware == rm.FIRMWARE_VERSION
    assert "dualscale" in ident.text and "fw=0.1.0" in ident.text \
        and "proto={}.{}".format(*rm.PROTOCOL_VERSION) in ident.text
    assert ident.target == ("stm32f405" if sim.target == "qemu" else "posix")
    assert ident.server_id == 1 and ident.running
    objs = rig.device_identification(read_code=2)
    assert objs[0] == "dualscale" and objs[2] == "0.1.0"
    assert objs[5] == ident.target


def test_input_block_describes_the_rig(rig):
    w = rig.read_input(rm.IR.MAGIC, 8)
    assert w == [rm.MAGIC, (rm.PROTOCOL_VERSION[0] << 8) | rm.PROTOCOL_VERSION[1], 0x0001, 0, rm.N_LEDS, rm.N_BACKLIGHTS, rm.MAX_STEPS, rm.FIFO_DEPTH]


def test_holding_defaults_match_the_register_map(rig, sim):
    regs = {r.name: r for r in rm.REGISTERS if r.space == "holding"}
    w = rig.read_holding(0, rm.HR_COUNT)
    for name, r in regs.items():
        if r.default is None:
            continue
        got = w[r.addr] if r.words == 1 else (w[r.addr] << 16) | w[r.addr + 1]
        want = sim.frame_timeout_us if name == "FRAME_TIMEOUT_US" and sim.frame_timeout_us else r.default
        assert got == want, name
    assert w[rm.HR.COMMAND] == 0  # write-only reads 0


def test_write_and_read_back_holding(rig):
    rig.write_register(rm.HR.MANUAL_INTENSITY, 1234)
    rig.write_registers(rm.HR.FRAME_GAP_US, [0x0001, 0x0002])
    assert rig.read_holding(rm.HR.MANUAL_INTENSITY, 1) == [1234]
    assert rig.read_holding(rm.HR.FRAME_GAP_US, 2) == [1, 2]
    rig.write_registers(rm.HR.FRAME_GAP_US, [0, 0])


def test_fc17_writes_then_reads(rig):
    rr = rig._call("fc17", rig._mb.readwrite_registers, read_address=rm.HR.MANUAL_INTENSITY,
                   read_count=1, write_address=rm.HR.MANUAL_INTENSITY, values=[777])
    assert rr.registers == [777]


def test_out_of_range_write_is_refused_atomically(rig):
    rig.write_register(rm.HR.MANUAL_INTENSITY, 5)
    with pytest.raises(DeviceException) as e:  # MANUAL_INTENSITY fine, LED_MAX_ON_MS = 0 is not
        rig.write_registers(rm.HR.MANUAL_INTENSITY, [9, 0])
    assert e.value.code == 3
    assert rig.read_holding(rm.HR.MANUAL_INTENSITY, 1) == [5]


@pytest.mark.parametrize("space,addr", [("holding", rm.HR_COUNT), ("input", rm.IR_COUNT),
                                        ("input", rm.IR.EVT_WINDOW + 120)])
def test_unmapped_addresses_answer_02(rig, space, addr):
    with pytest.raises(DeviceException) as e:
        if space == "input":
            rig.read_input(addr, 1)
        else:
            rig.read_holding(addr, 1)
    assert e.value.code == 2


def test_device_identification_stream_restarts_at_object_0(rig, sim):
    """MB application protocol v1.1b3 section 6.21, through pymodbus: stream access (read codes
    1..3) from an object id that does not exist answers from object 0; individual access (4) 02."""
    for code, ids in ((1, [0, 1, 2]), (2, list(range(7))), (3, list(range(7)))):
        rr = rig._mb.read_device_information(read_code=code, object_id=0x99)
        assert not rr.isError() and sorted(rr.information) == ids, code
        assert rr.information[0] == b"dualscale" and rr.more_follows == 0
    rr = rig._mb.read_device_information(read_code=2, object_id=5)
    assert sorted(rr.information) == [5, 6]
    rr = rig._mb.read_device_information(read_code=4, object_id=0x99)
    assert rr.isError() and rr.exception_code == 2


def test_uart_error_counters_and_line_format_registers(rig):
    assert rig.read_input(rm.IR.UART_PARITY_ERRORS, 4) == [0, 0, 0, 0]  # a pty has no line noise
    assert rig.read_holding(rm.HR.SERIAL_PARITY, 2) == [rm.Parity.EVEN, 1]
    with pytest.raises(DeviceException) as e:  # 8N1: not a Modbus serial-line format
        rig.write_register(rm.HR.SERIAL_PARITY, rm.Parity.NONE)
    assert e.value.code == 3


def test_value_is_checked_before_the_address(raw):
    """FC 05 with the output value 0x1234 to an unmapped coil: 03, not 02 (state diagram order
    01 -> 03 -> 02 -> 04); the same with a quantity of 0 at an unmapped address for FC 01/03/04."""
    assert raw.request(bytes([1, 0x05, 0x00, 200, 0x12, 0x34]))[1:3] == bytes([0x85, 0x03])
    for fc in (0x01, 0x03, 0x04):
        assert raw.request(bytes([1, fc, 0xFF, 0x00, 0x00, 0x00]))[1:3] == bytes([fc | 0x80, 0x03])


def test_illegal_function(rig):
    with pytest.raises(DeviceException) as e:
        rig._call("fc02", rig._mb.read_discrete_inputs, 0, count=1)
    assert e.value.code == 1


def test_coils_switch_lights(rig):
    rig.set_intensity(1000)
    rig.set_light(LED, 3, True)
    rig.set_light(rm.Source.DIFFUSE, 0, True)
    assert rig.lights_on() == [(LED, 3), (rm.Source.DIFFUSE, 0)]
    rig._call("fc0f", rig._mb.write_coils, rm.Coil.LED + 10, [True, False, True])
    assert (LED, 10) in rig.lights_on() and (LED, 12) in rig.lights_on()
    rig.all_off()
    assert rig.lights_on() == []


def test_servo_window(rig):
    rig.write_register(rm.HR.SERVO_MAX_CDEG, 9000)
    try:
        rig.set_polarizer(9000)
        with pytest.raises(DeviceException) as e:
            rig.set_polarizer(12000)
        assert e.value.code == 3
        with pytest.raises(DeviceException):
            rig.write_register(rm.HR.SERVO_MIN_CDEG, 9500)  # min > max
    finally:
        rig.write_register(rm.HR.SERVO_MAX_CDEG, 18000)
    rig.set_polarizer(0)
    assert rig.status().polarizer_cdeg == 0


def test_short_sequence_runs_to_done(rig):
    steps = [lit(i, polarizer_cdeg=0 if i == 0 else None) for i in range(6)]
    res = rig.run(steps, timeout_s=20)
    assert res.state == rm.State.DONE and res.error == rm.Error.NONE
    kinds = [e.kind for e in res.events]
    assert kinds[0] == rm.Event.SEQ_START and kinds[-1] == rm.Event.SEQ_DONE
    assert [e.step for e in res.events if e.kind == rm.Event.STEP_START] == list(range(6))
    assert rig.lights_on() == []


def test_busy_while_running_and_abort(rig):
    steps = [lit(i % 127, exposure_us=200_000) for i in range(20)]
    rig.upload(steps)
    rig.sync_events()
    rig.start()
    try:
        with pytest.raises(DeviceException) as e:
            rig.set_light(LED, 0, True)
        assert e.value.code == 6
        with pytest.raises(DeviceException) as e:
            rig.write_registers(rm.STEP_TABLE_ADDR, steps[0].to_words())
        assert e.value.code == 6
    finally:
        rig.abort()
    st = rig.status()
    assert st.state == rm.State.ABORTED and rig.lights_on() == []
    kinds = [e.kind for e in rig.poll_events()]
    assert rm.Event.SEQ_ABORT in kinds


UNSAFE = [
    ("bad source index", [lit(200)], rm.Error.BAD_SOURCE, 0),
    ("unknown source kind", [Step(rm.Source.DIFFUSE, 3, 100, None, 0, 100, 0, 1, 0, 1)], rm.Error.BAD_SOURCE, 0),
    ("zero intensity with a light", [lit(0), lit(1, intensity=0)], rm.Error.BAD_INTENSITY, 1),
    ("polarizer out of range", [lit(0, polarizer_cdeg=18001)], rm.Error.POLARIZER_RANGE, 0),
    ("zero exposure", [lit(0, exposure_us=0)], rm.Error.EXPOSURE_RANGE, 0),
    ("bracket too long", [lit(0, exposure_us=40_000_000, brackets=2, ev_step=1)], rm.Error.EXPOSURE_RANGE, 0),
    ("settle too long", [lit(0, settle_us=60_000_001)], rm.Error.SETTLE_RANGE, 0),
    ("pulse longer than exposure", [lit(0, pulse_us=3000)], rm.Error.PULSE_RANGE, 0),
    ("no brackets", [lit(0, brackets=0)], rm.Error.BRACKETS_RANGE, 0),
    ("too many EV stops", [lit(0, brackets=2, ev_step=5)], rm.Error.BRACKETS_RANGE, 0),
    ("trigger bit that does not exist", [lit(0, triggers=0x10)], rm.Error.TRIGGER_MASK, 0),
    ("no trigger on a lit step", [lit(0), lit(1, triggers=0)], rm.Error.TRIGGER_MASK, 1),
    ("on-time over the limit", [lit(0, exposure_us=11_000_000)], rm.Error.LED_ON_TIME, 0),
    ("servo cannot make it", [lit(0, polarizer_cdeg=0, settle_us=300_000), lit(1, polarizer_cdeg=9000, settle_us=1000)],
     rm.Error.SERVO_SETTLE, 1),
    ("gate-mode brackets with no time low", [lit(0, pulse_us=0, brackets=2)], rm.Error.TRIGGER_GAP, 0),
    ("pulse leaves the line low too briefly", [lit(0, pulse_us=1995, brackets=2)], rm.Error.TRIGGER_GAP, 0),
    ("next step re-triggers too soon", [lit(0, pulse_us=0), lit(1, settle_us=5, pulse_us=0)], rm.Error.TRIGGER_GAP, 1),
    ("duty cycle over budget", [lit(0, exposure_us=4_000_000)] * 4, rm.Error.LED_DUTY, None),
]


@pytest.mark.parametrize("name,steps,error,step", UNSAFE, ids=[u[0] for u in UNSAFE])
def test_unsafe_sequences_are_refused(rig, name, steps, error, step):
    rig.upload(steps)
    with pytest.raises(SequenceRejected) as e:
        rig.start()
    assert e.value.error == error
    if step is not None:
        assert e.value.step == step
    assert rig.status().state != rm.State.RUNNING and rig.lights_on() == []


def test_empty_sequence_is_refused(rig):
    rig.write_register(rm.HR.SEQ_LEN, 0)
    with pytest.raises(SequenceRejected) as e:
        rig.start()
    assert e.value.error == rm.Error.SEQ_EMPTY


def test_manual_light_on_time_limit(rig):
    rig.write_register(rm.HR.LED_MAX_ON_MS, 150)
    rig.sync_events()
    rig.set_light(LED, 5, True)
    time.sleep(0.6)
    assert rig.lights_on() == []
    evs = rig.poll_events()
    assert any(e.kind == rm.Event.LED_LIMIT for e in evs)
    assert rig.status().error == rm.Error.LED_LIMIT


def test_watchdog_switches_lights_off_when_the_host_goes_silent(rig):
    before = rig.status().watchdog_trips
    rig.set_light(LED, 7, True)
    rig.set_watchdog(200)
    time.sleep(0.7)  # the host says nothing
    st = rig.status()
    assert st.state == rm.State.FAULT and st.error == rm.Error.WATCHDOG
    assert st.watchdog_trips == before + 1
    assert rig.lights_on() == []


def test_host_disappears_mid_sequence(rig):
    rig.upload([lit(i, exposure_us=100_000) for i in range(30)])
    rig.set_watchdog(250)
    rig.sync_events()
    rig.start()
    time.sleep(1.0)  # vanish for four watchdog periods
    st = rig.status()
    assert st.state == rm.State.FAULT and st.error == rm.Error.WATCHDOG
    assert rig.lights_on() == []
    kinds = [e.kind for e in rig.poll_events()]
    assert rm.Event.SEQ_ABORT in kinds and rm.Event.WATCHDOG in kinds


def test_run_ends_even_when_the_fifo_overflows_and_drops_seq_done(rig, sim):
    if sim.target != "posix":
        pytest.skip("needs events faster than any host can read them: 700 in a few ms")
    steps = [lit(i % 127, settle_us=0, exposure_us=20, pulse_us=10) for i in range(230)]
    res = rig.run(steps, timeout_s=30)
    assert res.state == rm.State.DONE and res.dropped > 0
    assert len(res.events) + res.dropped == 2 + 3 * len(steps)  # SEQ_START/DONE + 3 per step
