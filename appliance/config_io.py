"""Load YAML files into typed, frozen, validated models; every error names the file and key path.

Config sections are pydantic models deriving from :class:`StrictModel` (unknown keys rejected,
immutable). ``load_model(path, Model)`` reads and validates a whole file; ``validate_model`` does the
same for data already read (for a section of a larger file, pass ``key_prefix``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from appliance.errors import ConfigError

ModelT = TypeVar("ModelT", bound=BaseModel)


class StrictModel(BaseModel):
    """Base of config models: unknown keys are errors and loaded values cannot change."""

    model_config = ConfigDict(extra="forbid", frozen=True)


def key_path(location: tuple[Any, ...], prefix: str = "") -> str:
    """``("views", "p", "K", 2)`` -> ``views.p.K[2]``."""
    text = prefix
    for part in location:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else str(part)
    return text or "(top level)"


def read_yaml(path: str | Path, error: type[Exception] = ConfigError) -> Any:
    """Read a YAML file with ``safe_load``; a missing or malformed file raises ``error`` naming it."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as err:
        raise error(f"{path}: file not found") from err
    except OSError as err:
        raise error(f"{path}: cannot read ({err.strerror or err})") from err
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(err, "problem", None) or str(err)
        raise error(f"{path}: not valid YAML{where}: {problem}") from err


def describe_validation_error(err: ValidationError, source: str, key_prefix: str = "") -> str:
    lines = []
    for item in err.errors(include_url=False):
        where = key_path(tuple(item["loc"]), key_prefix)
        got = item.get("input")
        shown = "" if isinstance(got, (dict, list)) or item["type"] == "missing" else f", got {got!r}"
        lines.append(f"{source}: {where}: {item['msg']}{shown}")
    return "\n".join(lines)


def validate_model(model: type[ModelT], data: Any, source: str, *, key_prefix: str = "",
                   error: type[Exception] = ConfigError) -> ModelT:
    """Validate ``data`` (already parsed) into ``model``; ``source`` names the file in messages."""
    if data is None:
        raise error(f"{source}: {key_prefix or 'file'} is empty")
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise error(describe_validation_error(err, source, key_prefix)) from err


def load_model(path: str | Path, model: type[ModelT], *, error: type[Exception] = ConfigError) -> ModelT:
    """Read ``path`` and validate it into ``model``."""
    return validate_model(model, read_yaml(path, error), str(path), error=error)


def project_root() -> Path:
    """The checkout's root (config/ lives there)."""
    return Path(__file__).resolve().parent.parent


def config_path(name: str) -> Path:
    """Path of a file shipped in ``config/``."""
    return project_root() / "config" / name
