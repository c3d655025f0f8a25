"""MAVLink values by name, never as bare numbers (issue 17, "one way for each thing").

Commands, results, frames, message ids and type masks are written by name
(companion/link/enums.py: ``MavCmd.MAV_CMD_NAV_TAKEOFF``, ``MsgId.HEARTBEAT``, ...): 22 says
nothing, and a slip of it is another valid command. This test reads the AST of every module
of PACKAGES (but the generated EXCLUDED ones) and fails on each int literal, naming
file:line, where a MAVLink value of those kinds goes.

The rule. A *checked field* is one of CHECKED_FIELDS (command, frame, result, msgid,
message_id, coordinate_frame, type_mask). An *int literal* is an int constant, signed or not
(``22``, ``-1``); True and False are not. An int literal is an offence when it is:

1. an argument of a call that names a checked field: a keyword argument ``command=``,
   ``frame=``, ... of any call; or the first positional argument of one of the project's
   helpers in HELPER_FIRST_ARG (``command(``, ``command_now(``, ``request_message(``,
   ``set_message_interval(``, ``queue_fields(``, ``encode_fields(``, ``builder(``,
   ``send(`` (VehicleLink.send), ``encode(`` (Codec.encode: a message goes there, never
   an id));
2. a positional argument of a message built field by field, at a checked field: pymavlink's
   ``MAVLink_<name>_message(...)``, ``<name>_encode(...)``, ``<name>_send(...)``
   (``command_long_send(target, 1, 400, ...)``: 400 is the command), or the items of a
   literal list or tuple of values given to ``queue_fields``/``encode_fields``/``send``
   after a message id written by name (``MsgId.X``, ``MAVLINK_MSG_ID_X``); arguments are
   matched to the message's fields in declaration order (the dialects: pymavlink's common
   and swarmdrop), up to the first ``*args``;
3. compared (``==``, ``!=``, ``in``, ``not in``; alone or in a literal tuple, list or set)
   with a name or attribute called like a checked field (``msgid == 32``,
   ``msg.result != 5``) or with ``get_msgId()``.

0 and 1 are no exception: there they are MAVLink values (HEARTBEAT and SYS_STATUS,
MAV_RESULT_ACCEPTED and TEMPORARILY_REJECTED, MAV_FRAME_GLOBAL and LOCAL_NED). The one
exception is type_mask 0, the empty bitmask ("ignore nothing"), which no member names.
Other places of numbers (a target_component, a param) are not checked.
"""
from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

from pymavlink.dialects.v20 import common

from companion.link.msgdef import swarmdrop as sd

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("companion", "sim_bridge")
"""The packages scanned (sim_bridge joins when the SITL speaks by name too)."""
EXCLUDED = frozenset({"companion/link/msgdef/swarmdrop.py", "companion/link/enums.py"})
"""Generated files: where the numbers are defined."""
CHECKED_FIELDS = frozenset({"command", "frame", "result", "msgid", "message_id", "coordinate_frame", "type_mask"})
HELPER_FIRST_ARG = {
    "command": "command", "command_now": "command", "_command_values": "command",
    "request_message": "msgid", "set_message_interval": "msgid", "queue_fields": "msgid", "encode_fields": "msgid",
    "builder": "msgid", "send": "msgid", "encode": "message",
}
"""Helpers whose first positional argument is a MAVLink value (or a message), and what it is."""
VALUE_LIST_HELPERS = ("queue_fields", "encode_fields", "send")
"""Helpers taking (message id, field values in declaration order, ...)."""
EMPTY_MASK_FIELDS = frozenset({"type_mask"})
"""Checked fields where 0 (no bit set) is allowed."""


def _message_fields() -> dict[str, tuple[str, ...]]:
    """Message name (upper case) -> its field names in declaration order (the constructors' order)."""
    out: dict[str, tuple[str, ...]] = {}
    for module in (common, sd):
        for cls in module.mavlink_map.values():
            out.setdefault(cls.msgname, tuple(cls.fieldnames))
    return out


FIELDS = _message_fields()


def _int_literal(node: ast.AST) -> int | None:
    """The value of an int literal (22, -1, +3), None for anything else (bool included)."""
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        inner = _int_literal(node.operand)
        return None if inner is None else (-inner if isinstance(node.op, ast.USub) else inner)
    if isinstance(node, ast.Constant) and type(node.value) is int:
        return node.value
    return None


def _called_name(call: ast.Call) -> str:
    f = call.func
    return f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""


def _message_of_builder_name(name: str) -> str | None:
    """COMMAND_LONG for MAVLink_command_long_message, command_long_send, command_long_encode."""
    if name.startswith("MAVLink_") and name.endswith("_message"):
        msg = name[len("MAVLink_"):-len("_message")].upper()
    elif name.endswith(("_send", "_encode")):
        msg = name.rsplit("_", 1)[0].upper()
    else:
        return None
    return msg if msg in FIELDS else None


def _message_of_id(node: ast.AST) -> str | None:
    """COMMAND_LONG for MsgId.COMMAND_LONG, md.MAVLINK_MSG_ID_COMMAND_LONG, MAVLINK_MSG_ID_COMMAND_LONG."""
    name = node.attr if isinstance(node, ast.Attribute) else node.id if isinstance(node, ast.Name) else ""
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "MsgId":
        return name if name in FIELDS else None
    if name.startswith("MAVLINK_MSG_ID_"):
        msg = name[len("MAVLINK_MSG_ID_"):]
        return msg if msg in FIELDS else None
    return None


def _offence(node: ast.AST, what: str) -> tuple[int, str] | None:
    """(line, text) if node is an int literal where `what` goes (type_mask 0 allowed)."""
    value = _int_literal(node)
    if value is None or (value == 0 and what in EMPTY_MASK_FIELDS):
        return None
    return node.lineno, f"{what} is the number {value}"


def _positional(args: list[ast.expr], fields: tuple[str, ...], where: str) -> Iterator[tuple[int, str]]:
    """Offences among positional args matched to fields (up to the first *args)."""
    for arg, name in zip(args, fields):
        if isinstance(arg, ast.Starred):
            return
        if name in CHECKED_FIELDS and (o := _offence(arg, name)) is not None:
            yield o[0], f"{where}: {o[1]}"


def _call_offences(call: ast.Call) -> Iterator[tuple[int, str]]:
    name = _called_name(call)
    for kw in call.keywords:  # rule 1, keywords
        if kw.arg in CHECKED_FIELDS and (o := _offence(kw.value, kw.arg)) is not None:
            yield o[0], f"{name}({kw.arg}=...): {o[1]}"
    what = HELPER_FIRST_ARG.get(name)  # rule 1, the helpers' first argument
    if what is not None and call.args and (o := _offence(call.args[0], what)) is not None:
        yield o[0], f"{name}(...): {o[1]}"
    msg = _message_of_builder_name(name)  # rule 2, a message built positionally
    if msg is not None:
        yield from _positional(call.args, FIELDS[msg], f"{name}(...)")
    if name in VALUE_LIST_HELPERS and len(call.args) >= 2 and isinstance(call.args[1], (ast.List, ast.Tuple)):
        msg = _message_of_id(call.args[0])
        if msg is not None:
            yield from _positional(call.args[1].elts, FIELDS[msg], f"{name}({msg}, [values])")


def _subject(node: ast.AST) -> str | None:
    """What a compared expression holds, if it is a checked field or get_msgId()."""
    if isinstance(node, ast.Name) and node.id in CHECKED_FIELDS:
        return node.id
    if isinstance(node, ast.Attribute) and node.attr in CHECKED_FIELDS:
        return node.attr
    if isinstance(node, ast.Call) and _called_name(node) == "get_msgId":
        return "msgid"
    return None


def _compare_offences(cmp: ast.Compare) -> Iterator[tuple[int, str]]:
    operands = [cmp.left, *cmp.comparators]
    for (a, b), op in zip(zip(operands, operands[1:]), cmp.ops):
        if not isinstance(op, (ast.Eq, ast.NotEq, ast.In, ast.NotIn)):
            continue
        for subject, other in ((a, b), (b, a)):
            what = _subject(subject)
            if what is None:
                continue
            items = other.elts if isinstance(other, (ast.Tuple, ast.List, ast.Set)) else [other]
            for item in items:
                if (o := _offence(item, what)) is not None:
                    yield o[0], f"comparison with {ast.unparse(subject)}: {o[1]}"


def offences_in(path: Path, label: str | None = None) -> list[str]:
    """Every offence in one file, as "label:line: what" (label: the path as given)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    found: set[tuple[int, str]] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            found.update(_call_offences(node))
        elif isinstance(node, ast.Compare):
            found.update(_compare_offences(node))
    return [f"{label or path}:{line}: {text}" for line, text in sorted(found)]


def scanned_files() -> list[Path]:
    return [p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))
            if p.relative_to(ROOT).as_posix() not in EXCLUDED]


def test_mavlink_values_are_written_by_name():
    files = scanned_files()
    assert len(files) > 20  # the packages are there
    bad = [o for p in files for o in offences_in(p, p.relative_to(ROOT).as_posix())]
    assert not bad, ("bare MAVLink numbers (write the member of companion/link/enums.py; add it to ENUMS in "
                     "companion/link/msgdef/generate.py and regenerate if it is missing):\n" + "\n".join(bad))


def test_the_generated_files_are_the_only_exclusions():
    assert all((ROOT / p).is_file() for p in EXCLUDED)
    assert PACKAGES[0] == "companion" and isinstance(PACKAGES, tuple)


PLANTED = '''\
v.command(176, [1.0])
v.command_now(400, p)
await v.request_message(242)
await v.set_message_interval(32, 0.02)
ep.queue_fields(84, values)
codec.encode_fields(0, values, 1, 191, 0)
build = codec.builder(76)
frame = codec.encode(5, 1, 1, 0)
v.send(MsgId.SET_POSITION_TARGET_LOCAL_NED, [ms, 2, 1, 1, 3, *f])
ep.queue_fields(md.MAVLINK_MSG_ID_COMMAND_LONG, (2, 1, 512, 0, 33.0))
m = mavlink.MAVLink_command_long_message(1, 1, 22, 0, 0, 0, 0, 0, 0, 0, 10.0)
c.mav.command_int_send(1, 1, 6, 520, 0, 0, 1, 0, 0, 0, 0, 0, 0)
c.mav.command_ack_send(400, 0)
x = build(command=511, param1=33)
y = f(frame=1, coordinate_frame=8, result=-1, msgid=+31, message_id=33, type_mask=3)
if msgid == 32 or m.get_msgId() != 0 or msg.result in (0, 1) or 245 == self.msgid:
    pass
'''
PLANTED_CLEAN = '''\
v.command(MavCmd.MAV_CMD_DO_SET_MODE, [1.0, 4.0])
v.send(MsgId.SET_POSITION_TARGET_LOCAL_NED, build(time_boot_ms=ms, target_system=2, target_component=1,
       coordinate_frame=MavFrame.MAV_FRAME_LOCAL_NED, type_mask=0))
ep.queue_fields(MsgId.SET_ATTITUDE_TARGET, [ms, 2, 1, 0, q, 0.0, 0.0, 0.0, 0.5])
m = mavlink.MAVLink_set_attitude_target_message(0, 1, 1, 0, [1, 0, 0, 0], 0, 0, 0, 0.5)
link.send(buf, addr)
name.encode()
ok = f(frame=frame_bytes, result=True) and frame[0] == 0xFD and len(frame) > 9 and count == 3
'''


def test_the_rule_finds_each_kind_of_offence_and_names_its_line(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text(PLANTED)
    found = offences_in(bad, "bad.py")
    lines = {int(o.split(":")[1]) for o in found}
    assert lines == set(range(1, 17)), "\n".join(found)
    text = "\n".join(found)
    for expected in ("bad.py:1: command(...): command is the number 176",
                     "bad.py:9: send(SET_POSITION_TARGET_LOCAL_NED, [values]): coordinate_frame is the number 1",
                     "bad.py:10: queue_fields(COMMAND_LONG, [values]): command is the number 512",
                     "bad.py:11: MAVLink_command_long_message(...): command is the number 22",
                     "bad.py:12: command_int_send(...): command is the number 520",
                     "bad.py:12: command_int_send(...): frame is the number 6",
                     "bad.py:13: command_ack_send(...): result is the number 0",
                     "bad.py:15: f(result=...): result is the number -1",
                     "bad.py:15: f(type_mask=...): type_mask is the number 3",
                     "bad.py:16: comparison with m.get_msgId(): msgid is the number 0",
                     "bad.py:16: comparison with msg.result: result is the number 1",
                     "bad.py:16: comparison with self.msgid: msgid is the number 245"):
        assert expected in text, text
    assert "type_mask is the number 3" in text and "bad.py:9: send(SET_POSITION_TARGET_LOCAL_NED, [values]): " \
        "type_mask is the number 3" in text
    clean = tmp_path / "clean.py"
    clean.write_text(PLANTED_CLEAN)
    assert offences_in(clean) == []
