"""``dualscale view`` without a browser: locating the export and the run's data, the refusals,
the HTTP routes, the LED side-by-side images, and the command (serves, --no-browser, Ctrl-C)."""

from __future__ import annotations

import http.client
import io
import json
import os
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from .folders import CAPTURE_GAIN, LEDS, export_folder, maps_folder, run_folder, write_export_json

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    return run_folder(tmp_path_factory.mktemp("view") / "RUN")


@pytest.fixture(scope="module")
def out(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("view_out")
    return export_folder(tmp / "OUT", maps_folder(tmp / "maps", "plain"), ("glb", "gltf"))


def _get(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=60) as r:
            return r.status, r.headers["Content-Type"], r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers["Content-Type"], e.read()


def _png(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), np.float64) / 255.0


# ---------------------------------------------------------------------------------------------
# locating what to show

def test_locate_run(run):
    from dualscale.view import locate

    s = locate(run)
    doc = s.to_json()
    assert s.kind == "run" and s.maps == run / "fit" / "maps" and s.dataset == run / "calibrate" / "dataset"
    assert [e["key"] for e in doc["exports"]] == ["micro"]
    e = doc["exports"][0]
    assert e["url"] == "files/micro/glb/swatch.glb" and e["repeat_mm"] == pytest.approx([0.64, 0.64])
    assert doc["side_by_side"] and doc["no_capture"] is None
    assert [d["id"] for d in doc["leds"]] == [k for k, _, _ in LEDS]
    led7 = next(d for d in doc["leds"] if d["id"] == 7)
    assert led7["theta_deg"] == pytest.approx(55.0, abs=0.01) and led7["phi_deg"] == pytest.approx(140.0, abs=0.01)


def test_locate_export_prefers_glb_and_says_why_no_capture(out):
    from dualscale.view import locate

    s = locate(out)
    doc = s.to_json()
    assert s.kind == "export" and doc["exports"][0]["url"] == "files/export/glb/swatch.glb"
    assert not doc["side_by_side"] and "not a digitize run" in doc["no_capture"] and doc["leds"] == []


def test_locate_gltf_only(tmp_path):
    from dualscale.view import locate

    out = export_folder(tmp_path / "OUT", maps_folder(tmp_path / "maps", "plain"), ("gltf",))
    assert locate(out).exports[0].gltf == "gltf/swatch.gltf"


@pytest.mark.parametrize("case", ["exr_only", "empty_dir", "run_without_export"])
def test_refuses_a_folder_without_gltf(tmp_path, case, capsys):
    from dualscale.cli import main
    from dualscale.errors import InputError
    from dualscale.view import locate

    path = tmp_path / "X"
    if case == "exr_only":
        write_export_json(path, {"exr": ["exr/x_base_color.exr"]})
        want = "lists no glTF or GLB file; run `dualscale export MAPS -o"
    elif case == "empty_dir":
        path.mkdir()
        want = "neither an export folder (export.json) nor a digitize run (run.json)"
    else:
        path = run_folder(path, exports=())
        want = "the run has no glTF or GLB export"
    with pytest.raises(InputError, match=None) as e:
        locate(path)
    assert want in str(e.value)
    if _cli_has_view():
        assert main(["view", str(path), "--no-browser"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and want in err and "dualscale view: error:" in err


def test_refuses_a_listed_file_that_is_missing(tmp_path):
    from dualscale.errors import FormatError
    from dualscale.view import locate

    write_export_json(tmp_path / "X", {"glb": ["glb/x.glb"]})
    with pytest.raises(FormatError, match=r"formats.glb lists glb/x.glb, which is missing"):
        locate(tmp_path / "X")


# ---------------------------------------------------------------------------------------------
# the server

def test_routes(run):
    from dualscale.view import ViewerServer, locate, vendor_missing

    if vendor_missing():
        pytest.skip("three.js vendor files missing: run `make node`")
    with ViewerServer(locate(run)) as v:
        base = v.url
        assert base.startswith("http://127.0.0.1:")
        status, ctype, body = _get(base)
        assert status == 200 and ctype.startswith("text/html") and b'type="importmap"' in body
        # every module the page imports is served as JavaScript
        for path in ("viewer.js", "vendor/three.module.js", "vendor/three.core.js",
                     "vendor/addons/loaders/GLTFLoader.js", "vendor/addons/controls/OrbitControls.js",
                     "vendor/addons/utils/BufferGeometryUtils.js"):
            status, ctype, _ = _get(base + path)
            assert status == 200 and ctype.startswith("text/javascript"), path
        status, _, body = _get(base + "scene.json")
        assert status == 200 and json.loads(body)["exports"][0]["key"] == "micro"
        status, ctype, body = _get(base + "files/micro/glb/swatch.glb")
        assert status == 200 and ctype == "model/gltf-binary" and body[:4] == b"glTF"
        # nothing outside the served folders, however the path is spelled
        port = int(base.rstrip("/").rsplit(":", 1)[1])
        for raw in ("/files/micro/../../run.json", "/files/micro/%2e%2e/%2e%2e/run.json", "/../scene.py",
                    "/files/nope/glb/swatch.glb", "/vendor/../../scene.py", "/nothing.js"):
            c = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
            c.request("GET", raw)
            r = c.getresponse()
            assert r.status == 404, (raw, r.status)
            c.close()
        status, _, body = _get(base + "api/led/5.json")
        assert status == 400 and "LED 5 is not in the dataset" in json.loads(body)["error"]


def test_led_endpoint_captured_and_rendered(run):
    """Our renderer's image is the fitted maps under the dataset's LED direction with its
    analyser weights; the fixture's captures are that render x 1.1 (+1 % noise)."""
    import torch

    from dualscale.bsdf import evaluate
    from dualscale.formats.maps import load_maps
    from dualscale.view import ViewerServer, locate

    maps, _ = load_maps(run / "fit" / "maps")
    with ViewerServer(locate(run)) as v:
        status, _, body = _get(v.url + "api/led/7.json")
        info = json.loads(body)
        assert status == 200 and info["led"] == 7 and info["w_s"] == 1.0  # the P0 image (specular passed)
        assert info["theta_deg"] == pytest.approx(55.0, abs=1e-3) and info["size"] == [64, 64]
        assert info["rel_error"] == pytest.approx(1 - 1 / CAPTURE_GAIN, abs=0.01)
        pair = v.leds.pair(7)
        want = evaluate(maps, torch.tensor([pair.dir]), torch.tensor([0.0, 0.0, 1.0]), w_s=1.0, w_p=0.0,
                        diffuse_weight=0.5)[0].numpy()
        np.testing.assert_allclose(pair.rendered, np.minimum(want, 2.0), rtol=1e-5, atol=1e-7)
        imgs = {}
        for which in ("captured", "rendered"):
            status, ctype, body = _get(v.url + info[which])
            assert status == 200 and ctype == "image/png"
            imgs[which] = _png(body)
        assert imgs["captured"].shape == (64, 64, 3)
        # one exposure for both: the capture is brighter by the gain (sRGB 8-bit, away from clipping)
        lin = {k: np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4) for k, x in imgs.items()}
        ok = (lin["captured"] < 0.95) & (lin["rendered"] > 0.05)
        ratio = np.median(lin["captured"][ok] / lin["rendered"][ok])
        assert ratio == pytest.approx(CAPTURE_GAIN, rel=0.03)


def test_led_endpoint_absent_for_an_export_folder(out):
    from dualscale.view import ViewerServer, locate

    with ViewerServer(locate(out)) as v:
        status, _, body = _get(v.url + "api/led/0.json")
        assert status == 404 and "not a digitize run" in json.loads(body)["error"]


# ---------------------------------------------------------------------------------------------
# the command

def _cli_has_view() -> bool:
    import argparse

    from dualscale.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return "view" in sub.choices


# runs `dualscale view ARGS` through the console script's entry point; until cli/__init__.py
# registers the command, the test registers it the same way (cli.view.register)
_RUNNER = """
import argparse, sys
import dualscale.cli as cli
from dualscale.cli.view import register
_build = cli.build_parser
def build_parser():
    p = _build()
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    if "view" not in sub.choices:
        register(sub)
    return p
cli.build_parser = build_parser
sys.argv = ["dualscale", "view"] + sys.argv[1:]
cli.run()
"""


def test_command_serves_the_led_side_by_side_and_stops_on_ctrl_c(run):
    """`dualscale view RUN --no-browser --led 3` prints the URL, serves the page and LED 3's
    captured and rendered PNGs, and exits 130 without a traceback on SIGINT."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-c", _RUNNER, str(run), "--no-browser", "--led", "3"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)
    try:
        line = proc.stdout.readline()
        assert "dualscale view: serving" in line, (line, proc.stderr.read() if proc.poll() is not None else "")
        url = line.split(" at ")[1].split()[0]
        assert url.startswith("http://127.0.0.1:") and url.endswith("/?led=3")
        base = url.split("?")[0]
        status, _, body = _get(base)
        assert status == 200 and b"dualscale view" in body
        info = json.loads(_get(base + "api/led/3.json")[2])
        assert info["led"] == 3
        for which in ("captured", "rendered"):
            status, ctype, body = _get(base + info[which])
            assert status == 200 and ctype == "image/png" and _png(body).mean() > 0.02
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert proc.returncode == 130
    assert "Traceback" not in err and "error" not in err, err


def test_command_refuses_an_unknown_led(run):
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", _RUNNER, str(run), "--no-browser", "--led", "5"],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 2 and "--led 5: the dataset" in r.stderr and r.stdout == ""
    assert time.monotonic() - t0 < 60
