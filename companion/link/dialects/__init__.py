"""Autopilot dialects, picked from HEARTBEAT.autopilot (see base.py).

Every module in this folder is imported and every AutopilotDialect subclass it
defines is registered, so a third autopilot is one new file here.
"""
from __future__ import annotations

import importlib
import pkgutil

from companion.link.dialects.base import AutopilotDialect, HeartbeatState, Mode  # noqa: F401


class UnknownAutopilot(LookupError):
    """No dialect for this HEARTBEAT.autopilot value or name."""


def _registry() -> dict[str, AutopilotDialect]:
    found: dict[str, AutopilotDialect] = {}
    for info in pkgutil.iter_modules(__path__):
        if info.name != "base":
            importlib.import_module(f"{__name__}.{info.name}")
    stack = list(AutopilotDialect.__subclasses__())
    while stack:
        cls = stack.pop()
        stack += cls.__subclasses__()
        if not getattr(cls, "__abstractmethods__", None):
            found[cls.name] = cls()
    return found


DIALECTS = _registry()


def dialect_named(name: str) -> AutopilotDialect:
    """Raises UnknownAutopilot, naming the known ones."""
    try:
        return DIALECTS[name]
    except KeyError:
        raise UnknownAutopilot(f"unknown autopilot dialect {name!r}; known: {', '.join(sorted(DIALECTS))}") from None


def dialect_for_autopilot(autopilot_id: int) -> AutopilotDialect:
    """The dialect of a HEARTBEAT.autopilot value. Raises UnknownAutopilot."""
    for d in DIALECTS.values():
        if d.autopilot_id == autopilot_id:
            return d
    raise UnknownAutopilot(f"no dialect for HEARTBEAT.autopilot={autopilot_id} "
                           f"(known: {', '.join(f'{d.name}={d.autopilot_id}' for d in DIALECTS.values())})")
