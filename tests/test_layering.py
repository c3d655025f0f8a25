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
    f.write_text("def f():\n    from sim_bridge.world.physics import Physics\n    import numba\n")
    assert [m for _, m in _imports(f)] == ["sim_bridge.world.physics", "numba"]


# ---------------------------------------------------------------------------- sim_bridge's layers
LAYERS = {"world": 0, "scenario": 1, "reports": 2, "sitl": 3, "runs": 4}
"""sim_bridge's parts, lowest first: a module may import its own part and those below it
(world <- scenario <- reports <- sitl <- runs; the SITL records with reports/, and no part
but the harnesses imports a harness)."""


def _part(module: str) -> str | None:
    """The layer of a sim_bridge module name ("sim_bridge.sitl.server" -> "sitl")."""
    bits = module.split(".")
    if bits[0] != "sim_bridge" or len(bits) < 2:
        return None
    return bits[1] if bits[1] in LAYERS else "root"


def _sim_modules() -> dict[str, Path]:
    out = {}
    for p in sorted((ROOT / "sim_bridge").rglob("*.py")):
        rel = p.relative_to(ROOT).with_suffix("")
        name = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        out[name] = p
    return out


def _resolve(module: str, known: dict[str, Path]) -> str | None:
    """The sim_bridge module an import names (a `from pkg import mod` names the package)."""
    while module and module not in known:
        module = module.rpartition(".")[0]
    return module or None


def test_sim_bridge_parts_import_only_downwards():
    known = _sim_modules()
    bad = []
    for name, path in known.items():
        mine = _part(name)
        if mine in (None, "root"):
            continue
        for line, mod in _imports(path):
            theirs = _part(mod)
            if theirs in (None, "root"):
                continue
            if LAYERS[theirs] > LAYERS[mine]:
                bad.append(f"{path.relative_to(ROOT)}:{line}: {mine} imports {mod} ({theirs} is above it)")
    assert not bad, "\n".join(bad)


def test_no_import_circles_in_sim_bridge():
    """No module reaches itself through imports (at any depth, also imports inside functions)."""
    known = _sim_modules()
    graph = {name: {r for _, mod in _imports(path) if (r := _resolve(mod, known)) and r != name and
                    not (name.startswith(r + ".") and known[r].name == "__init__.py")}
             for name, path in known.items()}
    index, low, stack, on, cycles, counter = {}, {}, [], set(), [], [0]

    def strong(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    assert not cycles, f"import circles: {cycles}"
