"""The localization settings of a command (``mmpa localize``, ``mmpa navigate``, ``mmpa
benchmark localization``), layered as every mmpa command's config is
(:mod:`mmpa.core.config`), lowest first:

1. the defaults in code (the command's pydantic model, a
   :class:`~mmpa.localization.settings.LocalizationConfig`);
2. the robot file's ``localization`` section (``mmpa --robot FILE``;
   :func:`~mmpa.robot.robot_file.robot_localization`);
3. the ``--config`` YAML file;
4. the command's own options (``--method``, ``--seed``, ...: those given);
5. ``--set key=value`` (``--set amcl.alpha1=0.05``, ``--set method=hector``).

Errors are :class:`~mmpa.core.errors.ConfigError` naming the file (robot file or config) and
the key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from mmpa.core.config import apply_overrides
from mmpa.core.errors import ConfigError
from mmpa.core.yamlio import load_yaml
from mmpa.localization.settings import LocalizationConfig
from mmpa.robot.robot_file import robot_localization

__all__ = ["LocalizationConfig", "check_robot_localization", "load_localization_config"]

M = TypeVar("M", bound=BaseModel)


def _errors(e: ValidationError, prefix: str = "") -> str:
    out = []
    for err in e.errors():
        loc = ".".join(str(x) for x in err["loc"])
        out.append(f"{prefix}{loc}: {err['msg']}" if loc else f"{prefix}{err['msg']}")
    return "; ".join(out)


def check_robot_localization(robot_file: str | Path | None) -> dict[str, Any]:
    """The ``localization`` section of ``robot_file`` (None: no robot file), checked against
    :class:`LocalizationConfig`; a malformed one is a ConfigError naming the file and key
    (``robot.yaml: localization.amcl.alpha1: Input should be greater than or equal to 0``)."""
    if robot_file is None:
        return {}
    section = robot_localization(robot_file) or {}
    try:
        LocalizationConfig.model_validate(section)
    except ValidationError as e:
        raise ConfigError(f"{robot_file}: {_errors(e, 'localization.')}") from None
    return section


def _merge(base: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in new.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _plain(v: Any) -> Any:
    """``v`` as YAML-able values (models as dicts, tuples as lists)."""
    if isinstance(v, BaseModel):
        return v.model_dump(mode="json", exclude_unset=True)
    if isinstance(v, tuple | list):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    return v


def load_localization_config(
    model: type[M],
    robot_file: str | Path | None = None,
    config_file: str | Path | None = None,
    options: dict[str, Any] | None = None,
    overrides: list[str] | None = None,
) -> M:
    """``model`` (a :class:`LocalizationConfig` with a command's own fields) from the layers
    of the module docstring; ``options``: the command's options that were given (None
    values are left out)."""
    data: dict[str, Any] = _merge({}, check_robot_localization(robot_file))
    if config_file is not None:
        loaded = load_yaml(config_file)
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, dict):
            raise ConfigError(f"{config_file}: a config file must be a YAML mapping")
        data = _merge(data, loaded)
    given = {k: _plain(v) for k, v in (options or {}).items() if v is not None}
    data = _merge(data, given)
    data = apply_overrides(data, overrides or [])
    try:
        return model.model_validate(data)
    except ValidationError as e:
        where = f"{config_file}: " if config_file is not None else ""
        raise ConfigError(f"invalid configuration: {where}{_errors(e)}") from None
