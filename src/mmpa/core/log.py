"""Logging for mmpa: every module logs to ``logging.getLogger(__name__)`` (under ``mmpa``);
the CLI's ``-v`` / ``--log-level`` turn it on with a rich handler on stderr. A library user
configures ``logging`` as usual; mmpa adds no handler of its own unless asked."""

from __future__ import annotations

import logging

from rich.console import Console
from rich.logging import RichHandler

from mmpa.core.errors import ConfigError

__all__ = ["LEVELS", "setup_logging"]

LEVELS = ("debug", "info", "warning", "error")


def setup_logging(level: str = "warning") -> logging.Logger:
    """Send the ``mmpa`` loggers at ``level`` and above to stderr through rich; returns the
    ``mmpa`` logger. Calling it again changes the level (one handler)."""
    name = level.lower()
    if name not in LEVELS:
        raise ConfigError(f"unknown log level {level!r}; valid: {', '.join(LEVELS)}")

    log = logging.getLogger("mmpa")
    log.setLevel(name.upper())
    if not any(getattr(h, "_mmpa", False) for h in log.handlers):
        handler = RichHandler(console=Console(stderr=True), show_path=False, markup=False)
        handler._mmpa = True  # type: ignore[attr-defined]
        handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
        log.addHandler(handler)
    return log
