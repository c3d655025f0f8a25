"""companion/link/enums.py: the generated MAVLink names, checked against pymavlink as the
reference (every name and value), against the dialect (MsgId), against the generator
(the committed file is its output; --check notices a stale one), and for a light import."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common

from companion.link import enums
from companion.link.enums import MAVLINK_ENUMS, MavCmd, MsgId
from companion.link.msgdef import generate
from companion.link.msgdef import swarmdrop as sd

ROOT = Path(__file__).resolve().parents[1]


def _pymavlink_members(enum_name: str) -> dict[str, int]:
    """name -> value of every member of a pymavlink enum (without mavgen's *_ENUM_END)."""
    return {e.name: v for v, e in common.enums[enum_name].items() if not e.name.endswith("_ENUM_END")}


@pytest.mark.parametrize("enum_name", sorted(generate.ENUMS))
def test_every_member_has_pymavlinks_name_and_value(enum_name):
    cls = MAVLINK_ENUMS[enum_name]
    assert cls.__name__ == generate.class_name(enum_name)
    reference = _pymavlink_members(enum_name)
    assert len(cls) > 0
    for member in cls:
        assert getattr(common, member.name) == member.value, member  # pymavlink's mavlink.<NAME>
        assert common.enums[enum_name][member.value].name == member.name, member  # and its enums table
    wanted = generate.ENUMS[enum_name]
    expected = set(reference) if wanted is generate.ALL else set(wanted)
    assert {m.name for m in cls} == expected  # exactly the selection, no alias swallowed a member


def test_every_enum_class_is_listed_and_selected():
    classes = {name for name, obj in vars(enums).items()
               if isinstance(obj, type) and issubclass(obj, enums.IntEnum) and obj is not enums.IntEnum}
    assert classes == {generate.class_name(n) for n in generate.ENUMS} | {"MsgId"}
    assert set(MAVLINK_ENUMS) == set(generate.ENUMS)


def test_msgid_is_every_dialect_message_plus_the_named_only_ones():
    assert {m.value for m in MsgId} == set(sd.mavlink_map) | set(generate.NAMED_ONLY_MESSAGES)
    for m in MsgId:
        if m.value in sd.mavlink_map:
            assert sd.mavlink_map[m.value].msgname == m.name
            assert getattr(sd, f"MAVLINK_MSG_ID_{m.name}") == m.value
        else:  # only pymavlink's common carries it
            assert common.mavlink_map[m.value].msgname == m.name == generate.NAMED_ONLY_MESSAGES[m.value]
        if m.value in common.mavlink_map:
            assert getattr(common, f"MAVLINK_MSG_ID_{m.name}") == m.value
    assert MsgId.SWARMDROP_STATE == generate.SWARMDROP_STATE_ID and MsgId.SWARMDROP_TICK == generate.SWARMDROP_TICK_ID


def test_members_are_plain_ints_on_the_wire():
    # what the agent sends today as bare numbers, by name
    assert (MavCmd.MAV_CMD_DO_SET_MODE, MavCmd.MAV_CMD_COMPONENT_ARM_DISARM, MavCmd.MAV_CMD_NAV_TAKEOFF,
            MavCmd.MAV_CMD_SET_MESSAGE_INTERVAL, MavCmd.MAV_CMD_REQUEST_MESSAGE) == (176, 400, 22, 511, 512)
    assert (MsgId.ATTITUDE_QUATERNION, MsgId.LOCAL_POSITION_NED) == (31, 32)
    assert {MsgId.LOCAL_POSITION_NED: "x"}[32] == "x"
    assert enums.PositionTargetTypemask.POSITION_TARGET_TYPEMASK_YAW_IGNORE | 1 == 1025
    assert type(enums.MavModeFlag.MAV_MODE_FLAG_SAFETY_ARMED | enums.MavModeFlag.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) is int


def test_committed_file_is_what_the_generator_produces():
    committed_xml = (generate.HERE / "swarmdrop.xml").read_text(encoding="utf-8")
    assert generate.enums_source(committed_xml) == generate.ENUMS_PATH.read_text(encoding="utf-8"), \
        "companion/link/enums.py is stale: run python -m companion.link.msgdef.generate"


def test_check_mode_notices_a_stale_enums_file(tmp_path, capsys):
    for name in ("swarmdrop.xml", "swarmdrop.py"):
        shutil.copy(generate.HERE / name, tmp_path / name)
    shutil.copy(generate.ENUMS_PATH, tmp_path / "enums.py")
    assert generate.main(["--check", "--out", str(tmp_path)]) == 0
    text = (tmp_path / "enums.py").read_text(encoding="utf-8")
    (tmp_path / "enums.py").write_text(text.replace("MAV_CMD_NAV_TAKEOFF = 22", "MAV_CMD_NAV_TAKEOFF = 23"))
    assert generate.main(["--check", "--out", str(tmp_path)]) == 1
    assert "enums.py" in capsys.readouterr().err


def test_generator_refuses_what_it_cannot_name(monkeypatch):
    roots = generate.parse_with_includes(generate.pymavlink_v20_dir() / "common.xml")
    commands = generate.ENUMS["MAV_CMD"]
    monkeypatch.setitem(generate.ENUMS, "MAV_CMD", ("MAV_CMD_NAV_TAKEOFF", "MAV_CMD_NO_SUCH_THING"))
    with pytest.raises(generate.GenerateError, match="MAV_CMD_NO_SUCH_THING"):
        generate.select_enums(roots)
    monkeypatch.setitem(generate.ENUMS, "MAV_CMD", ("MAV_CMD_NAV_TAKEOFF", "MAV_CMD_NAV_TAKEOFF"))
    with pytest.raises(generate.GenerateError, match="share values"):
        generate.select_enums(roots)
    monkeypatch.setitem(generate.ENUMS, "MAV_CMD", commands)
    monkeypatch.setitem(generate.ENUMS, "MAV_NO_SUCH_ENUM", generate.ALL)
    with pytest.raises(generate.GenerateError, match="MAV_NO_SUCH_ENUM"):
        generate.select_enums(roots)
    xml = (generate.HERE / "swarmdrop.xml").read_text(encoding="utf-8")
    monkeypatch.setattr(generate, "NAMED_ONLY_MESSAGES", {147: "BATTERY_STATUS_TYPO"})
    with pytest.raises(generate.GenerateError, match="BATTERY_STATUS_TYPO"):
        generate.message_ids(xml, roots)
    monkeypatch.setattr(generate, "NAMED_ONLY_MESSAGES", {76: "COMMAND_LONG"})  # already in the dialect
    with pytest.raises(generate.GenerateError, match="in the dialect"):
        generate.message_ids(xml, roots)


def test_import_is_light():
    """The onboard import: no pymavlink, no numpy, nothing but enum and the packages."""
    code = ("import sys; before = set(sys.modules); import companion.link.enums; "
            "print(' '.join(sorted(set(sys.modules) - before)))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60, check=True)
    assert set(out.stdout.split()) <= {"companion", "companion.link", "companion.link.enums", "enum"}
