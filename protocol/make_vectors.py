#!/usr/bin/env python3
"""Write protocol/vectors.toml: request/response vectors derived by hand from PROTOCOL.md.

The expected responses are built here from the specification (not recorded from the firmware),
so replaying them tests the firmware. The vectors are replayed in file order against one freshly
initialised device at address 1 (target name "posix"), with >= t3.5 between frames; later
vectors rely on earlier writes. Nothing here depends on time (no UPTIME_US, no timestamps).

    python3 protocol/make_vectors.py && python3 protocol/gen.py
"""
from __future__ import annotations

import struct
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "protocol" / "vectors.toml"
sys.path.insert(0, str(ROOT / "host"))
from dualscale.protocol.crc import crc16, rtu_frame  # noqa: E402  (pure Python, no dependencies)

VECTORS: list[tuple[str, bytes, bytes]] = []


def adu(addr: int, pdu: bytes) -> bytes:
    return rtu_frame(bytes([addr]) + pdu)


def words(*ws: int) -> bytes:
    return b"".join(struct.pack(">H", w & 0xFFFF) for w in ws)


def vec(name: str, request: bytes, response: bytes | None) -> None:
    VECTORS.append((name, request, response or b""))


def ok(name: str, req_pdu: bytes, resp_pdu: bytes, addr: int = 1) -> None:
    vec(name, adu(addr, req_pdu), adu(1, resp_pdu))


def exc(name: str, req_pdu: bytes, code: int) -> None:
    vec(name, adu(1, req_pdu), adu(1, bytes([req_pdu[0] | 0x80, code])))


def read(fc: int, start: int, values: list[int]) -> tuple[bytes, bytes]:
    return bytes([fc]) + words(start, len(values)), bytes([fc, 2 * len(values)]) + words(*values)


def rd_ir(name: str, start: int, values: list[int]) -> None:
    ok(name, *read(0x04, start, values))


def rd_hr(name: str, start: int, values: list[int]) -> None:
    ok(name, *read(0x03, start, values))


def wr1(name: str, addr: int, value: int) -> None:
    pdu = bytes([0x06]) + words(addr, value)
    ok(name, pdu, pdu)


def wr1_exc(name: str, addr: int, value: int, code: int) -> None:
    exc(name, bytes([0x06]) + words(addr, value), code)


def wrn_pdu(addr: int, values: list[int]) -> bytes:
    return bytes([0x10]) + words(addr, len(values)) + bytes([2 * len(values)]) + words(*values)


def wrn(name: str, addr: int, values: list[int]) -> None:
    ok(name, wrn_pdu(addr, values), bytes([0x10]) + words(addr, len(values)))


def coil_bytes(bits: list[int]) -> bytes:
    out = bytearray((len(bits) + 7) // 8)
    for i, b in enumerate(bits):
        if b:
            out[i // 8] |= 1 << (i % 8)
    return bytes(out)


def rd_coils(name: str, start: int, bits: list[int]) -> None:
    ok(name, bytes([0x01]) + words(start, len(bits)),
       bytes([0x01, (len(bits) + 7) // 8]) + coil_bytes(bits))


def step(source=0x0100, intensity=1000, pol=0xFFFF, settle=0, exposure=1, pulse=0,
         brackets=0x0001, triggers=0x0001) -> list[int]:
    return [source, intensity, pol, settle >> 16, settle & 0xFFFF, exposure >> 16,
            exposure & 0xFFFF, pulse, brackets, triggers]


def seq_crc(steps: list[list[int]]) -> int:
    return crc16(b"".join(words(*s) for s in steps))


# enums (registers.toml)
IDLE, ARMED, RUNNING, DONE, ABORTED, FAULT = range(6)
START, ABORT, CLEAR_ERROR, ALL_OFF, CLEAR_EVENTS = 1, 2, 3, 4, 5
EV_SEQ_START, EV_STEP_START, EV_TRIGGER, EV_STEP_END, EV_SEQ_DONE, EV_SEQ_ABORT = 1, 2, 3, 4, 5, 6
EV_POLARIZER = 10
NONE16 = 0xFFFF
HR_COMMAND, HR_MODE, HR_SEQ_LEN, HR_ACK, HR_WD, HR_POL, HR_MANUAL = 0, 1, 2, 3, 4, 5, 6
HR_ON_MS, HR_DUTY, HR_SMIN, HR_SMAX, HR_CAM_TO, HR_CAM, HR_GAP = 7, 8, 9, 10, 11, 12, 13
IR_STATE, IR_POL_NOW, IR_EVT_COUNT, IR_FRAMES_OK, IR_SEQ_DUR = 8, 16, 17, 20, 24
STEPS = 0x1000
TARGET = "posix"
FW, PROTO = "0.1.0", "1.1"
PARITY_NONE, PARITY_ODD, PARITY_EVEN = 0, 1, 2
HR_FRAME_TO, HR_PARITY, HR_STOP = 15, 16, 17
IR_COUNT, HR_COUNT = 31, 18


def build() -> None:
    # ---- identification -----------------------------------------------------------------
    rd_ir("fc04_identity", 0, [0x4453, 0x0101, 0x0001, 0, 127, 4, 2048, 512])
    rd_ir("fc04_state_after_boot", 8, [IDLE, 0, NONE16, 0, 0xFFFF])  # SEQ_CRC of 0 steps = init
    rd_hr("fc03_defaults", 0, [0, 0, 0, 0, 0, 0, 32768, 10000, 500, 0, 18000, 2000, 0, 0, 0])
    # (FRAME_TIMEOUT_US, 15, is left out: the QEMU launcher raises it by broadcast)
    rd_hr("fc03_serial_defaults_8e1", HR_PARITY, [PARITY_EVEN, 1])  # serial line v1.02 s. 2.5.1
    rd_ir("uart_error_counters_zero", 27, [0, 0, 0, 0])
    text = f"dualscale fw={FW} proto={PROTO} target={TARGET}".encode()
    ok("fc11_report_server_id", b"\x11", bytes([0x11, 2 + len(text), 0x01, 0xFF]) + text)
    objs = [b"dualscale", b"DS-RIG", FW.encode(), b"https://github.com/dualscale/dualscale",
            b"dualscale rig controller", TARGET.encode(), f"proto={PROTO}".encode()]

    def devid(code: int, ids: list[int]) -> bytes:
        body = bytes([0x2B, 0x0E, code, 0x82, 0x00, 0x00, len(ids)])
        for i in ids:
            body += bytes([i, len(objs[i])]) + objs[i]
        return body

    ok("fc2b_basic_stream", bytes([0x2B, 0x0E, 0x01, 0x00]), devid(1, [0, 1, 2]))
    ok("fc2b_regular_stream", bytes([0x2B, 0x0E, 0x02, 0x00]), devid(2, list(range(7))))
    ok("fc2b_individual_model_name", bytes([0x2B, 0x0E, 0x04, 0x05]), devid(4, [5]))
    ok("fc2b_individual_user_app", bytes([0x2B, 0x0E, 0x04, 0x06]), devid(4, [6]))
    exc("fc2b_unknown_mei_type", bytes([0x2B, 0x0D, 0x01, 0x00]), 0x01)
    exc("fc2b_bad_read_code", bytes([0x2B, 0x0E, 0x05, 0x00]), 0x03)
    exc("fc2b_unknown_object", bytes([0x2B, 0x0E, 0x04, 0x07]), 0x02)
    # stream access (read codes 01..03): an id that is not an object of the category restarts at
    # 0x00 (MB application protocol v1.1b3 section 6.21); only individual access (04) answers 02
    ok("fc2b_basic_stream_from_1", bytes([0x2B, 0x0E, 0x01, 0x01]), devid(1, [1, 2]))
    ok("fc2b_basic_stream_regular_id_restarts", bytes([0x2B, 0x0E, 0x01, 0x03]), devid(1, [0, 1, 2]))
    ok("fc2b_basic_stream_missing_id_restarts", bytes([0x2B, 0x0E, 0x01, 0x99]), devid(1, [0, 1, 2]))
    ok("fc2b_regular_stream_from_5", bytes([0x2B, 0x0E, 0x02, 0x05]), devid(2, [5, 6]))
    ok("fc2b_regular_stream_missing_id_restarts", bytes([0x2B, 0x0E, 0x02, 0x07]),
       devid(2, list(range(7))))
    ok("fc2b_extended_stream", bytes([0x2B, 0x0E, 0x03, 0x00]), devid(3, list(range(7))))
    ok("fc2b_extended_stream_missing_private_id_restarts", bytes([0x2B, 0x0E, 0x03, 0x80]),
       devid(3, list(range(7))))
    exc("fc2b_individual_missing_private_id", bytes([0x2B, 0x0E, 0x04, 0x80]), 0x02)
    # order: the read code (03) is checked before the object (02)
    exc("fc2b_order_read_code_before_object", bytes([0x2B, 0x0E, 0x05, 0x99]), 0x03)
    exc("fc2b_order_mei_type_before_read_code", bytes([0x2B, 0x0D, 0x05, 0x99]), 0x01)
    exc("unknown_function_07", bytes([0x07]), 0x01)
    exc("unknown_function_41", bytes([0x41, 0x00, 0x00]), 0x01)
    exc("fc11_order_length", b"\x11\x00", 0x03)  # FC 11 has no address: 01 then 03

    # ---- manual coils -------------------------------------------------------------------
    ok("fc05_led5_on", bytes([0x05]) + words(5, 0xFF00), bytes([0x05]) + words(5, 0xFF00))
    rd_coils("fc01_led5_is_on", 0, [1 if i == 5 else 0 for i in range(16)])
    exc("fc05_bad_value", bytes([0x05]) + words(6, 0x1234), 0x03)
    exc("fc05_unmapped_coil_127", bytes([0x05]) + words(127, 0xFF00), 0x02)
    # order (MB application protocol v1.1b3 state diagrams): 01 -> 03 -> 02 -> 04; the output
    # value is a field of the request and is checked before the address
    exc("fc05_order_value_before_address", bytes([0x05]) + words(200, 0x1234), 0x03)
    ok("fc0f_backlights_0_and_2", bytes([0x0F]) + words(128, 4) + b"\x01\x05",
       bytes([0x0F]) + words(128, 4))
    rd_coils("fc01_backlights", 128, [1, 0, 1, 0])
    rd_coils("fc01_diffuse_off", 136, [0])
    exc("fc01_quantity_zero", bytes([0x01]) + words(0, 0), 0x03)
    exc("fc01_quantity_2001", bytes([0x01]) + words(0, 2001), 0x03)
    exc("fc01_range_crosses_unmapped_127", bytes([0x01]) + words(120, 16), 0x02)
    exc("fc01_order_quantity_before_address", bytes([0x01]) + words(5000, 2001), 0x03)
    exc("fc0f_byte_count_mismatch", bytes([0x0F]) + words(128, 4) + b"\x02\x05\x00", 0x03)
    exc("fc0f_unmapped_132", bytes([0x0F]) + words(130, 3) + b"\x01\x00", 0x02)
    exc("fc0f_order_byte_count_before_address", bytes([0x0F]) + words(5000, 9) + b"\x01\x00", 0x03)
    wr1("all_off_command", HR_COMMAND, ALL_OFF)
    rd_coils("fc01_all_leds_off", 0, [0] * 127)
    rd_coils("fc01_backlights_off", 128, [0, 0, 0, 0])

    # ---- holding registers: ranges, atomicity, servo window, u32 ------------------------
    rd_hr("command_reads_zero", HR_COMMAND, [0])
    wr1_exc("fc06_command_out_of_range", HR_COMMAND, 6, 0x03)
    wr1_exc("fc06_trigger_mode_out_of_range", HR_MODE, 2, 0x03)
    wr1_exc("fc06_seq_len_too_long", HR_SEQ_LEN, 2049, 0x03)
    wr1_exc("fc06_watchdog_below_min", HR_WD, 49, 0x03)
    wr1_exc("fc06_watchdog_above_max", HR_WD, 60001, 0x03)
    wr1_exc("fc06_led_max_on_zero", HR_ON_MS, 0, 0x03)
    wr1_exc("fc06_duty_zero", HR_DUTY, 0, 0x03)
    wr1_exc("fc06_duty_1001", HR_DUTY, 1001, 0x03)
    wr1_exc("fc06_camera_timeout_zero", HR_CAM_TO, 0, 0x03)
    wr1_exc("fc06_master_camera_4", HR_CAM, 4, 0x03)
    wr1_exc("fc06_unmapped_18", HR_COUNT, 0, 0x02)
    # FC06's only request-field check is the value 0..0xFFFF (always true); a register's own
    # range belongs to the execution: the address answers first
    wr1_exc("fc06_order_address_before_register_range", HR_COUNT, 0xFFFF, 0x02)
    wr1_exc("fc06_unmapped_past_step_table", STEPS + 10 * 2048, 0, 0x02)
    exc("fc03_quantity_126", bytes([0x03]) + words(0, 126), 0x03)
    exc("fc03_quantity_zero", bytes([0x03]) + words(0, 0), 0x03)
    exc("fc03_range_17_18", bytes([0x03]) + words(HR_COUNT - 1, 2), 0x02)
    exc("fc03_order_quantity_before_address", bytes([0x03]) + words(0x0FFF, 126), 0x03)
    exc("fc03_gap_between_regions", bytes([0x03]) + words(0x0FFF, 2), 0x02)
    exc("fc04_unmapped_31", bytes([0x04]) + words(IR_COUNT, 1), 0x02)
    exc("fc04_order_quantity_before_address", bytes([0x04]) + words(IR_COUNT, 0), 0x03)
    exc("fc04_window_past_end", bytes([0x04]) + words(256 + 119, 2), 0x02)
    exc("fc04_quantity_126", bytes([0x04]) + words(256, 126), 0x03)
    exc("fc03_short_pdu", bytes([0x03]) + words(0), 0x03)
    wr1("fc06_watchdog_zero_ok", HR_WD, 0)
    # FRAME_GAP_US is a u32 over two registers, range 0..60000000 (0x03938700)
    exc("fc10_frame_gap_above_max", wrn_pdu(HR_GAP, [0x0393, 0x8701]), 0x03)
    rd_hr("frame_gap_unchanged", HR_GAP, [0, 0])
    wr1("fc06_frame_gap_high_word", HR_GAP, 0x0393)
    wr1("fc06_frame_gap_low_word_max", HR_GAP + 1, 0x8700)
    wr1_exc("fc06_frame_gap_low_word_over", HR_GAP + 1, 0x8701, 0x03)
    rd_hr("frame_gap_is_60s", HR_GAP, [0x0393, 0x8700])
    wr1_exc("fc06_frame_gap_high_word_over", HR_GAP, 0x0394, 0x03)
    wrn("fc10_frame_gap_back_to_zero", HR_GAP, [0, 0])
    # atomic multi-register write: one bad value, nothing changes
    exc("fc10_atomic_one_bad_value", wrn_pdu(HR_MANUAL, [100, 0, 500]), 0x03)
    rd_hr("fc10_atomic_nothing_written", HR_MANUAL, [32768, 10000, 500])
    exc("fc10_order_byte_count_before_address",
        bytes([0x10]) + words(HR_COUNT, 2) + b"\x03" + words(1, 2), 0x03)
    exc("fc10_order_address_before_register_range", wrn_pdu(HR_COUNT - 1, [9, 0]), 0x02)
    exc("fc10_byte_count_mismatch", bytes([0x10]) + words(HR_MANUAL, 2) + b"\x03" + words(1, 2), 0x03)
    # (a full 124-register write would not fit in a 256-byte ADU: the quantity check answers first)
    exc("fc10_quantity_124", bytes([0x10]) + words(STEPS, 124) + bytes([248]) + words(0, 0), 0x03)
    # servo window
    wr1("servo_min_9000", HR_SMIN, 9000)
    wr1_exc("servo_max_below_min", HR_SMAX, 8000, 0x03)
    wr1_exc("polarizer_below_window", HR_POL, 5000, 0x03)
    wr1("polarizer_9000", HR_POL, 9000)  # event 0: POLARIZER (manual)
    rd_ir("polarizer_now_9000", IR_POL_NOW, [9000])
    exc("servo_window_inverted_pair", wrn_pdu(HR_SMIN, [12000, 11000]), 0x03)
    wrn("servo_window_reset", HR_SMIN, [0, 18000])
    # serial line format (PROTOCOL.md section 1): parity NONE needs 2 stop bits, 1 stop bit needs
    # parity; the pair is checked as one value, like the servo window; applied after the response
    wr1_exc("parity_none_needs_two_stop_bits", HR_PARITY, PARITY_NONE, 0x03)
    wr1_exc("parity_3_out_of_range", HR_PARITY, 3, 0x03)
    wr1_exc("stop_bits_0_out_of_range", HR_STOP, 0, 0x03)
    wrn("serial_8n2", HR_PARITY, [PARITY_NONE, 2])
    wr1_exc("one_stop_bit_needs_parity", HR_STOP, 1, 0x03)
    rd_hr("serial_reads_8n2", HR_PARITY, [PARITY_NONE, 2])
    wr1("serial_8o2", HR_PARITY, PARITY_ODD)
    wrn("serial_back_to_8e1", HR_PARITY, [PARITY_EVEN, 1])
    # FC 17: the write is done first
    ok("fc17_write_then_read", bytes([0x17]) + words(HR_POL, 3, HR_MANUAL, 1) + b"\x02" + words(1000),
       bytes([0x17, 6]) + words(9000, 1000, 10000))
    exc("fc17_write_quantity_122",
        bytes([0x17]) + words(0, 1, STEPS, 122) + bytes([244]) + words(0, 0), 0x03)
    exc("fc17_read_unmapped", bytes([0x17]) + words(HR_COUNT, 1, HR_MANUAL, 1) + b"\x02" + words(7), 0x02)
    exc("fc17_order_quantity_before_address",
        bytes([0x17]) + words(HR_COUNT, 0, HR_COUNT, 1) + b"\x02" + words(7), 0x03)
    exc("fc17_order_address_before_register_range",
        bytes([0x17]) + words(HR_COUNT, 1, HR_DUTY, 1) + b"\x02" + words(0), 0x02)
    rd_hr("fc17_failed_writes_nothing", HR_MANUAL, [1000])

    # ---- framing and silence ------------------------------------------------------------
    vec("broadcast_write_silent", adu(0, bytes([0x06]) + words(HR_MANUAL, 0x1234)), None)
    rd_hr("broadcast_write_took_effect", HR_MANUAL, [0x1234])
    vec("broadcast_read_ignored", adu(0, bytes([0x03]) + words(0, 1)), None)
    vec("other_address_ignored", adu(2, bytes([0x06]) + words(HR_MANUAL, 7)), None)
    rd_hr("other_address_wrote_nothing", HR_MANUAL, [0x1234])
    bad = bytearray(adu(1, bytes([0x06]) + words(HR_MANUAL, 9)))
    bad[-1] ^= 0x01
    vec("bad_crc_silent", bytes(bad), None)
    vec("truncated_frame_silent", adu(1, bytes([0x03]) + words(0, 1))[:5], None)
    vec("too_short_frame_silent", bytes([0x01, 0x03, 0x00]), None)
    vec("oversize_frame_silent", adu(1, bytes([0x10]) + words(STEPS, 125) + bytes([250]) + bytes(254)), None)
    rd_hr("garbage_wrote_nothing", HR_MANUAL, [0x1234])
    rd_ir("frame_error_counters", 21, [2, 2])  # FRAMES_BAD_CRC (bad CRC, truncated), FRAMES_BAD

    # ---- events -------------------------------------------------------------------------
    rd_ir("one_event_pending", IR_EVT_COUNT, [1, 0, 0])  # COUNT, FIRST_SEQ, DROPPED
    rd_ir("event0_polarizer", 256, [0, EV_POLARIZER, NONE16])
    rd_ir("window_slot1_zero", 256 + 6, [0, 0, 0, 0, 0, 0])
    wr1("ack_outside_range_ignored", HR_ACK, 5)
    rd_ir("still_one_event", IR_EVT_COUNT, [1, 0])
    wr1("ack_event0", HR_ACK, 0)
    rd_ir("no_event_pending", IR_EVT_COUNT, [0, 1])
    wr1("ack_repeated_harmless", HR_ACK, 0)
    rd_ir("still_no_event", IR_EVT_COUNT, [0, 1])
    rd_hr("evt_ack_reads_back", HR_ACK, [0])

    # ---- START validation ---------------------------------------------------------------
    wr1_exc("start_empty_sequence", HR_COMMAND, START, 0x03)
    rd_ir("error_seq_empty", 8, [IDLE, 0x10, NONE16])
    bad_steps = [step(), step(source=0x0500)]
    wrn("upload_bad_source", STEPS, bad_steps[0] + bad_steps[1])
    wr1("seq_len_2", HR_SEQ_LEN, 2)
    rd_ir("seq_crc_two_steps", 12, [seq_crc(bad_steps)])
    wr1_exc("start_bad_source", HR_COMMAND, START, 0x03)
    rd_ir("error_bad_source_step1", 8, [IDLE, 0x12, 1])
    wrn("step1_led_intensity_zero", STEPS + 10, step(intensity=0))
    wr1_exc("start_bad_intensity", HR_COMMAND, START, 0x03)
    rd_ir("error_bad_intensity_step1", 8, [IDLE, 0x13, 1])
    wrn("step1_no_trigger_device_master", STEPS + 10, step(triggers=0))
    wr1_exc("start_no_trigger", HR_COMMAND, START, 0x03)
    rd_ir("error_trigger_mask_step1", 8, [IDLE, 0x19, 1])
    wr1("clear_error", HR_COMMAND, CLEAR_ERROR)
    rd_ir("error_cleared", 8, [IDLE, 0, NONE16])

    # ---- a 1 us device-master sequence: done long before the next frame ----------------
    wr1("clear_events_before_run", HR_COMMAND, CLEAR_EVENTS)
    rd_ir("events_cleared", IR_EVT_COUNT, [0, 1])
    run = [step(source=0x0100, intensity=1000, exposure=1, pulse=0, triggers=0x0001)]
    wrn("upload_one_step", STEPS, run[0])
    wr1("seq_len_1", HR_SEQ_LEN, 1)
    rd_ir("seq_crc_one_step", 12, [seq_crc(run)])
    wr1("start_device_master", HR_COMMAND, START)
    rd_ir("state_done", 8, [DONE, 0, NONE16, 0, seq_crc(run)])
    rd_ir("seq_duration_1us", IR_SEQ_DUR, [0, 0, 1])
    rd_coils("lights_off_after_done", 0, [0] * 8)
    # events 1..5: SEQ_START(arg 0), STEP_START 0, TRIGGER(b 0) 0, STEP_END 0, SEQ_DONE
    rd_ir("five_events_pending", IR_EVT_COUNT, [5, 1])
    expect = [(1, EV_SEQ_START, NONE16), (2, EV_STEP_START, 0), (3, EV_TRIGGER, 0),
              (4, EV_STEP_END, 0), (5, EV_SEQ_DONE, NONE16)]
    for i, (s, k, st) in enumerate(expect):
        rd_ir(f"run_event{i}_kind", 256 + 6 * i, [s, k, st])
    wr1("ack_first_two", HR_ACK, 2)
    rd_ir("three_events_left", IR_EVT_COUNT, [3, 3])
    rd_ir("window_starts_at_seq3", 256, [3, EV_TRIGGER, 0])
    wr1("ack_older_than_pending_ignored", HR_ACK, 1)
    rd_ir("still_three_events", IR_EVT_COUNT, [3, 3])
    wr1("ack_all", HR_ACK, 5)
    rd_ir("fifo_empty", IR_EVT_COUNT, [0, 6])

    # ---- camera-master: ARMED, busy (06), ABORT ----------------------------------------
    wrn("camera_mode_and_long_timeout", HR_MODE, [1])
    wr1("camera_timeout_60s", HR_CAM_TO, 60000)
    wr1("start_camera_master", HR_COMMAND, START)  # event 6: SEQ_START arg 1
    rd_ir("state_armed", IR_STATE, [ARMED])
    exc("busy_coil_write", bytes([0x05]) + words(0, 0xFF00), 0x06)
    exc("busy_coils_write", bytes([0x0F]) + words(0, 1) + b"\x01\x01", 0x06)
    exc("busy_step_table", wrn_pdu(STEPS, step()), 0x06)
    wr1_exc("busy_trigger_mode", HR_MODE, 0, 0x06)
    wr1_exc("busy_polarizer", HR_POL, 100, 0x06)
    wr1_exc("busy_all_off", HR_COMMAND, ALL_OFF, 0x06)
    wr1_exc("busy_start_while_armed", HR_COMMAND, START, 0x06)
    exc("range_checked_before_busy", bytes([0x06]) + words(HR_MODE, 7), 0x03)
    rd_ir("error_busy", 8, [ARMED, 0x1D, NONE16])
    wr1("seq_len_writable_while_armed", HR_SEQ_LEN, 1)
    wr1("abort", HR_COMMAND, ABORT)  # event 7: SEQ_ABORT arg HOST
    rd_ir("state_aborted", IR_STATE, [ABORTED])
    rd_ir("abort_events", IR_EVT_COUNT, [2, 6])
    rd_ir("abort_event0", 256, [6, EV_SEQ_START | 1 << 8, NONE16])
    rd_ir("abort_event1", 256 + 6, [7, EV_SEQ_ABORT | 1 << 8, NONE16])
    ok("coils_writable_after_abort", bytes([0x05]) + words(136, 0x0000), bytes([0x05]) + words(136, 0x0000))
    wr1("back_to_device_master", HR_MODE, 0)
    n_ok = sum(1 for _, req, resp in VECTORS if resp and req[0] == 1) + 1
    rd_ir("frames_ok_counter", IR_FRAMES_OK, [n_ok & 0xFFFF])


def render() -> str:
    """The text of vectors.toml."""
    VECTORS.clear()
    build()
    lines = ["# Shared Modbus RTU test vectors, generated by protocol/make_vectors.py (edit that).",
             "# Replayed in file order against one freshly initialised device at address 1 (target",
             "# \"posix\"), >= t3.5 between frames. Hex bytes, CRC included; an empty response = silence.",
             ""]
    for name, req, resp in VECTORS:
        lines += ["[[vector]]", f'name = "{name}"', f'request = "{req.hex(" ")}"',
                  f'response = "{resp.hex(" ")}"', ""]
    return "\n".join(lines)


def main() -> None:
    OUT.write_text(render())
    print(f"wrote {OUT.relative_to(ROOT)} ({len(VECTORS)} vectors)")


if __name__ == "__main__":
    main()
