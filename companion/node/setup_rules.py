"""Set-up's rules as pure functions, shared by `swarmdrop agent` (companion.node.setup) and
`swarmdrop preflight` (companion.node.preflight): the streams the agent asks for, the mission
epoch, what --set-loss-action writes, when a companion-loss behaviour is refused, and when a
vehicle is not at the mission's site. No I/O."""
from __future__ import annotations

import math

from companion.link.dialects.base import AfterLoss, AutopilotDialect, LossBehaviour
from companion.link.enums import MsgId
from companion.mission import LossEnvelope

EXT_STATE_INTERVAL_S = 0.2
"""EXTENDED_SYS_STATE (landed state) stream period, s."""
SYSTEM_TIME_INTERVAL_S = 1.0
"""SYSTEM_TIME (the autopilot's clock) stream period, s."""


def telemetry_streams(rate_hz: float) -> tuple[tuple[MsgId, float], ...]:
    """(message, interval s) of the streams the agent asks its autopilot for at set-up: position
    and attitude at the setpoint rate, the landed state and the clock (docs/companion.md)."""
    return ((MsgId.LOCAL_POSITION_NED, 1.0 / rate_hz), (MsgId.ATTITUDE_QUATERNION, 1.0 / rate_hz),
            (MsgId.EXTENDED_SYS_STATE, EXT_STATE_INTERVAL_S), (MsgId.SYSTEM_TIME, SYSTEM_TIME_INTERVAL_S))


def mission_epoch_s(unix_offset_us: int) -> int:
    """Mission time 0 from the autopilot's clock (SYSTEM_TIME's Unix time less its boot time,
    µs): the whole hour before it, Unix s. Small floats; every exchanged time is absolute (µs),
    so agents need not share this epoch."""
    return unix_offset_us // 1_000_000 // 3600 * 3600


def loss_changes(d: AutopilotDialect, then: AfterLoss, values: dict[str, float],
                 timeout_max_s: float) -> dict[str, float]:
    """The parameters --set-loss-action `then` writes: the dialect's loss action, and its
    setpoint timeout down to timeout_max_s (the mission's loss envelope) if it is longer
    or unknown. Values already right are written again (set_loss_action skips them).

    Raises:
        ValueError: this autopilot cannot be set to do `then` (the message says why).
    """
    fix = d.loss_fix(then)
    timeout = values.get(d.setpoint_timeout_param)
    if timeout is None or not timeout <= timeout_max_s:
        fix = {**fix, d.setpoint_timeout_param: timeout_max_s}
    return fix


def loss_refusal(ap_name: str, d: AutopilotDialect, loss: LossBehaviour, envelope: LossEnvelope) -> str | None:
    """Why the agent refuses to fly with this companion-loss behaviour (the message names
    the parameter, what the vehicle would do and the fix), None if it does not: the vehicle
    must stop and hold or land (`loss.safe`) inside the ghost the swarm keeps clear for it
    (mission.swarm.loss). The one rule of set-up (verify_loss) and `swarmdrop preflight`."""
    if not loss.safe:
        return (f"{ap_name}: {loss.deciding()}: if this companion stops, the vehicle {loss.what_then()}, which the "
                f"swarm's ghost does not cover. Fix: {d.loss_fix_text()}, or pass --set-loss-action hold|land; or "
                "--allow-drifting-loss to fly anyway")
    over = envelope.excesses(loss)
    if not over:
        return None
    # The swarm draws this vehicle's ghost from the mission's envelope: beyond it, a silent
    # vehicle can fly where its neighbours do not expect it. One fix per kind of excess.
    fix_of = {"timeout": f"set {d.setpoint_timeout_param} to at most {envelope.timeout_s:g} s (--set-loss-action does)",
              "action": "make it hold (--set-loss-action hold), or set mission.swarm.loss.then: land for every vehicle",
              "limit": "bring the limits named to the mission's, or widen mission.swarm.loss for every vehicle"}
    kinds = {kind for kind, _ in over}
    fixes = [fix for kind, fix in fix_of.items() if kind in kinds]
    return (f"{ap_name}: if this companion stops, the vehicle can leave the ghost the swarm keeps clear for it "
            f"(mission.swarm.loss): {'; '.join(p for _, p in over)}. Fix: {'; '.join(fixes)}; or "
            "--allow-drifting-loss to fly anyway")


NEAR_MISSION_M = 1000.0
"""A vehicle farther than this beyond the reach of the mission's waypoints (from its origin) is
not at the mission's site: a wrong mission.origin, or another site."""


def off_site(pos_ned_m: tuple[float, float, float], waypoints_ned_m) -> str | None:
    """Why a vehicle at pos_ned_m (mission frame, m) is not at the mission's site, None if it is:
    over NEAR_MISSION_M beyond the farthest waypoint's horizontal distance from the origin.
    The agent would fly it from there to its slot (a wrong mission.origin by kilometres)."""
    reach = max(math.hypot(w[0], w[1]) for w in waypoints_ned_m)
    dist = math.hypot(pos_ned_m[0], pos_ned_m[1])
    if dist <= reach + NEAR_MISSION_M:
        return None
    return (f"the vehicle is {dist:.0f} m from the mission origin ({pos_ned_m[0]:.0f} m N, {pos_ned_m[1]:.0f} m E), "
            f"the mission's waypoints {reach:.0f} m: the agent would fly it from there. Check mission.origin (the "
            "flying site's) and that this is the right vehicle")
