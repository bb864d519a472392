"""Fixtures of the export tests: the external validators, skipped with a reason when absent.

* ``node_exe``: the ``node`` executable (skip when Node is not installed).
* ``node_package``: ``node_package("name")`` -> the repository's ``node_modules/name`` folder
  (skip when ``make node`` has not installed it).
* ``gltf_validator``: a :class:`GltfValidator` running the Khronos glTF-Validator (npm
  ``gltf-validator``, through ``tests/export/gltf_validate.mjs``) on a ``.gltf`` or ``.glb``.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
NODE_MODULES = REPO / "node_modules"
GLTF_VALIDATE = Path(__file__).resolve().parent / "gltf_validate.mjs"


@pytest.fixture(scope="session")
def node_exe() -> str:
    exe = shutil.which("node")
    if exe is None:
        pytest.skip("Node.js is not installed (`make deps` installs Debian's nodejs)")
    return exe


@pytest.fixture(scope="session")
def node_package(node_exe):
    """``node_package(name)`` -> ``node_modules/<name>``; skips the test when it is missing."""

    def find(name: str) -> Path:
        path = NODE_MODULES / name
        if not (path / "package.json").is_file():
            pytest.skip(f"npm package {name!r} is not installed in {NODE_MODULES} (run `make node`)")
        return path

    return find


class GltfValidator:
    """The Khronos glTF-Validator under Node.

    :meth:`report` returns the validator's JSON report (``issues.numErrors``, ``numWarnings``,
    ``messages`` with ``code``/``severity`` (0 error, 1 warning, 2 info, 3 hint)/``pointer``/
    ``message``; ``info.resources`` describes the buffers and images it loaded).
    :meth:`check` asserts zero errors and no warning outside ``allowed_warnings`` (codes), and
    returns the report."""

    def __init__(self, node: str, version: str) -> None:
        self.node = node
        self.version = version

    def report(self, path: str | Path) -> dict:
        proc = subprocess.run([self.node, str(GLTF_VALIDATE), str(path)], cwd=REPO,
                              capture_output=True, text=True, timeout=120)
        if proc.returncode != 0:
            raise AssertionError(f"glTF-Validator could not read {path}: {proc.stderr.strip()}")
        return json.loads(proc.stdout)

    def check(self, path: str | Path, allowed_warnings: tuple[str, ...] = ()) -> dict:
        rep = self.report(path)
        msgs = rep["issues"]["messages"]
        bad = [m for m in msgs if m["severity"] == 0
               or (m["severity"] == 1 and m["code"] not in allowed_warnings)]
        if bad or rep["issues"]["numErrors"]:
            lines = "\n".join(f"  [{m['severity']}] {m['code']} {m.get('pointer', '')}: {m['message']}"
                              for m in bad)
            raise AssertionError(f"glTF-Validator {self.version} on {Path(path).name}: "
                                 f"{rep['issues']['numErrors']} errors, "
                                 f"{rep['issues']['numWarnings']} warnings\n{lines}")
        return rep


@pytest.fixture(scope="session")
def gltf_validator(node_exe, node_package) -> GltfValidator:
    pkg = node_package("gltf-validator")
    version = json.loads((pkg / "package.json").read_text())["version"]
    return GltfValidator(node_exe, version)
