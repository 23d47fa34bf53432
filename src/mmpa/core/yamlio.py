"""Reading YAML from untrusted files: safe types only, no aliases, a size bound.

PyYAML's ``safe_load`` refuses ``!!python`` tags but expands aliases: a 2 KB "billion
laughs" document (anchors of lists of aliases of anchors ...) grows to gigabytes. Every
YAML mmpa reads from a file (task bundles, maps, reflector maps, scenes, configs, operator
scripts) goes through :func:`load_yaml`, which refuses any alias (``*name``) before it is
expanded, and any text longer than ``max_bytes``.
"""

from __future__ import annotations

import math
import sys
from numbers import Real
from pathlib import Path
from typing import Any

import yaml

from mmpa.core.errors import ConfigError

#: Largest YAML text read by default (bytes). mmpa's own files are a few KB.
MAX_YAML_BYTES = 4 * 1024 * 1024


class _NoAliasLoader(yaml.SafeLoader):
    """SafeLoader that raises on the first alias event instead of expanding it."""

    def compose_node(self, parent: Any, index: Any) -> Any:  # type: ignore[override]
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None,
                None,
                f"YAML alias *{event.anchor} is not accepted (aliases can expand without "
                "bound); write the value out",
                event.start_mark,
            )
        return super().compose_node(parent, index)


def load_yaml_text(text: str, what: str = "YAML text", max_bytes: int = MAX_YAML_BYTES) -> Any:
    """Parse ``text`` with safe types only and no aliases.

    Raises :class:`~mmpa.core.errors.ConfigError` naming ``what`` (a file name or a field) on a
    syntax error, an alias, or text longer than ``max_bytes``.
    """
    if len(text) > max_bytes:
        raise ConfigError(f"{what}: {len(text)} bytes of YAML, more than the {max_bytes} accepted")
    try:
        return yaml.load(text, Loader=_NoAliasLoader)  # a SafeLoader subclass
    except yaml.YAMLError as e:
        raise ConfigError(f"{what}: not valid YAML: {e}") from e
    except RecursionError:  # PyYAML's parser recurses once per nesting level
        raise ConfigError(
            f"{what}: YAML nested too deeply (more than Python's recursion limit of "
            f"{sys.getrecursionlimit()} levels)"
        ) from None


def load_yaml(path: str | Path, max_bytes: int = MAX_YAML_BYTES, what: str = "") -> Any:
    """Read and parse the YAML file ``path`` (see :func:`load_yaml_text`).

    The size is checked on disk before anything is read; errors name the file (and ``what``
    it is, e.g. "scene file": "cannot read scene file PATH").
    """
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > max_bytes:
            raise ConfigError(f"{p}: {size} bytes of YAML, more than the {max_bytes} accepted")
        raw = p.read_bytes()
    except OSError as e:
        kind = f"{what} " if what else ""
        raise ConfigError(f"cannot read {kind}{p}: {e.strerror or e}") from e
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{p}: not UTF-8 text ({e.reason} at byte {e.start})") from e
    return load_yaml_text(text, str(p), max_bytes)


def finite_number(value: Any, where: str) -> float:
    """``value`` read from YAML as a finite float; a bool, a string, NaN or inf is a
    :class:`~mmpa.core.errors.ConfigError` naming ``where`` (a file and field)."""
    if isinstance(value, bool) or not isinstance(value, Real):
        raise ConfigError(f"{where}: must be a number, got {value!r}")
    f = float(value)
    if not math.isfinite(f):
        raise ConfigError(f"{where}: must be finite, got {value!r}")
    return f
