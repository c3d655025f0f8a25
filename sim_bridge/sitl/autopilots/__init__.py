"""The SITL's autopilot behaviours, keyed by the companion dialect's name (see base.py).

Every AutopilotBehaviour subclass registers itself by being defined
(companion.link.registry): the modules of this folder are imported here, and a
behaviour defined elsewhere (a plug-in, a test's toy autopilot) joins as soon as its
module is imported. A third autopilot is a dialect (companion/link/dialects/) and a
behaviour (here): two new files.
"""
from __future__ import annotations

from companion.link.registry import SubclassRegistry
from sim_bridge.sitl.autopilots.base import AutopilotBehaviour, Knobs  # noqa: F401

AUTOPILOTS: SubclassRegistry[AutopilotBehaviour] = SubclassRegistry(AutopilotBehaviour, __name__)
"""name -> behaviour (the companion dialect's names)."""


class UnknownAutopilotBehaviour(LookupError):
    """No SITL behaviour for this autopilot name."""


def autopilot_named(name: str) -> AutopilotBehaviour:
    """The behaviour of the autopilot called name.

    Raises:
        UnknownAutopilotBehaviour: naming the known ones.
    """
    try:
        return AUTOPILOTS[name]
    except KeyError:
        raise UnknownAutopilotBehaviour(f"no SITL autopilot {name!r} (known: {', '.join(sorted(AUTOPILOTS))})") \
            from None
