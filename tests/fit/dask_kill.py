"""A worker killed mid-task, for the tiled fits' fault tests (tests/fit/test_tiled.py, test_stream.py)."""

from __future__ import annotations


def run_killing_a_busy_worker(client, fit, marker: str) -> dict:
    """Run ``fit()`` in a thread and SIGKILL the first worker process of ``client`` seen running
    a task whose key holds ``marker``; returns ``{"res": fit's result}`` or ``{"error": e}``,
    with ``killed`` (the pid; None when no worker was seen busy within 120 s)."""
    import os
    import signal
    import threading
    import time

    pids = client.run(os.getpid)
    out: dict = {}

    def run():
        try:
            out["res"] = fit()
        except BaseException as e:  # noqa: BLE001 - reported to the caller
            out["error"] = e

    t = threading.Thread(target=run)
    t.start()
    killed = None
    deadline = time.monotonic() + 120
    while killed is None and time.monotonic() < deadline and t.is_alive():
        busy = [w for w, keys in client.processing().items() if any(marker in str(k) for k in keys)]
        if busy:
            killed = pids[busy[0]]
            os.kill(killed, signal.SIGKILL)
        else:
            time.sleep(0.02)
    t.join(300)
    out["killed"] = killed
    return out
