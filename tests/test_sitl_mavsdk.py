"""Unmodified MAVSDK (PyPI mavsdk 4.x) flies vehicle k=2 of a 3-vehicle SITL."""
from __future__ import annotations

import asyncio
import math
import time

import pytest

mavsdk = pytest.importorskip("mavsdk.asyncio")
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.offboard import AccelerationNed, Attitude, OffboardAsync  # noqa: E402
from mavsdk.asyncio.plugins.param import ParamAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync  # noqa: E402

from sim_bridge.sitl.autopilot import Mode  # noqa: E402
from sim_bridge.sitl.background import BackgroundSitl  # noqa: E402
from sim_bridge.sitl.config import sitl_config  # noqa: E402
from sim_bridge.sitl.testing import local_endpoints  # noqa: E402

N, K = 3, 2


@pytest.fixture(scope="module")
def sitl():
    bg = BackgroundSitl(sitl_config(N, endpoints=local_endpoints(N)))
    server = bg.start()
    yield server
    bg.stop()


async def until(pred, timeout_s: float, poll_s: float = 0.05):
    """Await an async predicate with a deadline; returns its last truthy value or fails."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = await pred()
        if value:
            return value
        await asyncio.sleep(poll_s)  # polling interval of the condition, not synchronisation
    pytest.fail(f"condition not met within {timeout_s} s")


@pytest.mark.timeout(90)
async def test_mavsdk_flies_vehicle_k(sitl):
    port = sitl.cfg.endpoints.remote_base_port + K
    async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as m:
        await m.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await m.first_autopilot(timeout_s=10)
        assert await system.get_system_id() == K + 1
        tel, act, off, par = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system), ParamAsync(system)

        async def armable():
            h = await tel.health()
            return h.is_armable and h.is_home_position_ok and h.is_global_position_ok and h.is_local_position_ok

        await until(armable, 10)

        # parameters: set and get (REAL32), and one that drives the vehicle
        await par.set_param_float("MIS_TAKEOFF_ALT", 3.0)
        assert await par.get_param_float("MIS_TAKEOFF_ALT") == pytest.approx(3.0)
        await par.set_param_float("COM_DISARM_LAND", 0.5)
        assert await par.get_param_int("GF_ACTION") == 2

        # arm and take off to MIS_TAKEOFF_ALT, then Hold
        await act.arm()
        await act.takeoff()
        home_z = sitl.home_ned_m[K][2]

        async def at_altitude():
            pv = await tel.position_velocity_ned()
            return abs(pv.position.down_m - (home_z - 3.0)) < 0.3 and sitl.autopilots[K].mode == Mode.HOLD

        await until(at_altitude, 15)
        assert await tel.in_air()

        # offboard with acceleration setpoints: 1 m/s^2 north for ~1 s
        await off.set_acceleration_ned(AccelerationNed(0.0, 0.0, 0.0))
        await off.start()
        assert sitl.autopilots[K].mode == Mode.OFFBOARD
        v0 = (await tel.position_velocity_ned()).velocity
        t0, sim0 = time.monotonic(), sitl.sim_s
        while time.monotonic() - t0 < 1.0:
            await off.set_acceleration_ned(AccelerationNed(1.0, 0.0, 0.0))
            await asyncio.sleep(0.05)  # 20 Hz setpoint stream
        v1 = (await tel.position_velocity_ned()).velocity
        # (over the simulated time that passed: a SITL slowed below real time by a busy machine
        # accelerates the vehicle for less than the wall-clock second)
        gain = (v1.north_m_s - v0.north_m_s) / (sitl.sim_s - sim0)
        assert 0.6 < gain < 1.4, gain
        assert abs(v1.east_m_s - v0.east_m_s) < 0.2

        # attitude setpoint: 10 deg roll at about hover thrust
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.6:
            await off.set_attitude(Attitude(10.0, 0.0, 0.0, 0.52))
            await asyncio.sleep(0.05)
        att = await tel.attitude_euler()
        assert att.roll_deg == pytest.approx(10.0, abs=2.0) and abs(att.pitch_deg) < 2.0

        # stop offboard (-> Hold), land, auto-disarm
        await off.stop()
        assert sitl.autopilots[K].mode == Mode.HOLD
        await act.land()

        async def disarmed():
            return not await tel.armed()

        await until(disarmed, 25, 0.2)
        assert sitl.autopilots[K].landed
        assert not math.isnan((await tel.position_velocity_ned()).position.down_m)
