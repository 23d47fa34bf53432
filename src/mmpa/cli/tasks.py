"""``mmpa tasks``: list, show, export, import and delete taught tasks (mmpa.tasks); ``mmpa
teach`` and ``mmpa run``: teach a task and run it, in the twin or on the robot of ``mmpa
--robot R`` (a ros2 or direct backend: cli.hardware)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.table import Table

from mmpa.cli.common import (
    DbOpt,
    ProfileOpt,
    console,
    fail,
    profile_overrides,
    show_summary,
)
from mmpa.cli.hardware import YesOpt, backend_in_use, confirmer, open_hardware
from mmpa.core.errors import InvalidInputError, MMPAError

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


# ---------------------------------------------------------------------- teach and run
ConfigOpt = Annotated[Path | None, typer.Option("--config", "-c", help="YAML config file.")]
SetOpt = Annotated[list[str] | None, typer.Option("--set", help="Override: key=value (repeat).")]


SeedOpt = Annotated[
    int,
    typer.Option(help="Twin: robot instance / noise seed; hardware: the localizer's seed.", min=0),
]
FromOpt = Annotated[
    str | None,
    typer.Option(
        "--from",
        help="Hardware, a base: where it stands, roughly (a site or x,y,theta in map) for "
        "mmpa's localizer; not needed with the robot's own (backend.ros2.topics.pose).",
    ),
]
#: the devices teach and run wait for on a hardware robot (absent ones are skipped)
TEACH_DEVICES = ("clock", "arm", "camera", "odometry", "lidar")
RUN_DEVICES = ("clock", "arm", "camera", "gripper", "odometry", "base", "lidar")


def _mmpa_config(config: Path | None, seed: int, set_: list[str] | None, profile: str | None):
    from mmpa.core.config import load_config
    from mmpa.harness.twin_site import MMPAExperimentConfig

    sets = [*profile_overrides(profile), f"errors.seed={seed}", *(set_ or [])]
    return load_config(MMPAExperimentConfig, config, sets)


def _joints(text: str | None) -> np.ndarray | None:
    """``--sample-q``: six comma-separated joint angles (rad)."""
    if text is None:
        return None
    try:
        q = np.array([float(x) for x in text.split(",")])
    except ValueError:
        q = np.zeros(0)
    if q.shape != (6,) or not np.all(np.isfinite(q)):
        fail(InvalidInputError(f"--sample-q takes 6 comma-separated angles in rad, got {text!r}"))
    return q


def teach(
    site: Annotated[str, typer.Argument(help="Site where the task is taught (1 or 2).")],
    task: Annotated[str, typer.Argument(help="Task name (twin: its demonstration).")],
    db: DbOpt = None,
    seed: SeedOpt = 0,
    overwrite: Annotated[bool, typer.Option(help="Replace a stored task of that name.")] = False,
    from_bag: Annotated[
        Path | None, typer.Option(help="Hardware: the demonstration's /joint_states from a bag.")
    ] = None,
    sample_q: Annotated[
        str | None,
        typer.Option(help="Hardware: sampling joints, 6 rad comma-separated (default: as is)."),
    ] = None,
    rate: Annotated[float, typer.Option(help="Hardware: path rate (Hz).", min=1.0)] = 50.0,
    button: Annotated[
        str, typer.Option(help="Hardware: start/stop by 'key' (Enter) or 'di:N' (input N).")
    ] = "key",
    max_seconds: Annotated[
        float, typer.Option(help="Hardware: longest demonstration (s).", min=1.0)
    ] = 600.0,
    start: FromOpt = None,
    profile: ProfileOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """One-shot teaching (paper 000 §3.1): record a task and store it. The twin (default):
    its scripted operator plays the demonstration TASK. `mmpa --robot R` on a ros2 / direct
    robot: a person guides the arm (UR freedrive, or the pendant while /joint_states is
    read), started and stopped by --button; or --from-bag replays a recorded one. The park
    pose: the localizer's estimate where a robot with a base stands (its own localizer, or
    mmpa's started at --from); the identity on a fixed base."""
    from mmpa.apps.teach_person import teach_on_hardware
    from mmpa.apps.teach_run import teach_task

    path, backend = backend_in_use()
    try:
        if backend.hardware:
            with open_hardware(path, TEACH_DEVICES) as robot:
                summary = teach_on_hardware(
                    robot, site, task, kind=backend.kind, from_bag=from_bag,
                    sample_q=_joints(sample_q), rate_hz=rate, button=button,
                    max_seconds=max_seconds, db=db, overwrite=overwrite, say=console.print,
                    robot_file=path, start=start, seed=seed,
                )  # fmt: skip
        else:
            if from_bag is not None:
                fail(InvalidInputError("--from-bag teaches on a ros2 / direct robot (--robot)"))
            with console.status(f"teaching {task} at site {site}"):
                cfg = _mmpa_config(config, seed, set_, profile)
                summary = teach_task(site, task, db=db, cfg=cfg, overwrite=overwrite)
    except MMPAError as e:
        fail(e)
    show_summary(summary, f"taught {task}")


def run_cmd(
    task: Annotated[str, typer.Argument(help="Name of a stored task.")],
    site: Annotated[
        str | None,
        typer.Option(help="Twin: automation site (default: the task's; 2' for the bump)."),
    ] = None,
    db: DbOpt = None,
    seed: SeedOpt = 0,
    trial: Annotated[int, typer.Option(help="Twin: which parking draw of this seed.", min=0)] = 0,
    tmma: Annotated[bool, typer.Option(help="Twin: also replay the taught joints.")] = False,
    yes: YesOpt = False,
    dry_run: Annotated[
        Path | None,
        typer.Option(help="Hardware: stop before the path; write it and a picture here."),
    ] = None,
    start: FromOpt = None,
    drive: Annotated[
        bool,
        typer.Option(help="Hardware, a base: drive to the task's park pose first (or not)."),
    ] = True,
    timeout: Annotated[
        float, typer.Option(help="Hardware, a base: longest drive (s of its clock).", min=1.0)
    ] = 120.0,
    profile: ProfileOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    record: Annotated[
        Path | None,
        typer.Option(help="Twin: record the run to this ROS 2 bag (FILE.mcap or a folder)."),
    ] = None,
) -> None:
    """Automation stage (paper 000 §3.2): IPE, the adapted path, execute. The twin
    (default): park with a paper offset, errors against the truth. `mmpa --robot R` on a
    ros2 / direct robot: a base is localized (its own localizer, or mmpa's from --from)
    and driven to the task's park pose (--no-drive: from where it stands); then the
    estimate, the path's clearance from the taught one and the limits check are shown and
    asked about before the arm moves (--yes skips; --dry-run DIR stops there and writes the
    path and a picture)."""
    from mmpa.apps.teach_run import run_stored_task_on_robot, run_task

    path, backend = backend_in_use()
    try:
        if backend.hardware:
            with open_hardware(path, RUN_DEVICES) as robot:
                summary = run_stored_task_on_robot(
                    robot, task, db=db, kind=backend.kind,
                    confirm=confirmer(yes, backend), dry_run=dry_run,
                    robot_file=path, start=start, drive=drive, seed=seed, timeout=timeout,
                )  # fmt: skip
        else:
            with console.status(f"running {task}"):
                cfg = _mmpa_config(config, seed, set_, profile)
                summary = run_task(
                    task, site=site, db=db, cfg=cfg, trial=trial, tmma=tmma, record=record
                )
    except MMPAError as e:
        fail(e)
    show_summary(summary, f"mmpa run {task}")
    if not summary.get("executed") and not (dry_run is not None and "files" in summary):
        console.print(f"[yellow]not executed:[/] {summary.get('reason', '')}")
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    """Add ``teach`` and ``run`` to the main app."""
    app.command("teach")(teach)
    app.command("run")(run_cmd)
