"""A faulty serial line for tests: a pty in front of the simulator's pty.

`LinkProxy(port)` opens the simulator's serial device, makes a new pseudo-terminal and forwards
bytes both ways between them in a thread. It can corrupt bytes (XOR with a random non-zero
byte) and drop bytes, each with its own probability, in both directions, from a seeded RNG (so a
run is repeatable), and it can hold back, drop or cut replies on demand:

- `hold_next_reply()`: the device's next reply is held back and delivered right *after* the
  host's next request has been forwarded (a late reply arriving just as the next one is due);
- `release()`: deliver held-back bytes now;
- `drop_reply_after(pred)`: the reply to the next request whose bytes satisfy `pred` is lost;
- `cut(True/False)`: nothing passes either way.

A "reply" is whatever the device sends between two requests (Modbus RTU is half duplex).
"""
from __future__ import annotations

import os
import random
import select
import threading
import tty
from collections.abc import Callable


class LinkProxy:
    def __init__(self, port: str, corrupt: float = 0.0, drop: float = 0.0, seed: int = 0):
        self.corrupt, self.drop = corrupt, drop
        self.rng = random.Random(seed)
        self.up = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.up)
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo or line editing before a client opens it
        os.set_blocking(self.master, False)
        self.port = os.ttyname(self._slave)
        self.corrupted = self.dropped = 0  # bytes
        self.requests = 0  # host writes forwarded
        self._lock = threading.Lock()
        self._hold_armed = False
        self._holding = False
        self._held = b""
        self._drop_pred: Callable[[bytes], bool] | None = None
        self._dropping = False
        self._cut = False
        self._wake_r, self._wake_w = os.pipe()
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    # ---------------------------------------------------------------- controls
    def hold_next_reply(self) -> None:
        with self._lock:
            self._hold_armed = True

    def release(self) -> None:
        with self._lock:
            held, self._held, self._holding = self._held, b"", False
        if held:
            self._write(self.master, held)

    def drop_reply_after(self, pred: Callable[[bytes], bool]) -> None:
        with self._lock:
            self._drop_pred = pred

    def cut(self, on: bool) -> None:
        with self._lock:
            self._cut = on

    # ---------------------------------------------------------------- the line
    def _mangle(self, data: bytes) -> bytes:
        if not (self.corrupt or self.drop):
            return data
        out = bytearray()
        for b in data:
            if self.drop and self.rng.random() < self.drop:
                self.dropped += 1
                continue
            if self.corrupt and self.rng.random() < self.corrupt:
                b ^= self.rng.randrange(1, 256)
                self.corrupted += 1
            out.append(b)
        return bytes(out)

    @staticmethod
    def _write(fd: int, data: bytes) -> None:
        while data:
            try:
                n = os.write(fd, data)
            except BlockingIOError:
                select.select([], [fd], [], 0.1)
                continue
            data = data[n:]

    def _from_host(self, data: bytes) -> None:
        with self._lock:
            if self._cut:
                return
            release = self._held if self._holding else b""
            if self._holding:
                self._held, self._holding = b"", False
            self._dropping = False
            if self._drop_pred is not None and self._drop_pred(data):
                self._drop_pred, self._dropping = None, True
            if self._hold_armed:
                self._hold_armed, self._holding = False, True
            self.requests += 1
        self._write(self.up, self._mangle(data))
        if release:
            self._write(self.master, release)  # the late reply, just after the new request

    def _from_device(self, data: bytes) -> None:
        with self._lock:
            if self._cut or self._dropping:
                return
            if self._holding:
                self._held += data
                return
        self._write(self.master, self._mangle(data))

    def _run(self) -> None:
        while not self._stop:
            r, _, _ = select.select([self.master, self.up, self._wake_r], [], [], 0.5)
            for fd in r:
                try:
                    data = os.read(fd, 4096)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:  # the device went away (EIO): stop forwarding
                    if fd == self.up:
                        return
                    continue
                if fd == self.master:
                    self._from_host(data)
                elif fd == self.up:
                    self._from_device(data)

    def close(self) -> None:
        self._stop = True
        os.write(self._wake_w, b"x")
        self._thread.join(2)
        for fd in (self.master, self._slave, self.up, self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> LinkProxy:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
