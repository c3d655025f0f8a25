"""Compile companion kernels with numba, for the simulator's hot loops.

``compiled(f)`` returns a numba dispatcher for the @kernel function f. numba
resolves a function's global names when it compiles it, so f is re-created over
a copy of its module's namespace in which every kernel is replaced by its own
compiled twin; kernels call each other by bare name, so the compiled f calls
compiled callees. The companion package never imports numba: this module is the
only bridge, and it lives on the simulator side of the dependency line.
"""
from __future__ import annotations

import sys
import types

from numba import njit

from companion.control.kernel import JIT_OPTIONS_ATTR, is_kernel

_dispatchers: dict = {}
_namespaces: dict[str, dict] = {}


def _namespace(module_name: str) -> dict:
    ns = _namespaces.get(module_name)
    if ns is None:
        # Registered before it is filled: kernels of one module refer to each other,
        # and numba reads the dict only when a dispatcher first compiles.
        ns = _namespaces[module_name] = dict(vars(sys.modules[module_name]))
        for name, value in list(ns.items()):
            if isinstance(value, types.FunctionType) and is_kernel(value):
                ns[name] = compiled(value)
    return ns


def compiled(fn):
    """The numba-compiled twin of the @kernel function fn (cached on disk).

    Raises:
        TypeError: fn is not a @kernel function.
    """
    if not (isinstance(fn, types.FunctionType) and is_kernel(fn)):
        raise TypeError(f"{fn!r} is not a @kernel function")
    disp = _dispatchers.get(fn)
    if disp is None:
        ns = _namespace(fn.__module__)  # may already have created fn's twin
        disp = _dispatchers.get(fn)
        if disp is None:
            clone = types.FunctionType(fn.__code__, ns, fn.__name__, fn.__defaults__, fn.__closure__)
            clone.__qualname__, clone.__module__, clone.__doc__ = fn.__qualname__, fn.__module__, fn.__doc__
            disp = _dispatchers[fn] = njit(cache=True, **getattr(fn, JIT_OPTIONS_ATTR))(clone)
    return disp


def agent_kernels():
    """companion.agent.AgentKernels with every loop compiled (for simulating many vehicles)."""
    from companion.agent import AgentKernels

    base = AgentKernels()
    return AgentKernels(**{name: compiled(getattr(base, name)) for name in AgentKernels.__dataclass_fields__})


def output_kernels():
    """companion.output.OutputKernels with every loop compiled (for simulating many vehicles)."""
    from companion.output import OutputKernels

    base = OutputKernels()
    return OutputKernels(**{name: compiled(getattr(base, name)) for name in OutputKernels.__dataclass_fields__})
