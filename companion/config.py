"""YAML loading with validation errors that name the path and the reason.

Every config object is a pydantic dataclass with extra="forbid", so an unknown
key is an error, not a silently ignored typo. Numbers must be finite everywhere
(NaN and infinity are refused), and loaded data is validated strictly: `true` is
not an integer, `1` is not a boolean, `1.5` (or `2.0`) is not an integer, `"3"` is
not a number (docs/scenario.md, "What a config may hold").
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import ConfigDict, TypeAdapter, ValidationError

T = TypeVar("T")

STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
"""The pydantic config of every config dataclass: unknown keys are errors, values immutable,
every float finite (also when a dataclass is built in code)."""

SEED_MAX = 2**63 - 1
"""Largest random seed (seeds are non-negative and fit a signed 64-bit integer)."""

CONFIG_VERSION = 2
"""Schema version of swarmdrop's YAML files (scenarios, missions, SITL configs); a file says
which it was written for with a top-level `version:` (absent: the current one). Version 2
moved the SITL config's world (vehicle count, seed, airframe, gains, carrier, ground,
wind, estimator, faults, home, launch, swarm link) into its `scenario:` section, the
scenario schema; scenarios themselves are unchanged from version 1 (docs/scenario.md,
"Config versions")."""


def check_version(version: Any) -> int:
    """A file's `version:` value, checked (a pydantic field validator calls it).

    Raises:
        ValueError: not a whole number from 1 to CONFIG_VERSION; a newer one says to upgrade.
    """
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise ValueError(f"must be a whole number from 1 to {CONFIG_VERSION} (got {version!r})")
    if version > CONFIG_VERSION:
        raise ValueError(f"this file is written for a newer swarmdrop (config version {version}); this one reads "
                         f"versions up to {CONFIG_VERSION}: upgrade swarmdrop")
    return version


class ConfigError(ValueError):
    """A config file could not be read or did not validate; the message names the
    file, the dotted path of each offending key and the reason."""


_REASONS = {
    "unexpected_keyword_argument": "unknown key",
    "extra_forbidden": "unknown key",
    "finite_number": "must be a finite number (NaN and infinity are refused)",
    "int_type": "must be a whole number written without a decimal point (true/false and 2.0 are not)",
    "int_from_float": "must be a whole number written without a decimal point (true/false and 2.0 are not)",
    "bool_type": "must be true or false (1, 0 and strings are not)",
    "float_type": "must be a number (true/false and quoted strings are not; YAML reads 1e3 as a string: write 1.0e3)",
}


_COUNTS = {1: "one", 2: "two", 3: "three", 4: "four", 6: "six"}
_AXES = {"_ned_m": " x, y, z (NED, m)", "_ned_mps": " x, y, z (NED, m/s)", "_ned_mps2": " x, y, z (NED, m/s^2)",
         "_wxyz": " w, x, y, z"}
"""What the items of a fixed-length tuple are, by the suffix of its field's name."""


def _tuple_length(path: tuple, expected: int, got: Any) -> str:
    """The reason for a fixed-length tuple (a point, a quaternion) given the wrong number of
    items: "a waypoint needs three numbers x, y, z (NED, m), got 2"."""
    field = next((str(p) for p in reversed(path) if isinstance(p, str)), "")
    names = next((text for suffix, text in _AXES.items() if field.endswith(suffix)), "")
    items = got if isinstance(got, (list, tuple)) else []
    kind = "numbers" if all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in items) else "items"
    what = "a waypoint needs" if field == "waypoints_ned_m" and path and isinstance(path[-1], int) else "needs"
    shown = repr(list(items))
    return (f"{what} {_COUNTS.get(expected, str(expected))} {kind}{names}, got {len(items)}"
            + (f": {shown}" if items and len(shown) <= 80 else ""))


def _format_errors(source: str, err: ValidationError) -> str:
    errors = err.errors()
    # A tuple with too few items gives one "missing" error per absent position (path ...k, 1
    # and ...k, 2: "Field required"): one line for the tuple, naming what it needs, instead.
    short: dict[tuple, tuple[int, Any]] = {}
    for e in errors:
        loc = tuple(e["loc"])
        if e["type"] == "missing" and loc and isinstance(loc[-1], int) and isinstance(e.get("input"), (list, tuple)):
            need, _ = short.get(loc[:-1], (0, None))
            short[loc[:-1]] = (max(need, loc[-1] + 1), e["input"])
    lines: list[str] = []
    told: set[tuple] = set()
    for e in errors:
        loc = tuple(e["loc"])
        got = e.get("input")
        if loc[:-1] in short and e["type"] == "missing" and loc and isinstance(loc[-1], int):
            if loc[:-1] not in told:
                told.add(loc[:-1])
                need, got = short[loc[:-1]]
                lines.append(f"  {'.'.join(str(p) for p in loc[:-1])}: {_tuple_length(loc[:-1], need, got)}")
            continue
        path = ".".join(str(p) for p in loc) or "<root>"
        reason = _REASONS.get(e["type"], e["msg"])
        if e["type"] == "too_long" and isinstance(got, (list, tuple)) and str(e.get("ctx", {}).get("field_type")) == \
                "Tuple" and isinstance(e.get("ctx", {}).get("max_length"), int):
            reason = _tuple_length(loc, e["ctx"]["max_length"], got)
        if reason.startswith("Value error, "):  # a validator's own sentence
            reason = reason[len("Value error, "):]
        if e["type"] == "literal_error" and isinstance(got, bool):  # `mode: off` is read as false
            reason += " (YAML reads a bare on, off, yes or no as true or false: quote the word)"
        text = "" if isinstance(got, (dict, list, tuple)) or got is None else repr(got)
        shown = f" (got {text})" if text and len(text) <= 80 else ""  # (a whole section's repr says nothing)
        # (a whole-config validator's sentence names its own paths: no "<root>:" before it)
        lines.append(f"  {reason}{shown}" if not loc and e["type"] == "value_error" else f"  {path}: {reason}{shown}")
    return "\n".join([f"{source}: {len(lines)} invalid setting(s)", *lines])


def _plain(data: Any) -> Any:
    """data as JSON-ready values: mapping keys as strings, sequences as lists, other
    YAML scalars (dates, ...) as their text; floats (also NaN, inf) and ints unchanged."""
    if isinstance(data, dict):
        return {str(k): _plain(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [_plain(v) for v in data]
    if data is None or isinstance(data, (bool, int, float, str)):
        return data
    return str(data)


_ADAPTERS: dict[type, TypeAdapter] = {}


def _adapter(cls: type) -> TypeAdapter:
    """The (cached) pydantic adapter of a config class: building one costs milliseconds."""
    adapter = _ADAPTERS.get(cls)
    if adapter is None:
        adapter = _ADAPTERS[cls] = TypeAdapter(cls)
    return adapter


def validate(cls: type[T], data: Any, source: str = "<config>") -> T:
    """Validate plain data (as parsed from YAML) into the dataclass cls, strictly:
    numbers must be finite, integers and booleans must be written as such (JSON rules:
    a list is accepted where a tuple is expected, a mapping where a dataclass is).

    Raises:
        ConfigError: naming every invalid or unknown key by its dotted path.
    """
    text = json.dumps(_plain({} if data is None else data), allow_nan=True)
    try:
        return _adapter(cls).validate_json(text, strict=True)
    except ValidationError as err:
        raise ConfigError(_format_errors(source, err)) from None


def load_yaml(cls: type[T], path: str | Path) -> T:
    """Read a YAML file and validate it into cls.

    Raises:
        ConfigError: the file is missing or unreadable, is not YAML, or does not validate.
    """
    return validate(cls, read_yaml(path), str(path))


class _DuplicateKey(yaml.YAMLError):
    """A mapping that names one key twice (raised by _StrictLoader)."""

    def __init__(self, key: Any, line: int, first_line: int):
        super().__init__(f"duplicate key {key!r}")
        self.key, self.line, self.first_line = key, line, first_line


class _StrictLoader(yaml.SafeLoader):
    """yaml.SafeLoader that refuses a mapping naming one key twice (PyYAML keeps the last
    silently: `n_vehicles: 6` then `n_vehicles: 3` would fly 3). Keys brought in by a merge
    (`<<: *anchor`) may be overridden, as YAML intends."""

    def construct_mapping(self, node: yaml.Node, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=deep)
                try:
                    first = seen.get(key)
                except TypeError:  # an unhashable key: SafeLoader says so below
                    continue
                line = key_node.start_mark.line + 1
                if first is not None:
                    raise _DuplicateKey(key, line, first)
                seen[key] = line
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: str | Path) -> Any:
    """The parsed content of a YAML file (None for an empty file).

    Raises:
        ConfigError: the file is missing or unreadable, is not YAML, or names a key twice
            in one mapping (the key and both lines are named).
    """
    path = Path(path)
    try:
        return yaml.load(path.read_text(), Loader=_StrictLoader)  # (a SafeLoader: no arbitrary objects)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, not a config file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path}: cannot be read: {err}") from None
    except _DuplicateKey as err:
        raise ConfigError(f"{path}: line {err.line}: duplicate key {err.key!r} (already given on line "
                          f"{err.first_line} of the same mapping); YAML would keep only the last one: remove "
                          "one of them") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}") from None


MISSION_MISSING = ("a scenario or mission file must describe its mission in a `mission:` mapping (n_vehicles, "
                   "formation, waypoints_ned_m, ...; e.g. configs/small_6.yaml, docs/scenario.md): without one it "
                   "would fly a hidden default mission")


def mission_file_data(data: Any, source: str) -> dict:
    """A parsed scenario (or agent mission) file's top level as a mapping (an empty file: {}),
    for validation; require_mission then checks, after the values, that it has a mission.

    Raises:
        ConfigError: a top level that is not a mapping, or a `mission:` that is not one.
    """
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level")
    if "mission" in data and not isinstance(data["mission"], dict):
        what = "empty" if data["mission"] is None else f"a {type(data['mission']).__name__}, not a mapping"
        raise ConfigError(f"{source}: `mission:` is {what}: {MISSION_MISSING}")
    return data


def require_mission(data: dict, source: str) -> None:
    """Refuse a scenario (or agent mission) file without a `mission:` mapping: an empty file,
    or one without it, used to fly a hidden default mission. (Called once the file's values
    have validated, so that a bad value is reported as such first.)

    Raises:
        ConfigError: the file is empty, or has no `mission:` section (MISSION_MISSING).
    """
    if not data:
        raise ConfigError(f"{source}: the file is empty: {MISSION_MISSING}")
    if "mission" not in data:
        raise ConfigError(f"{source}: no `mission:` section: {MISSION_MISSING}")


def replace(obj: T, source: str = "arguments", **changes: Any) -> T:
    """dataclasses.replace for a config dataclass, with its validation errors as a ConfigError
    (e.g. a command-line override of a config value).

    Raises:
        ConfigError: naming each changed field that does not validate, and the reason.
    """
    try:
        return dataclasses.replace(obj, **changes)  # type: ignore[type-var]
    except ValidationError as err:
        raise ConfigError(_format_errors(source, err)) from None
