"""Per-vehicle maths written once, run interpreted onboard and compiled in simulation.

A function decorated with ``@kernel`` is plain Python in the subset that numba
compiles: scalars, tuples, numpy arrays indexed element by element, ``math``
functions, and calls to other kernels **by bare global name** (``from m import f``,
never ``module.f``). The companion agent runs these functions as they are, so no
JIT compiler sits on a companion computer's import path (numba alone costs about
0.5 s and 100 MB per process). ``sim_bridge.world.jit.compiled`` compiles the very same
function objects for the headless runner and the SITL, where one call covers
forty vehicles and thousands of physics steps. One source, two speeds, no fork.
"""
from __future__ import annotations

from typing import Any, Callable, TypeVar, overload

F = TypeVar("F", bound=Callable)

JIT_OPTIONS_ATTR = "_swarmdrop_jit_options"


@overload
def kernel(fn: F) -> F: ...


@overload
def kernel(fn: None = None, **jit_options: Any) -> Callable[[F], F]: ...


def kernel(fn: F | None = None, **jit_options: Any) -> F | Callable[[F], F]:
    """Mark fn as a kernel; jit_options (e.g. inline="always") go to numba.njit.

    Returns fn itself, unchanged: calling it runs the Python code.
    """

    def mark(f: F) -> F:
        setattr(f, JIT_OPTIONS_ATTR, dict(jit_options))
        return f

    return mark(fn) if fn is not None else mark


def is_kernel(obj) -> bool:
    """True for functions marked with @kernel."""
    return callable(obj) and hasattr(obj, JIT_OPTIONS_ATTR)
