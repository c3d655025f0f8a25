"""`swarmdrop agent` as the onboard install runs it: without the packages that only the
extras bring (pyproject.toml: sim, console, sweep) and without the simulators.

A child interpreter whose imports of those packages fail as they would where they are not
installed (`pip install swarmdrop` alone), so that every test flying the agent through
`lean_agent_cmd` also shows that the onboard install is enough to fly.
"""
from __future__ import annotations

import sys

EXTRAS_ONLY = ("scipy", "numba", "llvmlite", "matplotlib", "tqdm", "pymavlink", "aiohttp", "dask", "distributed")
"""Top-level packages an onboard install does not have (those only the extras bring)."""

_PRELUDE = """
import importlib.abc, sys
BLOCKED = {blocked!r}
class _NotInstalled(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}} (not importable here)", name=name)
        return None
sys.meta_path.insert(0, _NotInstalled())
from swarmdrop.cli import main
sys.exit(main(sys.argv[1:]))
"""


def lean_cmd(*args: str, blocked: tuple[str, ...] = EXTRAS_ONLY) -> list[str]:
    """`swarmdrop ARGS...` in an interpreter where the `blocked` packages cannot be imported."""
    return [sys.executable, "-c", _PRELUDE.format(blocked=blocked), *args]


def lean_agent_cmd(*args: str) -> list[str]:
    """`swarmdrop agent ARGS...` without the extras' packages, nor the simulators' (which the
    agent must not import either, although the install has them)."""
    return lean_cmd("agent", *args, blocked=(*EXTRAS_ONLY, "sim_bridge"))
