"""The client never takes a late reply for the answer to a later request, and a retried START,
ABORT or CLEAR_ERROR first asks the status whether the lost attempt took effect (issue 13 §2)."""
from __future__ import annotations

import struct
import time

import pytest

from dualscale.protocol import regmap as rm
from dualscale.protocol.crc import rtu_frame
from dualscale.rig.client import DeviceException, LinkError, RigClient, reply_mismatch
from dualscale.rig.launcher import SimulatedRig
from dualscale.rig.sequence import Step

from .linkproxy import LinkProxy


@pytest.fixture(scope="module")
def sim():
    with SimulatedRig("posix") as s:
        yield s


@pytest.fixture
def link(sim):
    with LinkProxy(sim.port) as p:
        c = RigClient(p.port, timeout=0.2, min_timeout=0.05, retries=0)
        c.open()
        yield p, c
        c.retries = 3
        p.cut(False)
        p.release()
        c.abort()
        c.clear_error()
        c.all_off()
        c.set_watchdog(0)
        c.write_register(rm.HR.LED_MAX_ON_MS, rm.LED_MAX_ON_MS_DEFAULT)
        c.close()


def command_is(cmd: rm.Command):
    """A predicate on the host's bytes: FC 06 COMMAND = cmd."""
    want = rtu_frame(struct.pack(">BBHH", rm.DEFAULT_ADDRESS, 0x06, rm.HR.COMMAND, int(cmd)))
    return lambda data: data == want


def test_a_late_read_reply_is_not_the_answer_to_the_next_read(link):
    proxy, c = link
    proxy.hold_next_reply()
    with pytest.raises(LinkError):
        c.read_input(rm.IR.MAGIC, 1)  # its reply is held back ...
    # ... and arrives right after the next request: same FC, another register count
    assert c.read_input(rm.IR.N_LEDS, 2) == [rm.N_LEDS, rm.N_BACKLIGHTS]
    assert c.stats.stale == 1


def test_a_late_write_echo_is_not_the_answer_to_the_next_write(link):
    proxy, c = link
    proxy.hold_next_reply()
    with pytest.raises(LinkError):
        c.write_register(rm.HR.MANUAL_INTENSITY, 111)
    # the device refuses this one (LED_MAX_ON_MS >= 1): the echo of the earlier write must not
    # be taken for its acceptance
    with pytest.raises(DeviceException) as e:
        c.write_register(rm.HR.LED_MAX_ON_MS, 0)
    assert e.value.code == 0x03
    assert c.stats.stale == 1
    assert c.read_holding(rm.HR.MANUAL_INTENSITY, 1) == [111]


def test_a_late_reply_on_the_line_is_drained_before_the_next_request(link):
    proxy, c = link
    proxy.hold_next_reply()
    with pytest.raises(LinkError):
        c.read_input(rm.IR.MAGIC, 1)
    proxy.release()  # it arrives late, before the next request
    time.sleep(0.05)
    assert c.read_input(rm.IR.N_LEDS, 2) == [rm.N_LEDS, rm.N_BACKLIGHTS]
    assert c.stats.drained_bytes == 7 and c.stats.stale == 0


def _frame(*b: int) -> bytes:
    return rtu_frame(bytes(b))


@pytest.mark.parametrize("request_, reply, why", [
    (_frame(1, 4, 0, 4, 0, 2), _frame(1, 4, 4, 0, 127, 0, 4), None),
    (_frame(1, 4, 0, 4, 0, 2), _frame(1, 4, 2, 0x44, 0x53), "2 data bytes, not the 4"),
    (_frame(1, 4, 0, 4, 0, 2), _frame(2, 4, 4, 0, 127, 0, 4), "from server 2"),
    (_frame(1, 4, 0, 4, 0, 2), _frame(1, 3, 4, 0, 127, 0, 4), "FC 03, not 04"),
    (_frame(1, 4, 0, 4, 0, 2), _frame(1, 0x84, 2), None),
    (_frame(1, 1, 0, 0, 0, 9), _frame(1, 1, 1, 0xFF), "1 data bytes, not the 2"),
    (_frame(1, 6, 0, 6, 0, 111), _frame(1, 6, 0, 6, 0, 111), None),
    (_frame(1, 6, 0, 7, 0, 0), _frame(1, 6, 0, 6, 0, 111), "echo of address 6 / 111, not 7 / 0"),
    (_frame(1, 0x10, 0x10, 0, 0, 10, 20) , _frame(1, 0x10, 0x10, 0, 0, 12), "echo of address"),
    (_frame(1, 5, 0, 3, 0xFF, 0), _frame(1, 5, 0, 3, 0, 0), "echo of address 3 / 0, not 3 / 65280"),
    (_frame(1, 0x2B, 0x0E, 1, 0), _frame(1, 0x2B, 0x0E, 3, 0x82, 0, 0, 0), "read code 03"),
])
def test_reply_mismatch_names_what_does_not_fit(request_, reply, why):
    got = reply_mismatch(request_, reply)
    assert (got is None) if why is None else (why in got)


STEPS = [Step(rm.Source.LED, i, 1000, None, 1000, 5000, 100, 1, 0, 1) for i in range(4)]


def test_a_lost_start_reply_is_not_answered_busy(link):
    """The retry finds the sequence running: run() follows it to the end."""
    proxy, c = link
    c.retries = 3
    c.upload(STEPS * 40)  # 160 steps x 6 ms: still running when the retry comes
    proxy.drop_reply_after(command_is(rm.Command.START))
    res = c.run(timeout_s=30)
    assert res.state == rm.State.DONE
    assert [e.kind for e in res.events].count(rm.Event.SEQ_START) == 1
    assert c.stats.confirmed_by_status == 1


def test_a_lost_start_reply_never_runs_a_short_sequence_twice(link):
    proxy, c = link
    c.retries = 3
    c.upload(STEPS[:1])  # 6 ms: over before the retry
    c.sync_events()
    proxy.drop_reply_after(command_is(rm.Command.START))
    c.start()
    time.sleep(0.2)
    kinds = [e.kind for e in c.poll_events()]
    assert kinds.count(rm.Event.SEQ_START) == 1 and kinds.count(rm.Event.SEQ_DONE) == 1
    assert c.stats.confirmed_by_status == 1


@pytest.mark.parametrize("cmd", [rm.Command.ABORT, rm.Command.CLEAR_ERROR])
def test_a_lost_abort_or_clear_reply_is_confirmed_by_the_status(link, cmd):
    proxy, c = link
    c.retries = 3
    c.upload(STEPS * 40)
    if cmd == rm.Command.CLEAR_ERROR:  # get into FAULT: the watchdog trips while running
        c.set_watchdog(rm.WATCHDOG_MS_MIN)
        c.start()
        time.sleep(0.3)
        assert c.status().state == rm.State.FAULT
    else:
        c.start()
    proxy.drop_reply_after(command_is(cmd))
    c.command(cmd)
    st = c.status()
    assert st.state == (rm.State.ABORTED if cmd == rm.Command.ABORT else rm.State.IDLE)
    assert st.error == rm.Error.NONE
    assert c.stats.confirmed_by_status == 1
    assert c.lights_on() == []


def test_a_slow_reply_whose_data_looks_like_a_frame_is_read_whole(tmp_path):
    """Data bytes ff ff 00 00 00 pass as an exception frame from server 255 with a valid CRC. When a
    reply arrives slowly (QEMU's USART: a byte per main-loop turn), the client used to find that
    'frame' inside the unfinished reply, cut the buffer there and call the reply corrupted: every
    status read after a servo move failed on QEMU. A frame from our server that is still arriving
    is now waited for."""
    import os
    import threading

    import serial

    words = [0, 0, 0xFFFF, 0, 0xFFFF, 0, 0x23, 0xAAAF, 0, 2, 0, 0, 0x0B, 0, 0, 0, 0, 0, 0]
    reply = rtu_frame(bytes([1, 4, 2 * len(words)]) + b"".join(w.to_bytes(2, "big") for w in words))
    assert bytes.fromhex("ff ff 00 00 00") in reply
    master, slave = os.openpty()
    port = os.ttyname(slave)
    client = RigClient(port, parity="N", stopbits=2, timeout=1.0)
    try:
        def answer():
            req = b""
            while len(req) < 8:
                req += os.read(master, 64)
            for b in reply:  # one byte every 2 ms
                os.write(master, bytes([b]))
                time.sleep(0.002)

        threading.Thread(target=answer, daemon=True).start()
        assert client.read_input(rm.IR.STATE, len(words)) == words
    finally:
        client.close()
        os.close(master)
        os.close(slave)
