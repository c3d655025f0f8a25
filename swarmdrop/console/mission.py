"""The mission as the console shows it: origin, obstacles, geofence, path and formation slots.

Live, the mission comes from `--mission FILE`, read exactly as `swarmdrop agent` reads it
(companion.node.config.load_mission_file: the same validation, mission.origin required).
In a replay it comes from the run directory's config.json (the resolved scenario `swarmdrop
simulate` and `swarmdrop run` write), validated as a MissionConfig, unless `--mission` is
given. Slots are the mission's own (companion.mission.Mission: offsets around the centre
path at tau = t - t_go); under an operator's plan the console shows the plan's slots when
companion.commands can compute them (swarmdrop.console.commands).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import ConfigError, validate
from companion.mission import Mission, MissionConfig


@dataclass
class MissionInfo:
    """What the page draws of a mission, and the mission's slots.

    Attributes:
        name: shown in the page's title.
        config: the validated mission (None: no mission given; nothing but vehicles drawn).
        sysids: MAVLink system id of each vehicle (vehicle k: k + 1 unless the mission maps them).
    """

    name: str
    config: MissionConfig | None
    sysids: list[int]
    display: dict[str, Any] | None = None
    """What to draw when there is no validated config (a run directory written by another
    version of the schema): read leniently from its config.json."""

    def __post_init__(self) -> None:
        self._mission: Mission | None = Mission(self.config) if self.config is not None else None
        self._slot_tau = math.nan
        self._slots = np.zeros((0, 3))

    @property
    def model(self) -> Mission | None:
        """The derived mission (companion.mission.Mission), None without one."""
        return self._mission

    @property
    def n(self) -> int | None:
        return self.config.n_vehicles if self.config is not None else None

    def slots(self, tau_s: float) -> np.ndarray | None:
        """Every vehicle's slot at tau_s after the transit start (tau < 0: at the assembly
        point), (n, 3) mission NED, m; None without a mission."""
        m = self._mission
        if m is None:
            return None
        tau = -1.0 if not math.isfinite(tau_s) or tau_s < 0 else round(tau_s, 2)
        if tau != self._slot_tau:
            self._slots, self._slot_tau = m.slot_ned_m(tau), tau
        return self._slots

    def to_json(self) -> dict[str, Any]:
        """The page's view of the mission (meta message)."""
        c = self.config
        if c is None and self.display is not None:
            return {"name": self.name, **self.display}
        if c is None:
            return {"name": self.name, "origin": None, "obstacles": [], "geofence": None, "waypoints": [],
                    "radius_m": None, "ground_z_m": None}
        o = c.origin
        return {
            "name": self.name,
            "origin": None if o is None else {"lat_deg": o.lat_deg, "lon_deg": o.lon_deg, "alt_m": o.alt_amsl_m},
            "obstacles": [{"c": list(ob.centre_ned_m), "r": ob.radius_m} for ob in c.obstacles],
            "geofence": None if c.geofence is None else {"min": list(c.geofence.min_ned_m),
                                                         "max": list(c.geofence.max_ned_m)},
            "waypoints": [list(w) for w in c.waypoints_ned_m],
            "radius_m": c.formation.radius_m,
            "ground_z_m": c.ground_z_m,
        }


def _sysids(cfg: MissionConfig) -> list[int]:
    from companion.node.config import mission_sysids

    return mission_sysids(cfg)


def load_mission(path: str | Path) -> MissionInfo:
    """A mission or scenario YAML, read as `swarmdrop agent` reads it.

    Raises:
        ConfigError: missing or invalid file (named by its dotted path), or no mission.origin.
    """
    from companion.node.config import load_mission_file

    mf = load_mission_file(path)
    return MissionInfo(Path(path).stem, mf.mission, _sysids(mf.mission))


def mission_of_run(run_dir: Path) -> MissionInfo | None:
    """The mission a run directory was flown with (its config.json), or None if it has none.

    Raises:
        ConfigError: config.json is there but is not a scenario (named, with the reason).
    """
    path = run_dir / "config.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise ConfigError(f"{path}: cannot read it: {err}") from None
    if not isinstance(data, dict) or not isinstance(data.get("mission"), dict):
        raise ConfigError(f"{path}: no mission section (not a run directory's config.json)")
    name = data.get("name") if isinstance(data.get("name"), str) else run_dir.name
    try:
        cfg = validate(MissionConfig, data["mission"], f"{path}: mission")
    except ConfigError:  # written by another version of the schema: draw what can be read
        return MissionInfo(str(name), None, [], display=_lenient(data["mission"]))
    return MissionInfo(str(name), cfg, _sysids(cfg))


def _point(v: Any) -> list[float] | None:
    if isinstance(v, (list, tuple)) and len(v) == 3 and all(isinstance(x, (int, float)) and math.isfinite(x)
                                                           and abs(x) <= 1e7 for x in v):
        return [float(x) for x in v]
    return None


def _number(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def _lenient(m: dict) -> dict[str, Any]:
    """The drawable parts of a mission section, each taken only if well-formed."""
    o = m.get("origin")
    origin = None
    if isinstance(o, dict) and all(_number(o.get(k)) is not None for k in ("lat_deg", "lon_deg", "alt_amsl_m")):
        origin = {"lat_deg": float(o["lat_deg"]), "lon_deg": float(o["lon_deg"]), "alt_m": float(o["alt_amsl_m"])}
    obstacles = []
    for ob in m.get("obstacles") or []:
        if isinstance(ob, dict) and _point(ob.get("centre_ned_m")) and (_number(ob.get("radius_m")) or 0) > 0:
            obstacles.append({"c": _point(ob["centre_ned_m"]), "r": float(ob["radius_m"])})
    g = m.get("geofence")
    fence = None
    if isinstance(g, dict) and _point(g.get("min_ned_m")) and _point(g.get("max_ned_m")):
        fence = {"min": _point(g["min_ned_m"]), "max": _point(g["max_ned_m"])}
    wps = [p for p in (_point(w) for w in (m.get("waypoints_ned_m") or [])[:64]) if p is not None]
    f = m.get("formation")
    return {"origin": origin, "obstacles": obstacles[:256], "geofence": fence, "waypoints": wps,
            "radius_m": _number(f.get("radius_m")) if isinstance(f, dict) else None,
            "ground_z_m": _number(m.get("ground_z_m"))}
