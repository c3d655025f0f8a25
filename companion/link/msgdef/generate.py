"""Regenerate the swarmdrop MAVLink dialect (``swarmdrop.xml``, then ``swarmdrop.py`` via mavgen)
and the named MAVLink values ``companion/link/enums.py``.

Why generate rather than hand-write: the dialect must carry pymavlink's *exact*
definitions of the common messages the companion and the SITL exchange with
autopilots and ground stations. A hand-copied field (name, type, order) changes a
message's CRC_EXTRA and the frames silently stop decoding on the other side, so the
definitions are copied element by element from pymavlink's shipped ``common.xml``
(and the files it includes), and the project's own messages are added in code.

What is changed in the copies: the ``enum`` and ``display`` attributes of fields are
removed. They only annotate values (CRC_EXTRA hashes the message name and the field
types/names/array lengths, never enums; ``check_crc_extras`` verifies it), and keeping
them would force copying their enums too (MAV_CMD alone is thousands of lines), which
would make the onboard module large and slow to import.

The enums come back, lean, in ``companion/link/enums.py``: one ``IntEnum`` per MAVLink enum
the project uses, holding only the members listed in ``ENUMS`` (a few whole small enums),
copied with their MAVLink names and values from the same XML, and ``MsgId`` for every
message of the dialect (plus ``NAMED_ONLY_MESSAGES``). It imports nothing but ``enum``, so
code can say ``MavCmd.MAV_CMD_NAV_TAKEOFF`` instead of 22 at no cost to the onboard import.

Reproducible: the same pymavlink gives byte-identical files (a test regenerates into
a temporary directory and compares with the committed ones).

Run::

    python -m companion.link.msgdef.generate            # rewrite the committed files
    python -m companion.link.msgdef.generate --check    # exit 1 if they are stale
    python -m companion.link.msgdef.generate --out DIR  # write elsewhere (enums.py too)
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import filecmp
import importlib.util
import io
import re
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

HERE = Path(__file__).resolve().parent
DIALECT = "swarmdrop"

# Common messages the companion and the SITL use (ids; names are checked on copy).
COMMON_MESSAGES = {
    0: "HEARTBEAT", 1: "SYS_STATUS", 2: "SYSTEM_TIME", 4: "PING", 20: "PARAM_REQUEST_READ",
    21: "PARAM_REQUEST_LIST", 22: "PARAM_VALUE", 23: "PARAM_SET", 24: "GPS_RAW_INT", 30: "ATTITUDE",
    31: "ATTITUDE_QUATERNION", 32: "LOCAL_POSITION_NED", 33: "GLOBAL_POSITION_INT",
    48: "SET_GPS_GLOBAL_ORIGIN", 49: "GPS_GLOBAL_ORIGIN", 75: "COMMAND_INT", 76: "COMMAND_LONG",
    77: "COMMAND_ACK", 82: "SET_ATTITUDE_TARGET", 83: "ATTITUDE_TARGET",
    84: "SET_POSITION_TARGET_LOCAL_NED", 85: "POSITION_TARGET_LOCAL_NED", 111: "TIMESYNC",
    148: "AUTOPILOT_VERSION", 242: "HOME_POSITION", 244: "MESSAGE_INTERVAL", 245: "EXTENDED_SYS_STATE",
    253: "STATUSTEXT", 256: "SETUP_SIGNING", 340: "UTM_GLOBAL_POSITION",
    # the SITL's replies and streams, built with the same codec (companion.link.builder)
    43: "MISSION_REQUEST_LIST", 44: "MISSION_COUNT", 110: "FILE_TRANSFER_PROTOCOL", 147: "BATTERY_STATUS",
}
STRIPPED_FIELD_ATTRS = ("enum", "display")

# Common messages the project names (MsgId) without carrying them in the dialect: the
# signing layer only names their ids (they are accepted unsigned, as PX4 does).
NAMED_ONLY_MESSAGES = {109: "RADIO_STATUS", 246: "ADSB_VEHICLE", 247: "COLLISION"}

ALL = None
"""In ENUMS: every member of the enum. Used for the small enums whose values the agent
receives and logs or branches on (a received value then always has a name)."""

# The MAVLink enums the companion and the SITL use, and which of their members (full
# MAVLink names, as pymavlink's ``mavlink.<NAME>``). Add a member here when code needs it.
ENUMS: dict[str, tuple[str, ...] | None] = {
    "MAV_CMD": (
        "MAV_CMD_NAV_LAND", "MAV_CMD_NAV_TAKEOFF", "MAV_CMD_DO_SET_MODE", "MAV_CMD_COMPONENT_ARM_DISARM",
        "MAV_CMD_INJECT_FAILURE", "MAV_CMD_GET_MESSAGE_INTERVAL", "MAV_CMD_SET_MESSAGE_INTERVAL",
        "MAV_CMD_REQUEST_MESSAGE", "MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES", "MAV_CMD_USER_1"),
    "MAV_RESULT": ALL,
    "MAV_FRAME": ("MAV_FRAME_LOCAL_NED", "MAV_FRAME_BODY_NED"),
    "MAV_MODE_FLAG": ALL,
    "MAV_TYPE": ("MAV_TYPE_QUADROTOR", "MAV_TYPE_GCS", "MAV_TYPE_ONBOARD_CONTROLLER"),
    "MAV_AUTOPILOT": ("MAV_AUTOPILOT_GENERIC", "MAV_AUTOPILOT_ARDUPILOTMEGA", "MAV_AUTOPILOT_INVALID",
                      "MAV_AUTOPILOT_PX4"),
    "MAV_COMPONENT": ("MAV_COMP_ID_ALL", "MAV_COMP_ID_AUTOPILOT1", "MAV_COMP_ID_MISSIONPLANNER",
                      "MAV_COMP_ID_ONBOARD_COMPUTER"),
    "MAV_STATE": ALL,
    "MAV_LANDED_STATE": ALL,
    "MAV_VTOL_STATE": ("MAV_VTOL_STATE_UNDEFINED",),
    "MAV_SEVERITY": ALL,
    "MAV_PARAM_TYPE": ALL,
    "POSITION_TARGET_TYPEMASK": ALL,
    "ATTITUDE_TARGET_TYPEMASK": ALL,
    "GPS_FIX_TYPE": ("GPS_FIX_TYPE_NO_FIX", "GPS_FIX_TYPE_3D_FIX"),
    "MAV_BATTERY_FUNCTION": ("MAV_BATTERY_FUNCTION_ALL",),
    "MAV_BATTERY_TYPE": ("MAV_BATTERY_TYPE_LIPO",),
    "MAV_SYS_STATUS_SENSOR": (
        "MAV_SYS_STATUS_SENSOR_3D_GYRO", "MAV_SYS_STATUS_SENSOR_3D_ACCEL", "MAV_SYS_STATUS_SENSOR_3D_MAG",
        "MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE", "MAV_SYS_STATUS_SENSOR_GPS",
        "MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL", "MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION",
        "MAV_SYS_STATUS_SENSOR_YAW_POSITION", "MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL",
        "MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL", "MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS",
        "MAV_SYS_STATUS_GEOFENCE", "MAV_SYS_STATUS_AHRS", "MAV_SYS_STATUS_SENSOR_BATTERY",
        "MAV_SYS_STATUS_PREARM_CHECK"),
    "MAV_PROTOCOL_CAPABILITY": (
        "MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT", "MAV_PROTOCOL_CAPABILITY_COMMAND_INT",
        "MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE", "MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET",
        "MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED", "MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT",
        "MAV_PROTOCOL_CAPABILITY_MAVLINK2",
        "MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST"),
    "FIRMWARE_VERSION_TYPE": ("FIRMWARE_VERSION_TYPE_OFFICIAL",),
    "FAILURE_UNIT": ("FAILURE_UNIT_SYSTEM_MOTOR",),
    "FAILURE_TYPE": ("FAILURE_TYPE_OK", "FAILURE_TYPE_OFF"),
    "MAV_MISSION_TYPE": ("MAV_MISSION_TYPE_MISSION",),
    "MAV_FTP_OPCODE": ("MAV_FTP_OPCODE_ACK", "MAV_FTP_OPCODE_NAK"),
    "MAV_FTP_ERR": ("MAV_FTP_ERR_FILENOTFOUND",),
}
ENUMS_PATH = HERE.parent / "enums.py"

# The project's message-id block. all.xml marks 52100..59999 as the next range to
# allocate, handed out upward from 52100, so its top end is the last to be taken;
# storm32 starts at 60000. Ids > 255: these messages are MAVLink 2 only.
ID_BLOCK = range(59900, 59950)
SWARMDROP_STATE_ID = 59900
SWARMDROP_TICK_ID = 59901
SWARMDROP_PLAN_ID = 59902
SWARMDROP_SLOTS_ID = 59903
PLAN_WAYPOINTS_MAX = 8
"""Centre waypoints one SWARMDROP_PLAN carries."""
SLOTS_PER_MESSAGE = 200
"""Vehicles one SWARMDROP_SLOTS carries (a fleet of up to 250 needs two)."""

_ID_COMMENT = f"""
      swarmdrop message ids: the block {ID_BLOCK.start}-{ID_BLOCK.stop - 1} (SWARMDROP_STATE {SWARMDROP_STATE_ID},
      SWARMDROP_TICK {SWARMDROP_TICK_ID}). pymavlink's all.xml leaves 52100-59999 unallocated and
      allocates new dialect ranges upward from 52100, so the top of that gap is the last to be
      taken (storm32 starts at 60000). generate.py checks that no message of all.xml or of the
      files it includes has an id in the block. Ids above 255 make these messages MAVLink 2 only.
    """
_HEADER_COMMENT = """
  GENERATED by companion/link/msgdef/generate.py - do not edit.
  The common messages are copied from pymavlink's dialects/v20/common.xml (and its includes)
  with the field attributes enum/display removed (they do not enter CRC_EXTRA).
  """


class GenerateError(RuntimeError):
    """The dialect cannot be generated consistently (missing source, id clash, CRC mismatch)."""


def pymavlink_v20_dir() -> Path:
    """Directory of pymavlink's shipped MAVLink 2 XML definitions and generated modules."""
    import pymavlink

    return Path(pymavlink.__file__).resolve().parent / "dialects" / "v20"


def parse_with_includes(path: Path) -> list[ET.Element]:
    """Root elements of an XML definition file and, breadth first, of every file it includes.

    Raises:
        GenerateError: if a file or an included file does not exist.
    """
    roots, seen, queue = [], set(), [path.resolve()]
    while queue:
        p = queue.pop(0)
        if p in seen:
            continue
        seen.add(p)
        if not p.is_file():
            raise GenerateError(f"MAVLink definition file not found: {p}")
        root = ET.parse(p).getroot()
        roots.append(root)
        queue.extend((p.parent / (inc.text or "").strip()).resolve() for inc in root.findall("include"))
    return roots


def all_xml_message_ids() -> dict[int, str]:
    """Every message id -> name defined by pymavlink's all.xml and the files it includes."""
    ids: dict[int, str] = {}
    for root in parse_with_includes(pymavlink_v20_dir() / "all.xml"):
        for m in root.iter("message"):
            ids[int(m.get("id", "-1"))] = m.get("name", "")
    return ids


def copy_common_messages() -> tuple[str, list[ET.Element]]:
    """Deep copies of the COMMON_MESSAGES elements (sorted by id) and common.xml's <version>.

    The version matters: mavgen uses it as HEARTBEAT.mavlink_version's constant.

    Raises:
        GenerateError: if a message is missing or has another name than expected.
    """
    roots = parse_with_includes(pymavlink_v20_dir() / "common.xml")
    version = roots[0].findtext("version")
    if version is None:
        raise GenerateError("common.xml has no <version>")
    found = {int(m.get("id", "-1")): m for root in roots for m in root.iter("message")}
    out = []
    for msgid, name in sorted(COMMON_MESSAGES.items()):
        src = found.get(msgid)
        if src is None or src.get("name") != name:
            raise GenerateError(f"common.xml: message {msgid} is {src.get('name') if src is not None else None}, "
                                f"expected {name}")
        m = copy.deepcopy(src)
        for field in m.iter("field"):
            for attr in STRIPPED_FIELD_ATTRS:
                field.attrib.pop(attr, None)
        out.append(m)
    return version.strip(), out


def _sub(parent: ET.Element, tag: str, text: str | None = None, **attrs: str) -> ET.Element:
    el = ET.SubElement(parent, tag, attrs)
    el.text = text
    return el


def _project_enums(enums: ET.Element) -> None:
    flags = _sub(enums, "enum", name="SWARMDROP_STATE_FLAGS", bitmask="true")
    _sub(flags, "description", "SWARMDROP_STATE.flags bits.")
    for value, name, desc in (
            (1, "ASSEMBLED", "The vehicle has reached its assembly slot at least once."),
            (2, "OWN_STATE_VALID", "The position, velocity and attitude fields are valid (else ignore them)."),
            (4, "READY", "The vehicle is ready to start the transit at t_go."),
            (8, "ID_CONFLICT", "Another sender has claimed this vehicle's id lately (docs/swarm.md)."),
            (16, "HANDED_OVER", "An ABORT plan handed the vehicle to its autopilot's own Hold: its agent "
                                "commands nothing.")):
        e = _sub(flags, "entry", value=str(value), name=f"SWARMDROP_STATE_FLAGS_{name}")
        _sub(e, "description", desc)
    phase = _sub(enums, "enum", name="SWARMDROP_PHASE")
    _sub(phase, "description", "Mission phase of a vehicle (the values of companion.agent.Phase, docs/agent.md).")
    for value, name, desc in (
            (0, "LAUNCH", "On the carrier or not yet released (also: unknown)."),
            (1, "STABILISE", "Released, recovering a level hover."),
            (2, "ASSEMBLE", "Flying to its slot of the formation."),
            (3, "TRANSIT", "Flying the mission path in formation (after t_go)."),
            (4, "HOVER", "Holding the formation at the last waypoint."),
            (5, "LAND", "Landing."),
            (6, "FAILED", "Lost control (e.g. a rotor failed): avoid it, leave it out of consensus.")):
        e = _sub(phase, "entry", value=str(value), name=f"SWARMDROP_PHASE_{name}")
        _sub(e, "description", desc)
    cmd = _sub(enums, "enum", name="SWARMDROP_COMMAND")
    _sub(cmd, "description", "The operator command a SWARMDROP_PLAN was made by (docs/swarm.md, \"Swarm commands\").")
    for value, name, desc in (
            (0, "NONE", "The mission's own plan (no command yet)."),
            (1, "HOLD", "The formation centre stops where it is; the formation is kept."),
            (2, "RESUME", "The centre goes on along the path it was held on."),
            (3, "GOTO", "The centre flies new waypoints at a new speed."),
            (4, "FORMATION", "A new shape, radius, spacing or rotation."),
            (5, "EXCLUDE", "Vehicles leave consensus (hold or land); the others close the gap."),
            (6, "REJOIN", "Excluded vehicles come back."),
            (7, "LAND", "All or some vehicles land, staggered."),
            (8, "RTL", "The formation flies back to the launch area, then lands."),
            (9, "ABORT", "Every agent hands its vehicle to the autopilot's own Hold/Loiter now.")):
        e = _sub(cmd, "entry", value=str(value), name=f"SWARMDROP_COMMAND_{name}")
        _sub(e, "description", desc)
    shape = _sub(enums, "enum", name="SWARMDROP_SHAPE")
    _sub(shape, "description", "Formation shapes (companion/control/shapes.py).")
    for value, name, desc in (
            (0, "CIRCLE", "A horizontal circle of radius_m."),
            (1, "LINE", "A horizontal line across the direction of travel, spacing_m apart."),
            (2, "GRID", "A horizontal square grid, spacing_m apart."),
            (3, "WEDGE", "A V opening backwards, spacing_m apart along each arm."),
            (4, "SHELL", "A sphere of radius_m (3-D).")):
        e = _sub(shape, "entry", value=str(value), name=f"SWARMDROP_SHAPE_{name}")
        _sub(e, "description", desc)
    pf = _sub(enums, "enum", name="SWARMDROP_PLAN_FLAGS", bitmask="true")
    _sub(pf, "description", "SWARMDROP_PLAN.flags bits.")
    for value, name, desc in (
            (1, "HOLD", "The centre holds at the first waypoint."),
            (2, "LAND_AT_END", "Every active vehicle lands when the centre reaches the last waypoint (RTL)."),
            (4, "ABORT", "Every agent hands its vehicle to the autopilot's Hold/Loiter and commands nothing."),
            (8, "EXCLUDED_LAND", "Excluded vehicles land (else they hold where they are).")):
        e = _sub(pf, "entry", value=str(value), name=f"SWARMDROP_PLAN_FLAGS_{name}")
        _sub(e, "description", desc)


def _project_messages(messages: ET.Element) -> None:
    messages.append(ET.Comment(_ID_COMMENT))
    st = _sub(messages, "message", id=str(SWARMDROP_STATE_ID), name="SWARMDROP_STATE")
    _sub(st, "description",
         "One vehicle's state, broadcast to its swarm peers. Position and velocity are in the mission "
         "NED frame shared by the swarm, not in the autopilot's local frame (every EKF has its own origin).")
    for ftype, name, units, desc in (
            ("uint64_t", "time_usec", "us", "Timestamp (UNIX epoch time, GNSS) at which the state was measured."),
            ("uint64_t", "t_go_usec", "us", "The sender's current proposal or adopted value of the swarm's transit "
                                            "start time t_go (UNIX epoch time). 0: none yet."),
            ("float", "x", "m", "X position (north), mission NED frame."),
            ("float", "y", "m", "Y position (east), mission NED frame."),
            ("float", "z", "m", "Z position (down), mission NED frame."),
            ("float", "vx", "m/s", "X velocity (north), mission NED frame."),
            ("float", "vy", "m/s", "Y velocity (east), mission NED frame."),
            ("float", "vz", "m/s", "Z velocity (down), mission NED frame."),
            ("float[4]", "q", None, "Attitude quaternion (w, x, y, z), NED to body FRD; null rotation (1, 0, 0, 0).")):
        attrs = {"type": ftype, "name": name} | ({"units": units} if units else {})
        _sub(st, "field", desc, **attrs)
    _sub(st, "field", "Mission phase.", type="uint8_t", name="phase", enum="SWARMDROP_PHASE")
    _sub(st, "field", "State flags.", type="uint8_t", name="flags", enum="SWARMDROP_STATE_FLAGS", display="bitmask")
    _sub(st, "field", "0-based index of the vehicle in the mission (its MAVLink system id may differ).",
         type="uint8_t", name="vehicle_id")
    _sub(st, "extensions")
    _sub(st, "field", "seq of the newest SWARMDROP_PLAN the vehicle has applied (0: the mission's own plan).",
         type="uint32_t", name="plan_seq")
    tick = _sub(messages, "message", id=str(SWARMDROP_TICK_ID), name="SWARMDROP_TICK")
    _sub(tick, "description",
         "Sent by a simulated radio medium after its last delivery of one simulation tick: every peer message "
         "of that tick has been delivered. Simulation only; real radios never send it.")
    _sub(tick, "field", "Time of the tick whose deliveries are complete (UNIX epoch time, simulated).",
         type="uint64_t", name="time_usec", units="us")
    plan = _sub(messages, "message", id=str(SWARMDROP_PLAN_ID), name="SWARMDROP_PLAN")
    _sub(plan, "description",
         "The swarm's commanded plan: a whole snapshot made by the command source (an operator's console, a "
         "scenario schedule), applied by every agent at effective_usec. The newest seq wins: agents relay the "
         "newest plan they hold, and a stale or reordered one never undoes a newer one (docs/swarm.md).")
    for ftype, name, units, desc in (
            ("uint64_t", "effective_usec", "us", "When every agent applies the plan (UNIX epoch time, as SWARMDROP_STATE)."),
            ("uint32_t", "seq", None, "Plan number, increasing; 0 is never sent (the mission's own plan)."),
            (f"float[{3 * PLAN_WAYPOINTS_MAX}]", "waypoints", "m", "Formation-centre waypoints x, y, z (mission NED), "
                                                                   "the first being the centre at effective_usec."),
            ("float", "speed", "m/s", "Centre speed along the waypoints."),
            ("float", "radius", "m", "Circle or shell radius."),
            ("float", "spacing", "m", "Line, grid or wedge spacing."),
            ("float", "rotation", "rad", "Bearing of the shape's forward axis, clockwise from north (absolute: "
                                       "not relative to the mission's yaw or the direction of travel)."),
            ("float", "morph_time", "s", "The formation moves from its old slots to the new ones over this time."),
            ("uint8_t[32]", "excluded", None, "Bit k (byte k // 8, bit k % 8): vehicle k is excluded."),
            ("uint8_t[32]", "landing", None, "Bit k: vehicle k lands.")):
        attrs = {"type": ftype, "name": name} | ({"units": units} if units else {})
        _sub(plan, "field", desc, **attrs)
    _sub(plan, "field", "Command that made this plan.", type="uint8_t", name="kind", enum="SWARMDROP_COMMAND")
    _sub(plan, "field", "Number of waypoints used.", type="uint8_t", name="n_waypoints")
    _sub(plan, "field", "Formation shape.", type="uint8_t", name="shape", enum="SWARMDROP_SHAPE")
    _sub(plan, "field", "Plan flags.", type="uint8_t", name="flags", enum="SWARMDROP_PLAN_FLAGS", display="bitmask")
    _sub(plan, "field", "Vehicles in the mission (the slot table's length).", type="uint8_t", name="n_vehicles")
    _sub(plan, "extensions")
    _sub(plan, "field", "Velocity of the formation centre at effective_usec (mission NED); the centre's path "
         "blends from it (zero: from rest, as before this field; zeros are truncated on the wire).",
         type="float[3]", name="start_velocity", units="m/s")
    slots = _sub(messages, "message", id=str(SWARMDROP_SLOTS_ID), name="SWARMDROP_SLOTS")
    _sub(slots, "description",
         "The slot table of a SWARMDROP_PLAN (computed by its source: few crossings, little travel), in chunks: "
         "vehicles first .. first + count - 1. A plan applies once every chunk of its seq is held.")
    _sub(slots, "field", "seq of the plan this table belongs to.", type="uint32_t", name="seq")
    _sub(slots, "field", "First vehicle of this chunk.", type="uint8_t", name="first")
    _sub(slots, "field", "Vehicles in this chunk.", type="uint8_t", name="count")
    _sub(slots, "field", "Slot index of each vehicle (255: no slot, excluded).",
         type=f"uint8_t[{SLOTS_PER_MESSAGE}]", name="slot")


def check_ids(ids: dict[int, str] | None = None) -> None:
    """Check the project ids lie in ID_BLOCK and that all.xml uses no id of the block.

    Raises:
        GenerateError: on a clash or a project id outside the block.
    """
    ids = all_xml_message_ids() if ids is None else ids
    for own in (SWARMDROP_STATE_ID, SWARMDROP_TICK_ID, SWARMDROP_PLAN_ID, SWARMDROP_SLOTS_ID):
        if own not in ID_BLOCK:
            raise GenerateError(f"project message id {own} is outside {ID_BLOCK}")
    clash = sorted(i for i in ids if i in ID_BLOCK)
    if clash:
        raise GenerateError(f"all.xml uses ids of the swarmdrop block: {[(i, ids[i]) for i in clash]}")


def dialect_xml() -> str:
    """The full text of swarmdrop.xml (deterministic for a given pymavlink)."""
    check_ids()
    version, common = copy_common_messages()
    root = ET.Element("mavlink")
    root.append(ET.Comment(_HEADER_COMMENT))
    _sub(root, "version", version)
    _project_enums(_sub(root, "enums"))
    messages = _sub(root, "messages")
    messages.extend(common)
    _project_messages(messages)
    ET.indent(root, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _load_module(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise GenerateError(f"cannot load {path} as a module")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def check_crc_extras(py_path: Path) -> None:
    """Check every copied common message of a generated module has pymavlink common's CRC_EXTRA.

    Raises:
        GenerateError: on any difference (the copy is then not wire compatible).
    """
    from pymavlink.dialects.v20 import common

    gen = _load_module(py_path, f"_swarmdrop_check_{id(py_path)}")
    bad = [(i, gen.mavlink_map[i].crc_extra, common.mavlink_map[i].crc_extra)
           for i in COMMON_MESSAGES if gen.mavlink_map[i].crc_extra != common.mavlink_map[i].crc_extra]
    if bad:
        raise GenerateError(f"CRC_EXTRA differs from pymavlink common (id, ours, common): {bad}")


_ENUMS_HEADER = '''"""MAVLink values by name: the enums and message ids swarmdrop uses.

GENERATED by companion/link/msgdef/generate.py - do not edit (add a member to its ENUMS
and regenerate). Members keep their MAVLink names and values, copied from pymavlink's
common.xml (and its includes): MavCmd.MAV_CMD_NAV_TAKEOFF == 22 == pymavlink's
mavlink.MAV_CMD_NAV_TAKEOFF. Only the members the project uses are here, with some small
enums whole (values read off the wire then always have a name), so the import stays cheap.

MsgId holds every message of the swarmdrop dialect, and a few common messages that only
the SITL builds (with pymavlink) or that the signing layer names; those are marked, and
the lean codec over the swarmdrop dialect cannot encode them.

Every class is an IntEnum, bitmasks too: a member is an int wherever an int goes (struct
packing, dict keys, comparisons with received values), and `|` of members is a plain int.

Imports: enum only.
"""
from enum import IntEnum
'''
LINE_WIDTH = 132  # the project's ruff line length


def class_name(enum_name: str) -> str:
    """Python class name of a MAVLink enum: MAV_CMD -> MavCmd, GPS_FIX_TYPE -> GpsFixType."""
    return "".join(part.capitalize() for part in enum_name.split("_"))


def _summary(el: ET.Element | None, room: int) -> str:
    """The first sentence of an element's <description>, on one line of at most room characters."""
    text = " ".join((el.findtext("description") or "").split()) if el is not None else ""
    text = re.split(r"(?<!e\.g)(?<!i\.e)\.\s+(?=[A-Z])", text)[0].rstrip(".")
    return text if len(text) <= room else text[:max(room - 3, 0)].rstrip() + "..."


def _comment(code: str, el: ET.Element | None, deprecated: bool = False) -> str:
    room = LINE_WIDTH - len(code) - 4 - (13 if deprecated else 0)
    text = ("(deprecated) " if deprecated else "") + _summary(el, room)
    return f"{code}  # {text}" if text.strip() else code


def select_enums(roots: list[ET.Element]) -> list[tuple[str, ET.Element, list[tuple[str, int, ET.Element]], int]]:
    """The ENUMS selection out of parsed XML: (enum name, first <enum> element, members
    (name, value, <entry>), number of members the enum has), in ENUMS order, members in XML order.

    Raises:
        GenerateError: an enum or a listed member does not exist, or two selected members
            share a value (an IntEnum would make the second an alias of the first).
    """
    found: dict[str, list[ET.Element]] = {}
    for root in roots:
        for e in root.iter("enum"):
            found.setdefault(e.get("name", ""), []).append(e)
    out = []
    for name, wanted in ENUMS.items():
        if name not in found:
            raise GenerateError(f"enum {name} is not in common.xml or its includes")
        entries = {x.get("name", ""): x for e in found[name] for x in e.findall("entry")}
        names = list(entries) if wanted is ALL else list(wanted)
        missing = [m for m in names if m not in entries]
        if missing:
            raise GenerateError(f"enum {name} has no member {missing}")
        members = [(m, int(entries[m].get("value", ""), 0), entries[m]) for m in names]
        values = [v for _, v, _ in members]
        if len(set(values)) != len(values):
            raise GenerateError(f"enum {name}: selected members share values {sorted(values)}")
        out.append((name, found[name][0], members, len(entries)))
    return out


def message_ids(dialect_xml_text: str, roots: list[ET.Element]) -> list[tuple[str, int, bool]]:
    """(name, id, in the dialect) of every message of the dialect and of NAMED_ONLY_MESSAGES, by id.

    Raises:
        GenerateError: a NAMED_ONLY_MESSAGES entry is not that common message, or is in the dialect.
    """
    ids = {int(m.get("id", "-1")): m.get("name", "") for m in ET.fromstring(dialect_xml_text).iter("message")}
    common = {int(m.get("id", "-1")): m.get("name", "") for root in roots for m in root.iter("message")}
    out = [(name, msgid, True) for msgid, name in ids.items()]
    for msgid, name in NAMED_ONLY_MESSAGES.items():
        if common.get(msgid) != name or msgid in ids:
            raise GenerateError(f"NAMED_ONLY_MESSAGES: {msgid} {name} is {common.get(msgid)} in common.xml"
                                f"{' and in the dialect' if msgid in ids else ''}")
        out.append((name, msgid, False))
    return sorted(out, key=lambda t: t[1])


def enums_source(dialect_xml_text: str) -> str:
    """The full text of companion/link/enums.py for a dialect XML (deterministic).

    Raises:
        GenerateError: see select_enums and message_ids.
    """
    roots = parse_with_includes(pymavlink_v20_dir() / "common.xml")
    out = [_ENUMS_HEADER.rstrip("\n")]
    classes = []
    for name, enum_el, members, total in select_enums(roots):
        cls = class_name(name)
        classes.append((name, cls))
        head = f"{name}{' (bitmask)' if enum_el.get('bitmask') == 'true' else ''}: " + (
            f"all {total} members" if len(members) == total else f"{len(members)} of its {total} members")
        text = _summary(enum_el, LINE_WIDTH - len(head) - 14).replace("\\", "/").replace('"', "'")
        doc = f"{head}. {text}" if text else head
        out += ["", "", f"class {cls}(IntEnum):", f'    """{doc}{"" if doc.endswith(".") else "."}"""']
        out += [_comment(f"    {member} = {value}", entry, entry.find("deprecated") is not None)
                for member, value, entry in members]
    out += ["", "", "class MsgId(IntEnum):",
            '    """Message ids: every message of the swarmdrop dialect, and a few common ones it does not carry."""']
    for name, msgid, in_dialect in message_ids(dialect_xml_text, roots):
        code = f"    {name} = {msgid}"
        out.append(code if in_dialect else f"{code}  # not in the dialect: pymavlink common only")
    out += ["", "", "MAVLINK_ENUMS: dict[str, type[IntEnum]] = {", *(f'    "{n}": {c},' for n, c in classes), "}",
            '"""Each enum class by its MAVLink name."""', ""]
    return "\n".join(out)


def generate_enums(xml_path: Path, out_path: Path = ENUMS_PATH) -> Path:
    """Write companion/link/enums.py (or out_path) for the dialect XML at xml_path.

    Raises:
        GenerateError: see enums_source.
    """
    out_path.write_text(enums_source(xml_path.read_text(encoding="utf-8")), encoding="utf-8")
    return out_path


def generate(out_dir: Path = HERE) -> tuple[Path, Path]:
    """Write swarmdrop.xml and run mavgen (Python, wire protocol 2.0) to write swarmdrop.py.

    Returns:
        (xml path, py path) in out_dir.
    Raises:
        GenerateError: if the sources are inconsistent or mavgen fails.
    """
    from pymavlink.generator import mavgen

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    xml_path, py_path = out_dir / f"{DIALECT}.xml", out_dir / f"{DIALECT}.py"
    xml_path.write_text(dialect_xml(), encoding="utf-8")
    opts = mavgen.Opts(str(out_dir / DIALECT), wire_protocol="2.0", language="Python", validate=True)
    chatter = io.StringIO()  # mavgen prints progress; show it only when it fails
    with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
        ok = mavgen.mavgen(opts, [str(xml_path)])
    if not ok or not py_path.is_file():
        raise GenerateError(f"mavgen failed:\n{chatter.getvalue()}")
    check_crc_extras(py_path)
    return xml_path, py_path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE,
                    help="output directory (default: this package; enums.py then goes to companion/link/)")
    ap.add_argument("--check", action="store_true", help="regenerate in a temporary directory and compare")
    args = ap.parse_args(argv)
    enums_path = ENUMS_PATH if args.out.resolve() == HERE else args.out / ENUMS_PATH.name
    if args.check:
        with tempfile.TemporaryDirectory() as tmp:
            xml_path, py_path = generate(Path(tmp))
            fresh = (xml_path, py_path, generate_enums(xml_path, Path(tmp) / ENUMS_PATH.name))
            stale = [p.name for p, committed in zip(fresh, (args.out / xml_path.name, args.out / py_path.name, enums_path))
                     if not committed.is_file() or not filecmp.cmp(p, committed, shallow=False)]
        if stale:
            print(f"stale generated files: {stale} (run python -m companion.link.msgdef.generate)", file=sys.stderr)
            return 1
        print("generated dialect and enums are up to date")
        return 0
    xml_path, py_path = generate(args.out)
    for p in (xml_path, py_path, generate_enums(xml_path, enums_path)):
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
