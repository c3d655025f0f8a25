"""Parameter values on the wire: how PARAM_VALUE / PARAM_SET carry integers.

MAVLink carries every parameter in a float32 ``param_value``. Autopilots disagree
on what that float means for an integer parameter:

* PX4 (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE): the four bytes of the
  int32 are reinterpreted as a float ("bytewise").
* ArduPilot: the integer is converted to a float by value ("C cast"); it does not
  advertise the capability bit, but every ArduPilot release does this.

Both the agent (reading MPC_THR_HOVER / MOT_THST_HOVER, setting GUID_OPTIONS) and
the SITL (serving its parameter table) encode and decode through here.
"""
from __future__ import annotations

import math
import struct
from typing import Literal

from companion.link.enums import MavParamType

# The names importers use (sim_bridge.sitl.params_table): the MavParamType members.
MAV_PARAM_TYPE_UINT8 = MavParamType.MAV_PARAM_TYPE_UINT8
MAV_PARAM_TYPE_INT8 = MavParamType.MAV_PARAM_TYPE_INT8
MAV_PARAM_TYPE_UINT16 = MavParamType.MAV_PARAM_TYPE_UINT16
MAV_PARAM_TYPE_INT16 = MavParamType.MAV_PARAM_TYPE_INT16
MAV_PARAM_TYPE_UINT32 = MavParamType.MAV_PARAM_TYPE_UINT32
MAV_PARAM_TYPE_INT32 = MavParamType.MAV_PARAM_TYPE_INT32
MAV_PARAM_TYPE_REAL32 = MavParamType.MAV_PARAM_TYPE_REAL32
INT_FORMATS: dict[int, str] = {
    MAV_PARAM_TYPE_UINT8: "<B", MAV_PARAM_TYPE_INT8: "<b", MAV_PARAM_TYPE_UINT16: "<H",
    MAV_PARAM_TYPE_INT16: "<h", MAV_PARAM_TYPE_UINT32: "<I", MAV_PARAM_TYPE_INT32: "<i",
}
Encoding = Literal["bytewise", "c_cast"]


def encode_param_value(value: float, param_type: int, encoding: Encoding = "bytewise") -> float:
    """Value -> the float carried in PARAM_VALUE/PARAM_SET.

    Raises:
        KeyError: unknown param_type. struct.error / ValueError: value does not fit.
    """
    if param_type == MAV_PARAM_TYPE_REAL32:
        return float(value)
    fmt = INT_FORMATS[param_type]
    if encoding == "c_cast":
        struct.pack(fmt, int(value))  # range check only
        return float(int(value))
    raw = struct.pack(fmt, int(value)).ljust(4, b"\x00")
    return struct.unpack("<f", raw)[0]


def decode_param_value(wire: float, param_type: int, encoding: Encoding = "bytewise") -> float:
    """Float from PARAM_SET/PARAM_VALUE -> value (inverse of encode_param_value).

    Raises:
        KeyError: unknown param_type. struct.error / ValueError / OverflowError: undecodable.
    """
    if param_type == MAV_PARAM_TYPE_REAL32:
        return float(wire)
    fmt = INT_FORMATS[param_type]
    if encoding == "c_cast":
        if not math.isfinite(wire):
            raise ValueError(f"integer parameter carried as {wire}")
        value = int(round(wire))
        struct.pack(fmt, value)  # range check
        return float(value)
    raw = struct.pack("<f", wire)[: struct.calcsize(fmt)]
    return float(struct.unpack(fmt, raw)[0])


def param_name(param_id) -> str:
    """PARAM_VALUE/PARAM_SET param_id (str or bytes, NUL-padded) -> name."""
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", "replace")
    return param_id.split("\x00", 1)[0]
