"""Helpers shared by the CLI sub-apps (kept free of imports of ``mmpa.cli.main``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, NoReturn

import typer
from rich.console import Console

from mmpa.errors import MMPAError

console = Console()


def fail(e: MMPAError) -> NoReturn:
    """Print ``e`` in red and exit with status 2 (the CLI's error code for bad input)."""
    console.print(f"[bold red]error:[/] {e}", highlight=False, soft_wrap=True)
    raise typer.Exit(2)


DbOpt = Annotated[
    Path | None,
    typer.Option(
        "--db",
        help="Task database (default: $MMPA_TASKS_DB or ~/.local/share/mmpa/tasks.db).",
    ),
]

ProfileOpt = Annotated[
    str | None,
    typer.Option(
        "--profile",
        help="Twin error model profile: ideal, reference, realistic (the default), harsh.",
    ),
]


def profile_overrides(profile: str | None) -> list[str]:
    """The ``--set`` overrides of ``--profile NAME`` (they go first: later ``--set
    errors....`` overrides apply on top of the profile)."""
    return [] if profile is None else [f"errors.profile={profile}"]
