"""The layering of docs/ARCHITECTURE.md, checked on the source: no production stage imports the
virtual rig, each layer imports only the layers below it, and no import cycles between modules."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "host" / "dualscale"

# layer of each top-level part (a module may import its own layer and lower ones)
LAYER = {"errors": 0, "formats": 1, "geometry": 1, "bsdf": 1, "protocol": 1, "progress": 1, "threads": 1, "engine": 1, "rig": 2,
         "capture": 3, "calib": 3,
         "fit": 4, "propagate": 5, "adaptive": 5, "tile": 6, "export": 6, "report": 6, "pipeline": 7, "view": 7, "batch": 7.5,
         "cli": 8, "sim": 9}


def _module(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Absolute dualscale modules imported anywhere in ``path`` (relative imports resolved)."""
    mod = _module(path)
    pkg = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("dualscale")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.startswith("dualscale"):
                out.add(target)
                out |= {f"{target}.{a.name}" for a in node.names}
    return out


def _part(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


FILES = sorted(PKG.rglob("*.py"))


def test_layers_are_known():
    unknown = {p.relative_to(PKG).parts[0].removesuffix(".py") for p in FILES} - set(LAYER) - {"__init__"}
    assert not unknown, f"add {unknown} to docs/ARCHITECTURE.md and LAYER"


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(PKG)))
def test_imports_follow_the_layers(path):
    own = _part(_module(path))
    if own in ("", "__init__"):
        return
    bad = sorted(m for m in _imports(path) if _part(m) in LAYER and LAYER[_part(m)] > LAYER[own]
                 and not (own == "cli" and _part(m) == "sim"))
    assert not bad, f"{path.relative_to(PKG)} ({own}, layer {LAYER[own]}) imports a later layer: {bad}"


def test_no_production_module_imports_the_virtual_rig():
    leaks = [str(p.relative_to(PKG)) for p in FILES if _part(_module(p)) not in ("sim", "cli")
             and any(_part(m) == "sim" for m in _imports(p))]
    assert not leaks


def test_no_import_cycles_between_modules():
    mods = {_module(p): p for p in FILES}
    graph = {m: {i for i in _imports(p) if i in mods and i != m} for m, p in mods.items()}
    # a package's __init__ re-exporting its modules is not a cycle of the modules themselves
    graph = {m: {i for i in deps if not (m.startswith(i + ".") or i.startswith(m + "."))} for m, deps in graph.items()}
    seen, stack, cycles = set(), [], []

    def visit(m):
        if m in stack:
            cycles.append(stack[stack.index(m):] + [m])
            return
        if m in seen:
            return
        seen.add(m)
        stack.append(m)
        for d in graph[m]:
            visit(d)
        stack.pop()

    for m in graph:
        visit(m)
    assert not cycles, f"import cycles: {cycles[:3]}"
