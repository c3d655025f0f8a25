"""The flight phases of a vehicle as its agent sees them (docs/agent.md, "Phases"): the enum
the swarm link carries and the recorder logs, and the plain-int lookups the per-tick code
uses. Its own module so that the agent and its avoidance rules (companion.avoidance) share
it without importing each other."""
from __future__ import annotations

from enum import IntEnum

import numpy as np


class Phase(IntEnum):
    """Flight phase of one vehicle as its agent sees it; the order is the order of a
    normal flight, FAILED last (table in docs/agent.md, "Phases"). The value is what the
    swarm link carries and the recorder logs (int8); ASSEMBLE, TRANSIT and HOVER are the
    formation phases (FORMATION_PHASES)."""

    LAUNCH = 0
    STABILISE = 1
    ASSEMBLE = 2
    TRANSIT = 3
    HOVER = 4
    LAND = 5
    FAILED = 6


FORMATION_PHASES = (Phase.ASSEMBLE, Phase.TRANSIT, Phase.HOVER)
# Plain ints for the per-tick code: IntEnum attribute access costs ~1 us each.
_LAUNCH, _STABILISE, _ASSEMBLE, _TRANSIT, _HOVER, _LAND, _FAILED = (int(p) for p in Phase)
IN_FORMATION = np.isin(np.arange(len(Phase)), [int(p) for p in FORMATION_PHASES])  # lookup by phase value
