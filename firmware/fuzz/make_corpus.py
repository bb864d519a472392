#!/usr/bin/env python3
"""Seed corpora for the fuzzers from protocol/vectors.toml.

    python3 fuzz/make_corpus.py OUT_DIR     (writes OUT_DIR/frame/* and OUT_DIR/rtu/*)

frame: each vector's request as one fuzz_frame record, plus the whole vector file as one input
(so the fuzzer starts from states that need earlier writes, e.g. an armed camera sequence).
rtu: the same requests as fuzz_rtu "feed" ops separated by t3.5 gaps.
"""
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def frame_record(req: bytes) -> bytes:
    # flags 0b110: address as is, CRC as is; gap 400 x 64 us
    return bytes([0x06, 0x90, 0x01, min(len(req), 255)]) + req[:255]


def rtu_ops(req: bytes) -> bytes:
    out = b""
    for i in range(0, len(req), 63):
        chunk = req[i:i + 63]
        out += bytes([0x00, len(chunk)]) + chunk
    return out + bytes([0x01, 200])  # 3.2 ms of silence ends the frame


def main() -> None:
    out = Path(sys.argv[1])
    vecs = tomllib.loads((ROOT / "protocol/vectors.toml").read_text())["vector"]
    (out / "frame").mkdir(parents=True, exist_ok=True)
    (out / "rtu").mkdir(parents=True, exist_ok=True)
    all_frames, all_rtu = b"", b""
    for i, v in enumerate(vecs):
        req = bytes.fromhex(v["request"])
        (out / "frame" / f"v{i:03d}").write_bytes(frame_record(req))
        (out / "rtu" / f"v{i:03d}").write_bytes(rtu_ops(req))
        all_frames += frame_record(req)
        all_rtu += rtu_ops(req)
    (out / "frame" / "all").write_bytes(all_frames)
    (out / "rtu" / "all").write_bytes(all_rtu)
    print(f"seed corpus: {len(vecs)} vectors -> {out}")


if __name__ == "__main__":
    main()
