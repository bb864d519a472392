"""Headless Chromium driven over the Chrome DevTools Protocol (websocket-client), with WebGL
through SwiftShader: the one browser harness of the report's and the viewer's tests.

WebGL in headless Chromium has no GPU here: ``--use-angle=swiftshader --enable-unsafe-swiftshader
--use-gl=angle`` gives WebGL 2 with float render targets (docs/VIEWER.md).
"""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest

GL_FLAGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--use-gl=angle"]


def chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def require_browser(vendor: bool = True) -> str:
    """The chromium binary, or skip (with the reason) when it, websocket-client or (``vendor``)
    the viewer's three.js vendor files are missing."""
    from dualscale.view.server import VENDOR_HINT, vendor_missing

    exe = chromium()
    if exe is None:
        pytest.skip("no chromium binary on PATH (Debian: apt-get install chromium; `make deps` installs it)")
    pytest.importorskip("websocket", reason="websocket-client is not installed (pip install -e '.[dev]')")
    missing = vendor_missing() if vendor else []
    if missing:
        pytest.skip(f"three.js vendor files missing ({', '.join(missing)}): {VENDOR_HINT}")
    return exe


class Page:
    """One page's DevTools session; every message not answering a call is kept in ``events``."""

    def __init__(self, ws_url: str, timeout: float):
        import websocket

        self.ws = websocket.create_connection(ws_url, timeout=timeout, suppress_origin=True)
        self.events: list[dict] = []
        self._id = 0

    def send(self, method: str, params: dict | None = None, timeout: float = 30.0) -> dict:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params or {}}))
        deadline = time.monotonic() + timeout
        while True:
            if time.monotonic() > deadline:
                raise TimeoutError(method)
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self.events.append(msg)

    def wait_event(self, method: str, timeout: float = 30.0) -> dict:
        deadline = time.monotonic() + timeout
        for e in self.events:
            if e.get("method") == method:
                return e
        while time.monotonic() < deadline:
            msg = json.loads(self.ws.recv())
            self.events.append(msg)
            if msg.get("method") == method:
                return msg
        raise TimeoutError(method)

    def evaluate(self, expression: str, timeout: float = 60.0):
        """The value of a JS expression (promises awaited); a thrown exception fails."""
        r = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True, "awaitPromise": True},
                      timeout=timeout)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expression[:80]}: {r['exceptionDetails']}")
        return r["result"].get("value")

    def screenshot(self, clip: dict | None = None):
        """A PNG screenshot as a ``(H, W, 4)`` uint8 array (``clip``: x, y, width, height in CSS px)."""
        import io

        import numpy as np
        from PIL import Image

        params = {"format": "png"}
        if clip:
            params["clip"] = {**clip, "scale": 1}
        data = base64.b64decode(self.send("Page.captureScreenshot", params)["data"])
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGBA"))

    def problems(self, base: str) -> dict[str, list]:
        """Console errors, exceptions, failed or >= 400 requests, and requests that left ``base``."""
        ev = self.events
        errors = [e["params"] for e in ev if e.get("method") == "Runtime.exceptionThrown"]
        errors += [e["params"] for e in ev if e.get("method") == "Runtime.consoleAPICalled"
                   and e["params"].get("type") in ("error", "assert")]
        errors += [e["params"]["entry"] for e in ev if e.get("method") == "Log.entryAdded"
                   and e["params"]["entry"].get("level") == "error"]
        urls = {e["params"]["requestId"]: e["params"]["request"]["url"] for e in ev
                if e.get("method") == "Network.requestWillBeSent"}
        failed = [(urls.get(e["params"]["requestId"]), e["params"].get("errorText"), e["params"].get("canceled"))
                  for e in ev if e.get("method") == "Network.loadingFailed"]
        failed += [(e["params"]["response"]["url"], e["params"]["response"]["status"]) for e in ev
                   if e.get("method") == "Network.responseReceived" and e["params"]["response"]["status"] >= 400]
        requested = [e["params"]["request"]["url"] for e in ev if e.get("method") == "Network.requestWillBeSent"]
        external = [u for u in requested if not (u.startswith(base) or u.startswith("data:"))]
        return {"errors": errors, "failed": failed, "external": external, "requested": requested}


class Browser:
    """``with Browser(tmp_path) as page:`` a headless Chromium (WebGL via SwiftShader) with one
    page whose Page, Runtime, Log and Network domains are enabled."""

    def __init__(self, profile: Path, window: tuple[int, int] = (1200, 800), vendor: bool = True):
        self.exe = require_browser(vendor)
        self.profile = Path(profile)
        self.window = window
        self.proc = None
        self.page: Page | None = None

    def __enter__(self) -> Page:
        try:
            return self._start()
        except BaseException:
            self.__exit__()
            raise

    def _start(self) -> Page:
        port_file = self.profile / "DevToolsActivePort"
        port_file.unlink(missing_ok=True)  # a stale one from an earlier browser on this profile
        self.proc = subprocess.Popen(
            [self.exe, "--headless=new", "--no-sandbox", "--no-first-run", "--disable-extensions",
             "--disable-background-networking", "--disable-sync", "--disable-component-update",
             "--disable-default-apps", *GL_FLAGS, "--remote-debugging-port=0",
             "--remote-debugging-address=127.0.0.1", f"--user-data-dir={self.profile}",
             f"--window-size={self.window[0]},{self.window[1]}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 30
        while not (port_file.is_file() and port_file.read_text().strip()):
            if self.proc.poll() is not None:
                pytest.skip(f"{self.exe} exited with code {self.proc.returncode} before opening its DevTools port")
            if time.monotonic() > deadline:
                raise TimeoutError("chromium did not open its DevTools port")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        targets: list = []
        while not targets:
            if time.monotonic() > deadline:
                raise TimeoutError("no page target")
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                targets = [t for t in json.load(r) if t.get("type") == "page"]
            time.sleep(0.05)
        self.page = Page(targets[0]["webSocketDebuggerUrl"], timeout=60)
        for domain in ("Page", "Runtime", "Log", "Network"):
            self.page.send(f"{domain}.enable")
        return self.page

    def __exit__(self, *_) -> None:
        if self.page is not None:
            self.page.ws.close()
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


def open_viewer(page: Page, url: str, timeout: float = 60.0) -> dict:
    """Navigate to the viewer (forgetting earlier events) and wait until it has loaded its
    material; returns its info()."""
    page.events.clear()
    page.send("Page.navigate", {"url": url})
    page.wait_event("Page.loadEventFired", timeout)
    deadline = time.monotonic() + timeout
    while page.evaluate("typeof window.dualscaleViewer") != "object":
        if time.monotonic() > deadline:
            raise TimeoutError("the viewer module did not start")
        time.sleep(0.1)
    ok = page.evaluate("window.dualscaleViewer.ready", timeout=timeout)
    status = page.evaluate("document.getElementById('status').textContent")
    assert ok, f"the viewer failed: {status}"
    return page.evaluate("window.dualscaleViewer.info()")
