"""Dependency direction: the onboard package never reaches into the simulator."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEAVY_FOR_ONBOARD = ("sim_bridge", "numba", "scipy", "matplotlib", "tqdm")


def _imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module))
    return out


def test_companion_never_imports_the_simulator_or_heavy_packages():
    """Every import statement in companion/, at any depth (also inside functions)."""
    bad = [f"{p.relative_to(ROOT)}:{line}: import {mod}"
           for p in sorted((ROOT / "companion").rglob("*.py"))
           for line, mod in _imports(p)
           if mod.split(".")[0] in HEAVY_FOR_ONBOARD]
    assert not bad, "companion/ must not import these:\n" + "\n".join(bad)


def test_the_layering_check_sees_a_wrong_way_import(tmp_path):
    """The scanner itself: a planted wrong-way import is found."""
    f = tmp_path / "bad.py"
    f.write_text("def f():\n    from sim_bridge.physics import Physics\n    import numba\n")
    assert [m for _, m in _imports(f)] == ["sim_bridge.physics", "numba"]
