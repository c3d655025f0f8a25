"""The scenario's `commands:` schedule: entries validated at load, checked against the
mission, and dry-run through a CommandSource.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Annotated, Literal

from pydantic import Field, model_validator
from pydantic.dataclasses import dataclass as config_dataclass

from companion.commands.plan import PLAN_WAYPOINTS_MAX, CommandError
from companion.commands.source import CommandSource
from companion.config import STRICT
from companion.control.shapes import FormationSpec, Shape
from companion.mission import Mission, Vec3

Vehicle = Annotated[int, Field(ge=1)]


@config_dataclass(config=STRICT)
class CommandEntry:
    """One command of a scenario's `commands:` schedule (docs/swarm.md, "Swarm commands").

    t_s is the mission time at which the command is issued (it applies a lead later). Which
    parameters a kind takes:

    | kind | parameters |
    |---|---|
    | hold, resume, rtl, abort | none |
    | goto | waypoints_ned_m (1 to 7), speed_mps (default: the mission's transit speed) |
    | formation | any of shape, radius_m, spacing_m, rotation_deg (the others keep their value) |
    | exclude | vehicles (1-based), land (default false: they hold where they are) |
    | rejoin | vehicles |
    | land | vehicles (default: all) |

    rotation_deg is the bearing of the shape's forward axis from north (companion.control.shapes).

    Raises:
        pydantic.ValidationError: a parameter the kind does not take, or one it needs missing.
    """

    t_s: Annotated[float, Field(ge=0)]
    kind: Literal["hold", "resume", "goto", "formation", "exclude", "rejoin", "land", "rtl", "abort"]
    waypoints_ned_m: tuple[Vec3, ...] | None = None
    speed_mps: float | None = Field(default=None, gt=0)
    shape: Shape | None = None
    radius_m: float | None = Field(default=None, gt=0)
    spacing_m: float | None = Field(default=None, gt=0)
    rotation_deg: float | None = None
    vehicles: tuple[Vehicle, ...] | None = None
    land: bool | None = None

    @model_validator(mode="after")
    def _parameters_fit_the_kind(self):
        takes = {"goto": {"waypoints_ned_m", "speed_mps"},
                 "formation": {"shape", "radius_m", "spacing_m", "rotation_deg"},
                 "exclude": {"vehicles", "land"}, "rejoin": {"vehicles"}, "land": {"vehicles"}}.get(self.kind, set())
        given = {k for k in ("waypoints_ned_m", "speed_mps", "shape", "radius_m", "spacing_m", "rotation_deg",
                             "vehicles", "land") if getattr(self, k) is not None}
        extra = sorted(given - takes)
        if extra:
            raise ValueError(f"{self.kind} does not take {', '.join(extra)}"
                             + (f" (it takes {', '.join(sorted(takes))})" if takes else " (it takes no parameter)"))
        if self.kind == "goto" and not self.waypoints_ned_m:
            raise ValueError("goto needs waypoints_ned_m (1 to 7 points x, y, z, NED m)")
        if self.kind == "goto" and len(self.waypoints_ned_m or ()) > PLAN_WAYPOINTS_MAX - 1:
            raise ValueError(f"goto takes at most {PLAN_WAYPOINTS_MAX - 1} waypoints, got {len(self.waypoints_ned_m or ())}")
        if self.kind == "formation" and not given:
            raise ValueError("formation needs at least one of shape, radius_m, spacing_m, rotation_deg")
        if self.kind in ("exclude", "rejoin") and not self.vehicles:
            raise ValueError(f"{self.kind} needs vehicles (1-based numbers)")
        if self.kind == "land" and self.vehicles is not None and not self.vehicles:
            raise ValueError("land: give vehicles (1-based) or leave it out to land every vehicle")
        if self.vehicles is not None and len(set(self.vehicles)) != len(self.vehicles):
            raise ValueError("vehicles lists a vehicle twice")
        return self

    def formation_spec(self, current: FormationSpec) -> FormationSpec:
        """The FORMATION command's spec: the given values over the current formation."""
        return dataclasses.replace(
            current, shape=self.shape or current.shape,
            radius_m=self.radius_m if self.radius_m is not None else current.radius_m,
            spacing_m=self.spacing_m if self.spacing_m is not None else current.spacing_m,
            rotation_rad=math.radians(self.rotation_deg) if self.rotation_deg is not None else current.rotation_rad)


def check_schedule(commands: Sequence[CommandEntry], n_vehicles: int, duration_s: float | None = None) -> None:
    """Checks of a schedule against its mission and run: vehicle numbers within the mission,
    the commands in time order, and issued before the run ends (duration_s, if given).

    Raises:
        ValueError: naming the entry ("commands.3.vehicles: ...").
    """
    last = -math.inf
    for k, c in enumerate(commands):
        if c.t_s < last:
            raise ValueError(f"commands.{k}.t_s: {c.t_s:g} s is earlier than the command before it ({last:g} s): "
                             "list the commands in time order")
        if duration_s is not None and c.t_s >= duration_s:
            raise ValueError(f"commands.{k}.t_s: {c.t_s:g} s is not before the end of the run (duration_s "
                             f"{duration_s:g} s): it would never be issued")
        last = c.t_s
        bad = [v for v in c.vehicles or () if v > n_vehicles]
        if bad:
            raise ValueError(f"commands.{k}.vehicles: {bad} not in the mission (vehicles are numbered 1..{n_vehicles})")


def schedule_problems(commands: Sequence[CommandEntry], mission: Mission) -> list[str]:
    """A dry run of a schedule through a CommandSource (no transit start agreed): the
    commands it would refuse, as "commands.K: reason" (e.g. a RESUME with nothing held, a
    formation into the ground, a command after ABORT). Each refused command is skipped
    and the run goes on. Pure; for a loader's findings."""
    src = CommandSource(mission)
    out = []
    for k, entry in enumerate(commands):
        try:
            src.apply(entry)
        except CommandError as exc:
            out.append(f"commands.{k}: {exc}")
    return out
