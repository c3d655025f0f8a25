"""The onboard install: `pip install swarmdrop` brings only what `swarmdrop agent` imports;
the simulators, the console and the sweeps come with extras, and a command whose extra is
missing says which and how to install it (exit 2), never a traceback.

(tests/test_agent_node.py and tests/test_identity.py fly the agent in an interpreter where
the extras' packages cannot be imported: tests/lean_agent.py.)
"""
from __future__ import annotations

import ast
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from lean_agent import EXTRAS_ONLY, lean_cmd

from swarmdrop.cli import EXTRAS

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
IMPORT_TO_DIST = {"yaml": "pyyaml"}
"""Import names that differ from their distribution's name."""


def _dist(requirement: str) -> str:
    return re.split(r"[<>=!~\[; ]", requirement, maxsplit=1)[0].lower()


def _third_party_imports(package: Path) -> set[str]:
    """Top-level names of every module imported anywhere in package (also inside functions),
    less the standard library and this project's packages."""
    names: set[str] = set()
    for path in package.rglob("*.py"):
        if path.name == "generate.py":  # the dialect generator: a development tool that needs pymavlink
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n not in ("companion", "swarmdrop", "sim_bridge")}


def test_the_base_install_is_what_the_agent_imports_and_nothing_heavy():
    base = {_dist(r) for r in PYPROJECT["project"]["dependencies"]}
    used = {IMPORT_TO_DIST.get(n, n) for n in _third_party_imports(ROOT / "companion")}
    assert used <= base, f"companion/ imports {sorted(used - base)}, which `pip install swarmdrop` does not bring"
    assert base == {"numpy", "pyyaml", "pydantic", "fastcrc", "pymap3d", "uvloop"}
    assert not base & {"scipy", "numba", "matplotlib", "tqdm", "pymavlink", "aiohttp", "dask"}


def test_every_extras_package_is_in_an_extra_and_make_installs_them():
    extras = PYPROJECT["project"]["optional-dependencies"]
    assert {_dist(r) for r in extras["sim"]} == {"scipy", "numba", "matplotlib", "tqdm", "pymavlink"}
    assert {_dist(r) for r in extras["console"]} == {"aiohttp", "scipy"}
    assert "dask" in {_dist(r) for r in extras["sweep"]}
    for extra, packages in EXTRAS.items():  # what the CLI checks for is what pyproject installs
        assert {_dist(r) for r in extras[extra]} == set(packages), extra
    blocked = set(EXTRAS_ONLY) - {"llvmlite", "distributed"}  # (these come with numba and dask)
    in_extras = {_dist(r) for reqs in extras.values() for r in reqs}
    assert blocked <= in_extras
    make = (ROOT / "Makefile").read_text()
    assert '-e ".[sim,console,sweep,test]"' in make  # make demo / make test: everything


@pytest.mark.timeout(60)
@pytest.mark.parametrize("argv, extra", [
    (["simulate", "configs/small_6.yaml"], "sim"),
    (["run", "configs/small_6.yaml"], "sim"),
    (["sitl", "--vehicles", "2"], "sim"),
    (["sweep", "configs/small_6.yaml", "--seeds", "2"], "sim"),
    (["console", "--mission", "configs/small_6.yaml"], "console"),
])
def test_a_command_whose_extra_is_missing_says_how_to_install_it(argv, extra):
    proc = subprocess.run(lean_cmd(*argv), cwd=ROOT, capture_output=True, text=True, timeout=50)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    extras = "sim,sweep" if argv[0] == "sweep" else extra
    assert f"pip install 'swarmdrop[{extras}]'" in proc.stderr and f"pip install '.[{extras}]'" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.timeout(60)
def test_help_and_the_agent_work_without_the_extras():
    for argv in (["--help"], ["agent", "--help"], ["run", "--help"]):
        proc = subprocess.run(lean_cmd(*argv), cwd=ROOT, capture_output=True, text=True, timeout=50)
        assert proc.returncode == 0, (argv, proc.stderr)
        assert "usage: swarmdrop" in proc.stdout
