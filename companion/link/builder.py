"""Named-field message values: ``build(field=value, ...)`` -> the tuple ``Codec.encode_fields`` takes.

Why: a positional list such as ``[target_sysid, 1, 512, 0, msgid, 0, 0, 0, 0, 0, 0]`` hides
which number is which field (and a field added or moved upstream shifts them all silently),
while a pymavlink message object costs several microseconds to build and pack. A builder is
a function compiled once per message type, with one keyword-only parameter per field, that
returns the values in declaration order (the order of ``cls.fieldnames``, which is what
``Codec.encode_fields`` and ``MavEndpoint.queue_fields`` take): one plain Python call, and
a misspelt or unknown field raises ``TypeError`` naming it, as a positional argument does.

Defaults of the fields a call leaves out, decided per field type:

* fields the generated ``MAVLink.<name>_encode`` defaults (extension fields, and
  HEARTBEAT.mavlink_version = the dialect's version): that default, arrays as tuples;
* ``float`` fields ``param1`` .. ``param7`` (COMMAND_LONG, COMMAND_INT): NaN. MAV_CMD's
  definition reserves NaN in float params for "optional / use the default value" (e.g.
  PX4's take-off altitude from MIS_TAKEOFF_ALT), and MAVSDK sends unset params as NaN, so
  an omitted param never turns into a real 0 (a take-off to 0 m, a yaw of north);
* every other number: 0 (0.0 for float/double), what MAVLink 2's trailing-zero
  truncation makes of an absent field and pymavlink's own default for extensions;
* numeric arrays: a tuple of zeros of the array's length; ``char[n]``: ``b""`` (all NUL
  on the wire); a single ``char``: ``b"\\x00"``.

Values are not checked here: ``Codec.encode_fields`` raises ``EncodeError`` for a value
that does not fit its field.

Imports: stdlib only.
"""
from __future__ import annotations

import keyword
import math
import re
from collections.abc import Callable
from typing import Any

_COMMAND_PARAM = re.compile(r"param[1-7]")


def field_default(name: str, ftype: str, array_length: int) -> Any:
    """The value a builder uses for a field left out, when mavgen gives it no default.

    Args:
        name: the field's name.
        ftype: its MAVLink base type ("float", "uint8_t", "char", ...).
        array_length: 0 for a scalar, else the number of elements.
    Returns:
        NaN for a float command param (param1..param7), else zeros of the right shape,
        b"" for char[n], b"\\x00" for char.
    """
    if ftype == "char":
        return b"" if array_length else b"\x00"
    zero = 0.0 if ftype in ("float", "double") else 0
    if array_length:
        return (zero,) * array_length
    if ftype == "float" and _COMMAND_PARAM.fullmatch(name):
        return math.nan
    return zero


def compile_builder(cls: Any, encode_defaults: tuple) -> Callable[..., tuple]:
    """Compile the builder of one mavgen message class.

    Args:
        cls: the message class (fieldnames, fieldtypes, ordered_fieldnames, array_lengths, msgname).
        encode_defaults: ``MAVLink.<name>_encode.__defaults__`` (or ()), the defaults of
            the last fields in declaration order.
    Returns:
        ``build(*, <field>=<default>, ...) -> tuple`` of the values in declaration order.
        Its ``fields`` attribute is the field names in that order, ``defaults`` the dict
        of defaults; calling it with a positional argument or an unknown field name raises
        TypeError naming the message and the argument.
    Raises:
        ValueError: a field or message name is not a Python identifier (cannot happen with
            mavgen output, whose constructors use the same names).
    """
    names = list(cls.fieldnames)
    for n in (*names, cls.msgname):
        if not n.isidentifier() or keyword.iskeyword(n) or n.startswith("_"):
            raise ValueError(f"{cls.msgname}: {n!r} cannot be a keyword argument")
    wire = list(cls.ordered_fieldnames)
    defaults = {n: field_default(n, t, cls.array_lengths[wire.index(n)]) for n, t in zip(names, cls.fieldtypes)}
    for n, d in zip(names[len(names) - len(encode_defaults):], encode_defaults):
        defaults[n] = tuple(d) if isinstance(d, list) else d
    namespace = {f"_d{i}": defaults[n] for i, n in enumerate(names)}
    params = ", ".join(f"{n}=_d{i}" for i, n in enumerate(names))
    body = ", ".join(names) + ("," if len(names) == 1 else "")
    exec(f"def {cls.msgname}(*, {params}):\n    return ({body})\n", namespace)  # names checked above
    build = namespace[cls.msgname]
    build.__qualname__ = f"builder.{cls.msgname}"
    build.__module__ = __name__
    build.__doc__ = f"{cls.msgname} field values in declaration order, from keyword arguments (defaults: {defaults})."
    build.fields = tuple(names)
    build.defaults = defaults
    return build
