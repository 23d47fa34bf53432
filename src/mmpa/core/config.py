"""Configuration plumbing: pydantic models, optional YAML files and ``--set key=value``.

Defaults live in code (each stage's pydantic model); a YAML file overrides some of them and
``--set a.b=value`` overrides single fields (the value is parsed as YAML, so ``3``, ``0.5``,
``true``, ``[1, 2]`` work). The final configuration is saved next to every result.

Setting a section's ``profile`` (``--set errors.profile=harsh``, what ``--profile`` does)
re-bases that section: its other fields, except ``seed``, are dropped so that the profile
supplies them, then later overrides apply on top. A saved ``config.yaml`` lists every field,
so loading it with another profile does what one expects.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from mmpa.core.errors import ConfigError
from mmpa.core.yamlio import load_yaml, load_yaml_text

M = TypeVar("M", bound=BaseModel)

__all__ = ["apply_overrides", "load_config", "save_config"]


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply ``key.sub=value`` strings to a nested dict (returns a new dict)."""
    out = yaml.safe_load(yaml.safe_dump(data))
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like key=value (e.g. seed=3)")
        key, raw = item.split("=", 1)
        parts = [p for p in key.strip().split(".") if p]
        if not parts:
            raise ConfigError(f"override {item!r} has an empty key")
        node = out
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                node[p] = {} if node.get(p) is None else node[p]
                if not isinstance(node[p], dict):
                    raise ConfigError(f"override {item!r}: {p!r} is not a section")
            node = node[p]
        value = load_yaml_text(raw, f"override {item!r}: the value")
        if parts[-1] == "profile" and len(parts) > 1:  # re-base the section (module doc)
            for k in [k for k in node if k not in ("seed", "profile")]:
                del node[k]
        node[parts[-1]] = value
    return out


def load_config(
    model: type[M], path: str | Path | None = None, overrides: list[str] | None = None
) -> M:
    """Defaults of ``model``, then the YAML file at ``path``, then ``overrides``."""
    # only what is set explicitly: sections with a profile fill the rest when validated
    data: dict[str, Any] = model().model_dump(mode="json", exclude_unset=True)
    if path is not None:
        loaded = load_yaml(path)  # no aliases, bounded size; errors name the file
        if not isinstance(loaded, dict):
            raise ConfigError(f"{path}: a config file must be a YAML mapping")
        data = _merge(data, loaded)
    data = apply_overrides(data, overrides or [])
    try:
        return model.model_validate(data)
    except ValidationError as e:
        lines = [f"  {'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors()]
        raise ConfigError("invalid configuration\n" + "\n".join(lines)) from None


def save_config(cfg: BaseModel, path: str | Path) -> None:
    """Write the final configuration as YAML."""
    Path(path).write_text(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False))


def _merge(base: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in new.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out
