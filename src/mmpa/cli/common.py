"""Helpers shared by the CLI sub-apps (kept free of imports of ``mmpa.cli.main``)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, NoReturn

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from mmpa.core.errors import MMPAError

console = Console()


def show_summary(summary: dict, title: str) -> None:
    """Print a command's summary as a two-column table (key, value)."""
    t = Table(title=title, show_header=False)
    for k, v in summary.items():
        t.add_row(k, str(v))
    console.print(t)


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


def in_range(
    lo: float, hi: float, *, closed: bool = False
) -> Callable[[float | None], float | None]:
    """A typer callback accepting a finite number in ``(lo, hi]`` (``[lo, hi]`` when
    ``closed``); click's own ranges let a NaN through (every comparison with NaN is false)."""

    def check(value: float | None) -> float | None:
        if value is None:
            return value
        above = value >= lo if closed else value > lo
        if not (math.isfinite(value) and above and value <= hi):
            span = f"{'[' if closed else '('}{lo:g}, {hi:g}]"
            raise typer.BadParameter(f"must be a finite number in {span}, got {value}")
        return value

    return check


def out_dir(path: Path) -> Path:
    """Create the output folder ``path`` (and its parents), or fail with a clear error naming
    the part of the path that is in the way (a file) or cannot be written."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        for parent in [path, *path.parents]:
            if parent.exists() and not parent.is_dir():
                fail(MMPAError(f"cannot create the output folder {path}: {parent} is a file"))
        fail(MMPAError(f"cannot create the output folder {path}: {e.strerror or e}"))
    return path


@contextmanager
def progress_bar(
    first: str, max_chars: int | None = None
) -> Iterator[Callable[[str, float], None]]:
    """A transient progress bar; yields the ``progress(stage, fraction)`` callback the
    runners take (``fraction`` clipped to [0, 1]; ``stage`` cut to ``max_chars``)."""
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task(first, total=1.0)

        def progress(stage: str, frac: float) -> None:
            text = stage if max_chars is None else stage[:max_chars]
            bar.update(task, description=text, completed=max(0.0, min(frac, 1.0)))

        yield progress


WorkersOpt = Annotated[
    int, typer.Option(help="Trials in this many processes (or Ray CPUs).", min=1)
]
ExecutorOpt = Annotated[str, typer.Option(help="Where trials run: local (processes) or ray.")]
RayAddressOpt = Annotated[
    str | None, typer.Option(help="Ray cluster to connect to (--executor ray).")
]


def robot_reflector_map(ctx: typer.Context) -> Path | None:
    """The ``reflector_map`` of the robot file given with ``mmpa --robot FILE``, or None
    (the root command's ``robot`` parameter: typer bundles its own click, so click's context
    lookup does not see it)."""
    from mmpa.robot.robot_file import robot_reflector_map as entry

    path = ctx.find_root().params.get("robot")
    return entry(path) if path is not None else None
