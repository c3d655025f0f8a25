"""Autopilot dialects, picked from HEARTBEAT.autopilot (see base.py).

Every AutopilotDialect subclass is registered by being defined (companion.link.registry):
the modules of this folder are imported here, and a dialect defined elsewhere (a
plug-in, a test's toy autopilot) joins as soon as its module is imported. A third
autopilot is one new file, here or anywhere.
"""
from __future__ import annotations

from companion.link.dialects.base import AutopilotDialect, HeartbeatState, Mode  # noqa: F401
from companion.link.registry import SubclassRegistry


class UnknownAutopilot(LookupError):
    """No dialect for this HEARTBEAT.autopilot value or name."""


DIALECTS: SubclassRegistry[AutopilotDialect] = SubclassRegistry(AutopilotDialect, __name__, unique=("autopilot_id",))
"""name -> dialect; names and HEARTBEAT.autopilot values are unique."""


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
