"""The register map has one source of truth: generated files must match protocol/*.toml."""
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
GENERATED = ["firmware/core/include/ds_regmap.h", "host/dualscale/protocol/regmap.py",
             "firmware/tests/ds_vectors.h", "protocol/PROTOCOL.md"]


def _copy_tree(tmp: Path) -> Path:
    for rel in ["protocol/gen.py", "protocol/registers.toml", "protocol/rig.toml",
                "protocol/vectors.toml", *GENERATED]:
        src = REPO / rel
        if src.exists():
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src, tmp / rel)
    return tmp


def test_generated_files_are_fresh():
    r = subprocess.run([sys.executable, str(REPO / "protocol/gen.py"), "--check"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_check_fails_when_the_toml_changes(tmp_path):
    root = _copy_tree(tmp_path)
    gen = root / "protocol/gen.py"
    assert subprocess.run([sys.executable, str(gen), "--check"]).returncode == 0
    toml = root / "protocol/registers.toml"
    toml.write_text(toml.read_text().replace("version_minor = 0", "version_minor = 9", 1))
    r = subprocess.run([sys.executable, str(gen), "--check"], capture_output=True, text=True)
    assert r.returncode == 1 and "ds_regmap.h" in r.stderr and "regmap.py" in r.stderr


def test_python_and_c_agree_on_every_address():
    from dualscale.protocol import regmap as rm

    header = (REPO / "firmware/core/include/ds_regmap.h").read_text()
    defines = {}
    for line in header.splitlines():
        parts = line.split()
        if line.startswith("#define DS_") and len(parts) >= 3 and parts[2][0].isdigit():
            defines[parts[1]] = int(parts[2].rstrip("u"), 0)
    for reg in rm.REGISTERS:
        tag = "IR" if reg.space == "input" else "HR"
        assert defines[f"DS_{tag}_{reg.name}"] == reg.addr
    assert defines["DS_N_LEDS"] == rm.N_LEDS == sum(rm.DOME_COUNTS) == 127
    for e in rm.Error:
        assert defines[f"DS_ERR_{e.name}"] == e.value


def test_vectors_toml_matches_its_generator():
    """vectors.toml is derived from the spec by protocol/make_vectors.py; it must not drift."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_vectors", REPO / "protocol/make_vectors.py")
    mv = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mv)
    assert mv.render() == (REPO / "protocol/vectors.toml").read_text(), "run protocol/make_vectors.py"
