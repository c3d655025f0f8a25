"""The SITL's progress line (`--status`), typed: written by the SITL, read by the fleet harness."""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field


@dataclass(frozen=True)
class SitlStatus:
    """One STATUS line.

    Attributes:
        sim_s / wall_s: simulated and wall time since the clock started, s.
        rtf: simulated over wall time since the clock started (None before it has).
        attached: vehicles a companion has talked to; armed: vehicles armed.
        complete: the recorded mission is complete.
        phases: vehicles per agent phase (launch, stabilise, assemble, transit, hover, land, failed),
            as the agents last reported them over the radio (empty without a radio).
        link_bytes_per_s_per_vehicle: radio bytes received per simulated second and vehicle.
        t_go_s: the earliest transit start the agents have published, mission time, s
            (None before any has; a progress bar's ETA reads it).
        id_conflicts: swarm states the radio refused because another address already
            sends that vehicle id (two agents with one --vehicle-id).
    """

    sim_s: float = 0.0
    wall_s: float = 0.0
    rtf: float | None = None
    attached: int = 0
    armed: int = 0
    complete: bool = False
    phases: tuple[int, ...] = field(default_factory=tuple)
    link_bytes_per_s_per_vehicle: float | None = None
    t_go_s: float | None = None
    id_conflicts: int = 0

    def to_line(self) -> str:
        return "STATUS " + json.dumps(dataclasses.asdict(self))

    @classmethod
    def from_line(cls, line: str) -> "SitlStatus | None":
        """Parse a STATUS line; None if it is not one (or is malformed)."""
        if not line.startswith("STATUS "):
            return None
        try:
            data = json.loads(line[7:])
            names = {f.name for f in dataclasses.fields(cls)}
            kept = {k: v for k, v in data.items() if k in names}
            if "phases" in kept:
                kept["phases"] = tuple(int(x) for x in kept["phases"])
            return cls(**kept)
        except (ValueError, TypeError):
            return None
