#!/usr/bin/env python3
"""Seed corpora for the fuzzers from protocol/vectors.toml.

    python3 fuzz/make_corpus.py [--max-len N] [--clean] OUT_DIR   (OUT_DIR/frame/*, OUT_DIR/rtu/*)

frame: each vector's request as one fuzz_frame record (file vNNN), plus the vector file replayed
in order in pieces of at most N bytes (files allNN), so the fuzzer starts from states that need
earlier writes (e.g. an armed camera sequence) without inputs longer than its -max_len.
rtu: the same requests as fuzz_rtu "feed" ops, each followed by a t3.5 gap.
Both also get fifo_fill: the vectors' one-step upload made a 10-step sequence (settle 10 us, so
the trigger line falls between steps) and started 17 times without an ack: 17 x 32 events
overflow the 512-event FIFO (EVT_DROPPED), which no input under 1 KiB reached by chance.
Deterministic: the same vectors give the same bytes. The committed set is fuzz/corpus/
(`make -C firmware fuzz-corpus`); --clean first removes the files this script writes there.
"""
import argparse
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "host"))
from dualscale.protocol.crc import rtu_frame  # noqa: E402  (pure Python: no package dependencies)


def frame_record(req: bytes) -> bytes:
    # flags 0b110: address as is, CRC as is; gap 400 x 64 us
    return bytes([0x06, 0x90, 0x01, min(len(req), 255)]) + req[:255]


def rtu_ops(req: bytes) -> bytes:
    out = b""
    for i in range(0, len(req), 63):
        chunk = req[i:i + 63]
        out += bytes([0x00, len(chunk)]) + chunk
    return out + bytes([0x01, 200])  # 3.2 ms of silence ends the frame


def with_crc(body: bytes) -> bytes:
    """Address + PDU + CRC-16/MODBUS (the host's one implementation, as firmware/core/src/crc.c)."""
    return rtu_frame(body)


def fifo_fill(vecs: dict[str, bytes], steps: int = 10, starts: int = 17) -> list[bytes]:
    """Requests that overflow the event FIFO: see the module docstring."""
    one = vecs["upload_one_step"]          # 01 10 1000 000a 14 <20 bytes of step> crc
    assert one[1] == 0x10 and one[6] == 20, "upload_one_step is no longer a one-step FC 10"
    step = bytearray(one[7:27])
    step[6:10] = (10).to_bytes(4, "big")   # SETTLE_US (words 3-4, u32) = 10 us
    words = bytes(step) * steps
    upload = with_crc(bytes([1, 0x10, 0x10, 0x00, 0, 10 * steps, 20 * steps]) + words)
    seq_len = with_crc(bytes([1, 0x06, 0x00, 0x02, 0, steps]))
    return [upload, seq_len] + [vecs["start_device_master"]] * starts


def pieces(records: list[bytes], max_len: int) -> list[bytes]:
    """Consecutive records joined into inputs of at most max_len bytes (a longer record alone)."""
    out, cur = [], b""
    for r in records:
        if cur and len(cur) + len(r) > max_len:
            out.append(cur)
            cur = b""
        cur += r
    if cur:
        out.append(cur)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--max-len", type=int, default=1024)
    ap.add_argument("--clean", action="store_true")
    a = ap.parse_args()
    vecs = tomllib.loads((ROOT / "protocol/vectors.toml").read_text())["vector"]
    for kind, enc in (("frame", frame_record), ("rtu", rtu_ops)):
        d = a.out / kind
        d.mkdir(parents=True, exist_ok=True)
        if a.clean:
            for old in list(d.glob("v[0-9][0-9][0-9]")) + list(d.glob("all*")) + list(d.glob("fifo_fill")):
                old.unlink()
        recs = [enc(bytes.fromhex(v["request"])) for v in vecs]
        for i, r in enumerate(recs):
            (d / f"v{i:03d}").write_bytes(r)
        for j, p in enumerate(pieces(recs, a.max_len)):
            (d / f"all{j:02d}").write_bytes(p)
        by_name = {v["name"]: bytes.fromhex(v["request"]) for v in vecs}
        fill = b"".join(enc(r) for r in fifo_fill(by_name))
        assert len(fill) <= a.max_len, len(fill)
        (d / "fifo_fill").write_bytes(fill)
    print(f"seed corpus: {len(vecs)} vectors -> {a.out}")


if __name__ == "__main__":
    main()
