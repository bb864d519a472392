"""The register map has one source of truth: generated files must match protocol/*.toml."""
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

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
    toml.write_text(toml.read_text().replace("version_minor = 1", "version_minor = 9", 1))
    r = subprocess.run([sys.executable, str(gen), "--check"], capture_output=True, text=True)
    assert r.returncode == 1 and "ds_regmap.h" in r.stderr and "regmap.py" in r.stderr


def _c_header(root: Path = REPO) -> tuple[dict[str, int], list[int]]:
    """The integer #defines of ds_regmap.h and its DS_HR_DEFAULTS table, parsed from the text."""
    header = (root / "firmware/core/include/ds_regmap.h").read_text()
    defines = {m[1]: int(m[2], 0) for m in re.finditer(r"^#define (DS_\w+) (0x[0-9A-Fa-f]+|\d+)u\b", header, re.M)}
    body = re.search(r"DS_HR_DEFAULTS\[DS_HR_COUNT\] = \{(.*?)\};", header, re.S)
    assert body, "ds_regmap.h has no DS_HR_DEFAULTS table"
    table = [int(v, 0) for v in re.findall(r"(0x[0-9A-Fa-f]+|\d+)u,", re.sub(r"/\*.*?\*/", "", body[1]))]
    return defines, table


def _expected_from_toml(root: Path = REPO) -> tuple[int, int, list[int], dict[str, int]]:
    """Counts and reset words worked out here from the toml alone (not through gen.py)."""
    regs = tomllib.loads((root / "protocol/registers.toml").read_text())
    rig = tomllib.loads((root / "protocol/rig.toml").read_text())
    width = {"u16": 1, "u32": 2, "u48": 3, "event": 6}
    named = dict(rig["limits"])
    named["default_parity"] = regs["enums"]["parity"][rig["serial"]["parity"]]
    named["default_stop_bits"] = rig["serial"]["stop_bits"]

    def value(v):
        return v if isinstance(v, int) else named[v]

    def count(space):
        return max(r["addr"] + width[r["type"]] for r in regs[space] if "count" not in r)

    hr = [0] * count("holding")
    defaults = {}
    for r in regs["holding"]:
        if "default" in r:
            v, n = value(r["default"]), width[r["type"]]
            defaults[r["name"]] = v
            for i in range(n):
                hr[r["addr"] + i] = (v >> (16 * (n - 1 - i))) & 0xFFFF
    return count("input"), count("holding"), hr, defaults


def test_c_counts_sizes_and_defaults_come_from_the_toml():
    defines, table = _c_header()
    n_ir, n_hr, hr, defaults = _expected_from_toml()
    assert (defines["DS_IR_COUNT"], defines["DS_HR_COUNT"]) == (n_ir, n_hr) == (31, 18)
    assert table == hr and len(table) == n_hr
    for name, v in defaults.items():
        assert defines[f"DS_HR_{name}_DEFAULT"] == v, name
    regs = tomllib.loads((REPO / "protocol/registers.toml").read_text())
    for name, sv in regs["special"].items():
        assert defines[f"DS_{name}"] == sv["value"]

    # ... and the firmware uses them instead of numbers of its own
    core_h = (REPO / "firmware/core/include/ds_core.h").read_text()
    assert re.search(r"uint16_t hr\[DS_HR_COUNT\];", core_h), "hr[] must be sized by DS_HR_COUNT"
    assert not re.search(r"\b(hr|ir)\[\d+\]", core_h)
    core_c = (REPO / "firmware/core/src/core.c").read_text()
    assert "DS_HR_DEFAULTS" in core_c
    assert not re.search(r"hr\[[^\]]+\]\s*=", core_c), "core.c must not assign register defaults by hand"
    for path in [*(REPO / "firmware/core").rglob("*.[ch]"), *(REPO / "firmware/targets").rglob("*.[ch]")]:
        if path.name == "ds_regmap.h":
            continue
        text = path.read_text()
        for name in ("DS_HR_COUNT", "DS_IR_COUNT", "DS_HR_DEFAULTS", *(f"DS_{k}" for k in regs["special"])):
            assert not re.search(rf"#define\s+{name}\b", text), f"{path.relative_to(REPO)} defines {name}"


def test_check_fails_when_the_header_is_edited_by_hand(tmp_path):
    root = _copy_tree(tmp_path)
    gen = root / "protocol/gen.py"
    header = root / "firmware/core/include/ds_regmap.h"
    original = header.read_text()
    for old, new in (("#define DS_HR_COUNT 18u", "#define DS_HR_COUNT 32u"),
                     ("0x8000u, /* 6 MANUAL_INTENSITY", "0x1000u, /* 6 MANUAL_INTENSITY")):
        assert old in original
        header.write_text(original.replace(old, new))
        r = subprocess.run([sys.executable, str(gen), "--check"], capture_output=True, text=True)
        assert r.returncode == 1 and "ds_regmap.h" in r.stderr and "regmap.py" not in r.stderr
    assert subprocess.run([sys.executable, str(gen)], capture_output=True).returncode == 0
    assert header.read_text() == original


@pytest.mark.parametrize("old,new,why", [
    ('range = [0, 65535]\ndefault = 32768\n', 'range = [0, 1000]\ndefault = 32768\n', "outside its range"),
    ('name = "MANUAL_INTENSITY"\naddr = 6\n', 'name = "MANUAL_INTENSITY"\naddr = 5\n', "overlaps"),
])
def test_gen_refuses_a_map_the_firmware_cannot_implement(tmp_path, old, new, why):
    root = _copy_tree(tmp_path)
    toml = root / "protocol/registers.toml"
    text = toml.read_text()
    assert text.count(old) == 1
    toml.write_text(text.replace(old, new))
    r = subprocess.run([sys.executable, str(root / "protocol/gen.py")], capture_output=True, text=True)
    assert r.returncode != 0 and why in r.stderr, r.stderr


NEW_REGISTER = """
[[holding]]
name = "TEST_EXTRA"
addr = 18
type = "u16"
access = "rw"
range = [0, 65535]
default = 4321
doc = "A register added by the test."
"""

PROBE = r"""
#include <stdio.h>
#include "ds_core.h"
static ds_core_t core;
int main(void)
{
    uint8_t req[8] = {1, 0x03, (uint8_t)(DS_HR_TEST_EXTRA >> 8), (uint8_t)DS_HR_TEST_EXTRA, 0, 1, 0, 0};
    uint8_t resp[DS_RTU_MAX_ADU];
    ds_core_init(&core, NULL, 1, 0);
    uint16_t crc = ds_crc16(req, 6);
    req[6] = (uint8_t)(crc & 0xFFu);
    req[7] = (uint8_t)(crc >> 8);
    size_t n = ds_core_handle_frame(&core, req, sizeof req, resp, 0);
    printf("%u %u %u\n", (unsigned)(sizeof core.hr / sizeof core.hr[0]), (unsigned)n,
           (unsigned)(resp[3] << 8 | resp[4]));
    return 0;
}
"""


def test_a_new_register_with_a_default_needs_no_c_edit(tmp_path):
    """Add a holding register to registers.toml only: the count, the array, the reset table and
    the mapping all follow, and the unchanged core serves the default over Modbus."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    root = _copy_tree(tmp_path)
    toml = root / "protocol/registers.toml"
    toml.write_text(toml.read_text().replace("\n[step_table]", NEW_REGISTER + "\n[step_table]", 1))
    r = subprocess.run([sys.executable, str(root / "protocol/gen.py")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    defines, table = _c_header(root)
    n_ir, n_hr, hr, _ = _expected_from_toml(root)
    assert defines["DS_HR_COUNT"] == n_hr == 19 and table == hr and table[18] == 4321

    inc = root / "firmware/core/include"  # ds_core.h includes "ds_regmap.h" from its own folder
    for h in ("ds_core.h", "ds_hal.h"):
        shutil.copy(REPO / "firmware/core/include" / h, inc / h)
    (tmp_path / "probe.c").write_text(PROBE)
    srcs = sorted(str(p) for p in (REPO / "firmware/core/src").glob("*.c"))
    exe = tmp_path / "probe"
    flags = "-std=c11 -Wall -Wextra -Wshadow -Wconversion -Wno-sign-conversion -Werror -O1".split()
    r = subprocess.run([cc, *flags, f"-I{inc}", f"-I{REPO / 'firmware/core/src'}", str(tmp_path / "probe.c"),
                        *srcs, "-o", str(exe)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    out = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["19", "7", "4321"]  # hr[19]; a 7-byte FC 03 answer carrying the default


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
