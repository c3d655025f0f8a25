"""Injected faults: a rotor that stops on a chosen vehicle at a chosen time.

The same resolved list drives the headless runner and the SITL (the fleet harness
resolves it once and hands it to the SITL), so a seed fails the same rotor of the
same vehicle at the same time in both. A failed rotor's speed command is zero from
then on: the motor spins down with its time constant (an ESC or motor that quits),
and the vehicle's own inner loop, unaware, cannot hold attitude on three rotors.

Vehicle and rotor numbers in the config are 1-based (vehicle 1 is the first launched;
rotors are numbered as in docs/vehicle.md); the resolved list is 0-based.
"""
from __future__ import annotations

from dataclasses import dataclass as plain_dataclass

import numpy as np
from pydantic import Field, model_validator
from pydantic.dataclasses import dataclass

from companion.config import STRICT

_FAULT_STREAM = 0x524F544F  # "ROTO": the draws of random failures, apart from every other stream


@dataclass(config=STRICT)
class RotorFailureConfig:
    """One rotor failure, given explicitly."""

    vehicle: int = Field(ge=1)
    """1-based vehicle number (launch order)."""
    time_s: float = Field(ge=0)
    """Mission time at which the rotor stops, s."""
    rotor: int = Field(default=1, ge=1, le=4)
    """1-based rotor number (docs/vehicle.md)."""


@dataclass(config=STRICT)
class FaultsConfig:
    """Faults injected into a run (default: none)."""

    rotor_failures: tuple[RotorFailureConfig, ...] = ()
    random_rotor_failures: int = Field(default=0, ge=0)
    """This many more failures, each on a different vehicle (not one listed above), at a
    time uniform in random_window_s and on a uniform rotor, drawn from the run's seed."""
    random_window_s: tuple[float, float] = (50.0, 150.0)
    """Mission-time window of the random failures, s."""

    @model_validator(mode="after")
    def _window(self):
        lo, hi = self.random_window_s
        if not 0 <= lo <= hi:
            raise ValueError(f"random_window_s must be [start, end] with 0 <= start <= end, not {list(self.random_window_s)}")
        return self

    @property
    def active(self) -> bool:
        return bool(self.rotor_failures) or self.random_rotor_failures > 0


@plain_dataclass(frozen=True)
class RotorFailure:
    """A resolved failure: 0-based vehicle row and rotor index, mission time in s."""

    vehicle: int
    rotor: int
    time_s: float


def resolve_rotor_failures(cfg: FaultsConfig, n_vehicles: int, seed: int) -> tuple[RotorFailure, ...]:
    """The explicit failures plus the random ones drawn from `seed`, sorted by time.

    Raises:
        ValueError: a listed vehicle beyond n_vehicles, a vehicle listed twice, or more
            random failures than vehicles left to fail.
    """
    out, seen = [], set()
    for f in cfg.rotor_failures:
        if f.vehicle > n_vehicles:
            raise ValueError(f"faults.rotor_failures: vehicle {f.vehicle} but the mission has {n_vehicles}")
        if f.vehicle - 1 in seen:
            raise ValueError(f"faults.rotor_failures: vehicle {f.vehicle} is listed twice (one failure per vehicle)")
        seen.add(f.vehicle - 1)
        out.append(RotorFailure(f.vehicle - 1, f.rotor - 1, float(f.time_s)))
    k = cfg.random_rotor_failures
    if k:
        free = np.array(sorted(set(range(n_vehicles)) - seen))
        if k > len(free):
            raise ValueError(f"faults.random_rotor_failures: {k} but only {len(free)} vehicles can still fail")
        rng = np.random.default_rng([seed, _FAULT_STREAM])
        veh = rng.choice(free, size=k, replace=False)
        times = rng.uniform(*cfg.random_window_s, size=k)
        rotors = rng.integers(0, 4, size=k)
        out += [RotorFailure(int(v), int(r), float(t)) for v, r, t in zip(veh, rotors, times)]
    return tuple(sorted(out, key=lambda f: (f.time_s, f.vehicle)))


class RotorFaults:
    """Applies resolved failures as time passes: `scale` is the (N, 4) factor on every
    rotor's speed command (1 healthy, 0 failed), handed to Physics.step.

    Args:
        failures: resolved failures; n_vehicles: fleet size.
    """

    def __init__(self, failures: tuple[RotorFailure, ...], n_vehicles: int):
        self.pending = sorted(failures, key=lambda f: f.time_s)
        self.scale = np.ones((n_vehicles, 4))
        self.failed_at_s = np.full(n_vehicles, np.nan)
        """(N,) mission time each vehicle's rotor failed (NaN: healthy)."""

    def update(self, t_s: float) -> list[RotorFailure]:
        """Apply every failure due by t_s; returns those applied now (usually none)."""
        fired = []
        while self.pending and self.pending[0].time_s <= t_s + 1e-9:
            f = self.pending.pop(0)
            self.scale[f.vehicle, f.rotor] = 0.0
            self.failed_at_s[f.vehicle] = t_s
            fired.append(f)
        return fired

    def fail_now(self, vehicle: int, rotor: int, t_s: float) -> None:
        """Stop one rotor at once (a MAV_CMD_INJECT_FAILURE in the SITL)."""
        self.scale[vehicle, rotor] = 0.0
        if np.isnan(self.failed_at_s[vehicle]):
            self.failed_at_s[vehicle] = t_s
