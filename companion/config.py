"""YAML loading with validation errors that name the path and the reason.

Every config object is a pydantic dataclass with extra="forbid", so an unknown
key is an error, not a silently ignored typo.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import ConfigDict, TypeAdapter, ValidationError

T = TypeVar("T")

STRICT = ConfigDict(extra="forbid", frozen=True)
"""The pydantic config of every config dataclass: unknown keys are errors, values immutable."""


class ConfigError(ValueError):
    """A config file could not be read or did not validate; the message names the
    file, the dotted path of each offending key and the reason."""


def _format_errors(source: str, err: ValidationError) -> str:
    lines = [f"{source}: {err.error_count()} invalid setting(s)"]
    for e in err.errors():
        path = ".".join(str(p) for p in e["loc"]) or "<root>"
        reason = e["msg"]
        if e["type"] in ("unexpected_keyword_argument", "extra_forbidden"):
            reason = "unknown key"
        got = e.get("input")
        shown = "" if isinstance(got, (dict, list)) or got is None else f" (got {got!r})"
        lines.append(f"  {path}: {reason}{shown}")
    return "\n".join(lines)


def validate(cls: type[T], data: Any, source: str = "<config>") -> T:
    """Validate plain data (as parsed from YAML) into the dataclass cls.

    Raises:
        ConfigError: naming every invalid or unknown key by its dotted path.
    """
    try:
        return TypeAdapter(cls).validate_python({} if data is None else data)
    except ValidationError as err:
        raise ConfigError(_format_errors(source, err)) from None


def load_yaml(cls: type[T], path: str | Path) -> T:
    """Read a YAML file and validate it into cls.

    Raises:
        ConfigError: the file is missing, is not YAML, or does not validate.
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}") from None
    return validate(cls, data, str(path))
