"""``mmpa tasks``: list, show, export, import and delete taught tasks (mmpa.tasks)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.table import Table

from mmpa.cli.common import DbOpt, console, fail
from mmpa.core.errors import MMPAError

tasks_app = typer.Typer(
    help="Taught tasks: list, show, export, import, delete.", no_args_is_help=True
)


def _fmt(v: np.ndarray, scale: float = 1.0, digits: int = 4) -> str:
    return "[" + ", ".join(f"{x * scale:.{digits}f}" for x in np.ravel(v)) + "]"


def _pose(T: np.ndarray) -> str:
    from mmpa.core.geometry import T_to_vec6

    v = T_to_vec6(T)
    return f"xyz {_fmt(v[:3])} m, rpy {_fmt(v[3:], 180.0 / np.pi, 3)} deg"


@tasks_app.command("list")
def list_tasks(db: DbOpt = None) -> None:
    """List the stored tasks."""
    from mmpa.tasks import TaskStore

    try:
        with TaskStore(db) as store:
            infos = store.list()
            where = store.path
    except MMPAError as e:
        fail(e)
    t = Table(title=f"tasks in {where}")
    t.add_column("name", no_wrap=True)
    t.add_column("site", no_wrap=True)
    t.add_column("created (UTC)", no_wrap=True)
    t.add_column("cloud", no_wrap=True)
    t.add_column("path", no_wrap=True)
    t.add_column("description", overflow="fold")
    for i in infos:
        t.add_row(
            i.name,
            i.site,
            i.created.strftime("%Y-%m-%d %H:%M"),
            f"{i.n_points} {'rgb' if i.has_colors else 'xyz'}",
            f"{i.n_waypoints} @ {i.rate_hz:g} Hz, {i.duration:.2f} s",
            i.description,
        )
    console.print(t)
    if not infos:
        console.print("no tasks stored yet (teach one with `mmpa teach SITE TASK`)")


@tasks_app.command("show")
def show(name: Annotated[str, typer.Argument(help="Task name.")], db: DbOpt = None) -> None:
    """Show one task (loading it verifies every checksum)."""
    from mmpa.tasks import TaskStore

    try:
        with TaskStore(db) as store:
            task = store.load(name)
    except MMPAError as e:
        fail(e)
    p, c = task.path, task.cloud
    lo, hi = c.points.min(axis=0), c.points.max(axis=0)
    t = Table(title=f"task {task.name} (checksums verified)", show_header=False)
    t.add_column("field", style="bold")
    t.add_column("value")
    rows = [
        ("site", task.site),
        ("robot", task.robot_id),
        ("created (UTC)", task.created.isoformat()),
        ("description", task.description or "-"),
        ("format version", str(task.format_version)),
        ("park pose L_i (map)", _pose(task.T_map_base_park)),
        ("sampling joints q", _fmt(task.q_sample, 180.0 / np.pi, 3) + " deg"),
        ("nominal T_B_C", _pose(task.T_arm_base_camera)),
        (
            "cloud X_i(O)",
            f"{len(c)} points, {'colored' if task.has_colors else 'colorless'}, frame "
            f"{c.frame}, bounds {_fmt(lo, digits=3)} .. {_fmt(hi, digits=3)} m",
        ),
        (
            "tool path Path_i(O)",
            f"{len(p)} waypoints at {p.rate_hz:g} Hz over {p.duration:.3f} s, gripper "
            + ("none" if p.gripper is None else f"{p.gripper.min():.2f}..{p.gripper.max():.2f}"),
        ),
        ("path start (arm_base)", _pose(p.T_arm_base_tool[0])),
        ("path end (arm_base)", _pose(p.T_arm_base_tool[-1])),
    ]
    rows += [(f"meta.{k}", str(v)) for k, v in sorted(task.meta.items())]
    for k, v in rows:
        t.add_row(k, v)
    console.print(t)


@tasks_app.command("export")
def export(
    name: Annotated[str, typer.Argument(help="Task name.")],
    directory: Annotated[Path, typer.Argument(help="Bundle directory to write.")],
    overwrite: Annotated[bool, typer.Option(help="Replace a bundle already there.")] = False,
    db: DbOpt = None,
) -> None:
    """Write a task as a bundle: task.yaml + cloud.ply + path.csv."""
    from mmpa.tasks import TaskStore

    try:
        with TaskStore(db) as store:
            out = store.export(name, directory, overwrite=overwrite)
    except MMPAError as e:
        fail(e)
    console.print(f"exported task {name!r} to {out}", highlight=False)


@tasks_app.command("import")
def import_(
    directory: Annotated[Path, typer.Argument(help="Bundle directory to read.")],
    overwrite: Annotated[bool, typer.Option(help="Replace a task of the same name.")] = False,
    db: DbOpt = None,
) -> None:
    """Verify a bundle and store its task."""
    from mmpa.tasks import TaskStore

    try:
        with TaskStore(db) as store:
            task = store.import_bundle(directory, overwrite=overwrite)
    except MMPAError as e:
        fail(e)
    console.print(
        f"imported task {task.name!r} ({len(task.cloud)} points, {len(task.path)} waypoints)",
        highlight=False,
    )


@tasks_app.command("delete")
def delete(
    name: Annotated[str, typer.Argument(help="Task name.")],
    yes: Annotated[bool, typer.Option("--yes", "-y", help="Do not ask for confirmation.")] = False,
    db: DbOpt = None,
) -> None:
    """Delete a task (asks first unless --yes)."""
    from mmpa.tasks import TaskStore

    try:
        with TaskStore(db) as store:
            if name not in store:
                store.delete(name)  # raises TaskNotFoundError listing the stored names
            if not yes and not typer.confirm(f"delete task {name!r} from {store.path}?"):
                console.print("not deleted")
                raise typer.Exit(1)
            store.delete(name)
    except MMPAError as e:
        fail(e)
    console.print(f"deleted task {name!r}", highlight=False)
