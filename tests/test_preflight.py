"""`swarmdrop preflight` (docs/field-kit.md) against the SITL in both dialects, as the
onboard install runs it (none of the extras' packages, nor the simulators, importable): what
it finds, what it refuses, and that it changes nothing on the vehicle but the streams."""
from __future__ import annotations

import json
import re
import subprocess
import time
from pathlib import Path

import pytest
from lean_agent import EXTRAS_ONLY, lean_agent_cmd, lean_cmd
from pymavlink import mavutil

from companion.link.endpoints import MavEndpoint, UdpLink
from companion.link.msgdef import swarmdrop as md
from companion.link.wire import Codec
from companion.node.config import load_mission_file
from companion.node.preflight import PREFLIGHT_FAILED
from companion.swarm import FLAG_OWN_VALID
from sim_bridge.sitl.testing import free_udp_base_port

ROOT = Path(__file__).resolve().parents[1]
GROUND4 = ROOT / "configs" / "ground_4.yaml"


def _preflight(*args: str, neighbour: tuple[int, int, int] | None = None,
               timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    """Run preflight; with neighbour = (swarm port, sender sysid, vehicle id), a neighbour sends
    that vehicle's state to it at 10 Hz while it runs (as the swarm's radio would)."""
    cmd = lean_cmd("preflight", "--mission", str(GROUND4), *args, blocked=(*EXTRAS_ONLY, "sim_bridge"))
    if neighbour is None:
        return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)
    port, sysid, vehicle_id = neighbour
    ep = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=None, learn_remote=False), Codec(md), sysid, 191)
    with subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        try:
            for _ in range(int(timeout_s * 10)):
                t_us = int(time.time() * 1e6) - 50_000
                ep.queue_fields(md.MAVLINK_MSG_ID_SWARMDROP_STATE,
                                [t_us, 0, 1.0, 2.0, -3.0, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 1, FLAG_OWN_VALID,
                                 vehicle_id], ("127.0.0.1", port))
                ep.flush()
                try:
                    out, err = proc.communicate(timeout=0.1)
                    break
                except subprocess.TimeoutExpired:
                    continue
            else:
                proc.kill()
                out, err = proc.communicate()
        finally:
            ep.close()
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def _sitl(tmp: Path, dialect: str, ap_base: int, gcs_port: int | None = None):
    from sim_bridge.sitl.background import BackgroundSitl
    from sim_bridge.sitl.config import EndpointConfig, sitl_config

    mcfg = load_mission_file(GROUND4).mission
    ep = EndpointConfig(remote_host="127.0.0.1", remote_base_port=ap_base, bind_host="127.0.0.1", local_base_port=0,
                        gcs_enabled=gcs_port is not None, gcs_remote_port=gcs_port or 14550)
    cfg = sitl_config(2, seed=4, launch="ground", origin=mcfg.origin, dialect=dialect, endpoints=ep,
                      tlog_path=str(tmp / "sitl.tlog"))  # (its clock: this computer's, as a GNSS-timed autopilot)
    return BackgroundSitl(cfg)


def _checks(path: Path) -> dict[str, dict]:
    return {c["name"]: c for c in json.loads(path.read_text())["checks"]}


def _commands_to(tlog: Path, sysid: int) -> list[str]:
    """What the tlog shows sent to the autopilot sysid that changes it beyond its streams."""
    conn = mavutil.mavlink_connection(str(tlog))
    out = []
    while (m := conn.recv_match(type=["COMMAND_LONG", "PARAM_SET", "SET_MODE", "SET_POSITION_TARGET_LOCAL_NED",
                                      "SET_ATTITUDE_TARGET"])) is not None:
        if m.target_system != sysid:
            continue
        if m.get_type() == "COMMAND_LONG" and m.command in (mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                                                            mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE):
            continue
        out.append(m.get_type() if m.get_type() != "COMMAND_LONG" else f"COMMAND_LONG {m.command}")
    conn.close()
    return out


@pytest.mark.timeout(120)
@pytest.mark.parametrize("dialect", ["px4", "ardupilot"])
def test_preflight_on_a_stock_autopilot_fails_on_its_loss_parameters_and_passes_with_the_fix_it_changes_nothing(
        tmp_path, dialect):
    """Stock loss parameters fail (PX4 COM_OBL_RC_ACT 0 drifts; ArduPilot GUID_TIMEOUT 3 s is beyond
    the mission's 1 s), naming the parameter and the fix (exit 8); with --set-loss-action hold
    the same vehicle passes (exit 0), the report saying what the agent would write. Either way
    the streams come at the rate asked, a neighbour is heard, and nothing is armed, switched or
    written on the vehicle."""
    base = free_udp_base_port(2 + 1)
    bg = _sitl(tmp_path, dialect, base)
    server = bg.start()
    swarm_port = base + 2
    param = "COM_OBL_RC_ACT" if dialect == "px4" else "GUID_TIMEOUT"
    stock = server.autopilots[0].params[param]
    mode = server.autopilots[0].mode
    common = ("--vehicle-id", "0", "--autopilot", f"udpin://127.0.0.1:{base}", "--swarm-bind",
              f"127.0.0.1:{swarm_port}", "--swarm-peer", "127.0.0.1:9", "--listen", "2")
    try:
        bad = _preflight(*common, "--json", str(tmp_path / "bad.json"))
        assert bad.returncode == PREFLIGHT_FAILED, bad.stdout + bad.stderr
        checks = _checks(tmp_path / "bad.json")
        loss = checks["companion loss"]
        assert loss["status"] == "FAIL" and param in loss["detail"] and "--set-loss-action" in loss["detail"], loss
        assert "NOT ready" in bad.stdout and "FAIL  companion loss" in bad.stdout

        good = _preflight(*common, "--set-loss-action", "hold", "--json", str(tmp_path / "good.json"),
                          neighbour=(swarm_port, 2, 1))
        assert good.returncode == 0, good.stdout + good.stderr
        checks = _checks(tmp_path / "good.json")
        assert {n for n, c in checks.items() if c["status"] == "FAIL"} == set()
        assert checks["autopilot"]["status"] == "PASS" and checks["autopilot"]["detail"].startswith(dialect)
        for name in ("streams", "clock", "EKF origin", "vehicle state"):
            assert checks[name]["status"] == "PASS", checks[name]
        assert checks["companion loss"]["status"] == "WARN" and f"{param} {stock:g} -> " in checks["companion loss"][
            "detail"], checks["companion loss"]
        for name in ("LOCAL_POSITION_NED rate", "ATTITUDE_QUATERNION rate"):
            # (counted over 2 s of wall time against a real-time SITL: a busy machine may slow it a little)
            hz = float(checks[name]["detail"].split()[0])
            assert checks[name]["status"] in ("PASS", "WARN") and 35.0 <= hz <= 55.0, checks[name]
        assert checks["swarm link"]["status"] == "PASS" and "heard 1 of 3" in checks["swarm link"]["detail"]
        assert checks["signing"]["status"] == "WARN"
    finally:
        bg.stop()
    ap = server.autopilots[0]
    assert ap.params[param] == stock and not ap.armed and ap.mode == mode
    assert _commands_to(tmp_path / "sitl.tlog", 1) == []


@pytest.mark.timeout(90)
def test_preflight_fails_on_a_second_vehicle_with_this_id_and_on_a_silent_autopilot(tmp_path):
    """A neighbour's state that claims this vehicle's id (another companion started with the same
    --vehicle-id) fails the swarm check; an autopilot link where nothing comes fails at once,
    saying so, and the report still lists the checks that need no link."""
    base = free_udp_base_port(2 + 1)
    bg = _sitl(tmp_path, "px4", base)
    bg.start()
    swarm_port = base + 2
    try:
        out = _preflight("--vehicle-id", "0", "--autopilot", f"udpin://127.0.0.1:{base}", "--swarm-bind",
                         f"127.0.0.1:{swarm_port}", "--set-loss-action", "hold", "--listen", "1", "--json", "-",
                         neighbour=(swarm_port, 1, 0))  # sysid 1 says it is vehicle 0, from another address
        # vehicle 0's companion on vehicle 1's port, with a set-up timeout shorter than the
        # identity grace: still named as another vehicle's autopilot, not as silence
        wrong = _preflight("--vehicle-id", "0", "--autopilot", f"udpin://127.0.0.1:{base + 1}", "--setup-timeout",
                           "2", "--json", "-")
    finally:
        bg.stop()
    assert wrong.returncode == PREFLIGHT_FAILED, wrong.stdout + wrong.stderr
    ap = {c["name"]: c for c in json.loads(wrong.stdout)["checks"]}["autopilot"]
    assert ap["status"] == "FAIL" and "is sysid 2" in ap["detail"] and "--target-sysid" in ap["detail"], ap
    assert out.returncode == PREFLIGHT_FAILED, out.stdout + out.stderr
    report = json.loads(out.stdout)
    checks = {c["name"]: c for c in report["checks"]}
    assert not report["passed"] and checks["swarm link"]["status"] == "FAIL"
    assert "claim this vehicle's id 0" in checks["swarm link"]["detail"]
    assert checks["swarm peers"]["status"] == "WARN"  # no --swarm-peer

    silent = free_udp_base_port(1)
    out = _preflight("--vehicle-id", "0", "--autopilot", f"udpin://127.0.0.1:{silent}", "--setup-timeout", "1",
                     "--json", "-")
    assert out.returncode == PREFLIGHT_FAILED, out.stdout + out.stderr
    checks = {c["name"]: c for c in json.loads(out.stdout)["checks"]}
    assert checks["autopilot"]["status"] == "FAIL" and "nothing at all came" in checks["autopilot"]["detail"]
    assert checks["mission"]["status"] == "PASS" and "streams" not in checks


@pytest.mark.timeout(120)
def test_preflight_fails_on_a_mission_origin_kilometres_off_and_on_a_vehicle_already_flying(tmp_path):
    """A mission whose origin is 11 km from the flying site puts the vehicle 11 km from the
    mission: the agent would fly it there, so a ground launch fails (position); a vehicle that
    a ground station has armed and taken off fails too (vehicle state): the agent's set-up is
    for a vehicle on the ground or on the carrier."""
    from companion.link.dialects import Mode, dialect_named
    from companion.link.enums import MavCmd
    from sim_bridge.sitl.testing import MavClient

    base = free_udp_base_port(2 + 2)
    bg = _sitl(tmp_path, "px4", base, gcs_port=base + 3)
    server = bg.start()
    text = GROUND4.read_text()
    assert "lat_deg: 47.397742" in text
    far = tmp_path / "far.yaml"
    far.write_text(text.replace("lat_deg: 47.397742", "lat_deg: 47.497742"))  # 0.1 deg: 11.1 km north
    common = ("--vehicle-id", "0", "--autopilot", f"udpin://127.0.0.1:{base}", "--swarm-bind",
              f"127.0.0.1:{base + 2}", "--swarm-peer", "127.0.0.1:9", "--set-loss-action", "hold", "--listen", "1",
              "--json", "-")
    gcs = None
    try:
        out = _preflight(*common, "--mission", str(far))
        assert out.returncode == PREFLIGHT_FAILED, out.stdout + out.stderr
        checks = {c["name"]: c for c in json.loads(out.stdout)["checks"]}
        pos = checks["position"]
        assert pos["status"] == "FAIL" and "mission.origin" in pos["detail"], pos
        assert 11_000 < float(pos["detail"].split(" m from")[0].split()[-1]) < 11_300, pos  # its distance, m
        assert checks["vehicle state"]["status"] == "PASS"
        # the agent itself refuses it, before it writes any parameter (its set-up's check_site)
        agent = subprocess.run(lean_agent_cmd("--vehicle-id", "0", "--autopilot", f"udpin://127.0.0.1:{base}",
                                              "--mission", str(far), "--swarm-bind", f"127.0.0.1:{base + 2}",
                                              "--set-loss-action", "hold", "--setup-timeout", "20"),
                               cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert agent.returncode == 4 and re.search(r"is 11[01]\d\d m from the mission origin", agent.stderr) \
            and "mission.origin" in agent.stderr, agent.stderr
        assert _commands_to(tmp_path / "sitl.tlog", 1) == [] and not server.autopilots[0].armed

        gcs = MavClient(base + 3)
        assert gcs.wait("HEARTBEAT", lambda m: m.get_srcSystem() == 1, 10) is not None
        d = dialect_named("px4")
        for cmd, params in ((MavCmd.MAV_CMD_DO_SET_MODE, d.set_mode_params(d.takeoff_from_mode)),
                            (MavCmd.MAV_CMD_COMPONENT_ARM_DISARM, (1.0,)),
                            (MavCmd.MAV_CMD_NAV_TAKEOFF, d.takeoff_params(5.0, 488.0))):
            ack = gcs.command(1, int(cmd), *params)
            assert ack is not None and ack.result == 0, (cmd, ack)
        deadline = time.monotonic() + 30
        while not server.state.pos_ned_m[0, 2] < -2.0:  # (a condition polled with a deadline)
            assert time.monotonic() < deadline, "vehicle 0 did not take off"
            gcs.wait("HEARTBEAT", timeout_s=0.2)
        out = _preflight(*common)
        assert out.returncode == PREFLIGHT_FAILED, out.stdout + out.stderr
        checks = {c["name"]: c for c in json.loads(out.stdout)["checks"]}
        state = checks["vehicle state"]
        assert state["status"] == "FAIL" and state["detail"].startswith("armed and ") and "flying" in state["detail"], state
        assert checks["position"]["status"] == "PASS"
        assert server.autopilots[0].mode != Mode.OFFBOARD  # (nothing taken over)
    finally:
        if gcs is not None:
            gcs.close()
        bg.stop()


def test_preflight_refuses_bad_arguments_as_the_agent_does(tmp_path):
    out = _preflight("--vehicle-id", "9", "--autopilot", "udpin://127.0.0.1:14540")
    assert out.returncode == 2 and "vehicle" in out.stderr.lower(), out.stderr
    out = _preflight("--vehicle-id", "0", "--autopilot", "localhost:14540")
    assert out.returncode == 2 and "localhost:14540" in out.stderr, out.stderr
    out = _preflight("--vehicle-id", "0", "--autopilot", "udpin://127.0.0.1:14540", "--listen", "0")
    assert out.returncode == 2 and "--listen" in out.stderr, out.stderr
    for option in ("--json", "--stats", "--log-file"):  # refused at once, before any check
        bad = str(tmp_path / "missing" / "x.json")
        out = _preflight("--vehicle-id", "0", "--autopilot", "udpin://127.0.0.1:14540", option, bad)
        assert out.returncode == 2 and option in out.stderr and bad in out.stderr and not out.stdout, out


@pytest.mark.timeout(60)
def test_preflight_stopped_by_sigterm_reports_what_it_had(tmp_path):
    """A supervisor's SIGTERM (or Ctrl-C) while it waits for the autopilot: the checks so far and
    an 'interrupted' failure, exit 8."""
    url = f"udpin://127.0.0.1:{free_udp_base_port(1)}"
    cmd = lean_cmd("preflight", "--mission", str(GROUND4), "--vehicle-id", "0", "--autopilot", url,
                   "--setup-timeout", "40", "--log-level", "INFO", "--json", "-", blocked=(*EXTRAS_ONLY, "sim_bridge"))
    with subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        try:
            assert proc.stderr is not None
            for line in proc.stderr:  # (bounded by the test's timeout; the line comes after WAIT_LOG_S, 3 s)
                if "waiting for HEARTBEAT" in line:
                    break
            proc.terminate()
            out, _ = proc.communicate(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == PREFLIGHT_FAILED
    checks = {c["name"]: c for c in json.loads(out)["checks"]}
    assert checks["interrupted"]["status"] == "FAIL" and checks["mission"]["status"] == "PASS"


# ---------------------------------------------------------------------------- the shared rules, pure
def test_loss_refusal_names_one_fix_per_kind_of_excess():
    """The rule set-up and preflight share (companion.node.setup_rules.loss_refusal): a long timeout,
    a landing where the mission holds, and softer braking each get their own fix."""
    from companion.link.dialects import dialect_named
    from companion.mission import LossEnvelope
    from companion.node.setup_rules import loss_refusal

    px4 = dialect_named("px4")
    hold = LossEnvelope()
    base = {"COM_OF_LOSS_T": 1.0, "COM_OBL_RC_ACT": 5.0}
    assert loss_refusal("ap", px4, px4.loss_behaviour(base), hold) is None
    text = loss_refusal("ap", px4, px4.loss_behaviour({**base, "COM_OF_LOSS_T": 3.0}), hold)
    assert text is not None and "set COM_OF_LOSS_T to at most 1 s" in text and "mission.swarm.loss.then" not in text
    text = loss_refusal("ap", px4, px4.loss_behaviour({**base, "COM_OBL_RC_ACT": 4.0}), hold)
    assert text is not None and "mission.swarm.loss.then: land" in text and "COM_OF_LOSS_T to at most" not in text
    assert loss_refusal("ap", px4, px4.loss_behaviour({**base, "COM_OBL_RC_ACT": 4.0}), LossEnvelope(then="land")) \
        is None
    text = loss_refusal("ap", px4, px4.loss_behaviour({**base, "MPC_ACC_HOR": 1.0}), hold)
    assert text is not None and "bring the limits named" in text and "horizontal braking" in text
    text = loss_refusal("ap", px4, px4.loss_behaviour({**base, "COM_OBL_RC_ACT": 0.0}), hold)
    assert text is not None and "COM_OBL_RC_ACT = 0" in text and "drifting" in text


def test_off_site_is_measured_from_the_reach_of_the_waypoints():
    from companion.node.setup_rules import NEAR_MISSION_M, off_site

    waypoints = ((100.0, 0.0, -10.0), (0.0, -300.0, -10.0))
    assert off_site((0.0, 0.0, 0.0), waypoints) is None
    assert off_site((0.0, 300.0 + NEAR_MISSION_M - 1.0, 0.0), waypoints) is None
    text = off_site((-(300.0 + NEAR_MISSION_M + 5.0), 0.0, 0.0), waypoints)
    assert text is not None and "is 1305 m from the mission origin" in text and "waypoints 300 m" in text
