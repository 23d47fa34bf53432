"""mmpa command-line interface: parses arguments and hands off to the experiment runners."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

# Offscreen rendering without a GPU: OSMesa unless the user chose (e.g. MUJOCO_GL=egl).
os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import typer
from rich.table import Table

from mmpa.cli.common import (
    ExecutorOpt,
    ProfileOpt,
    RayAddressOpt,
    WorkersOpt,
    console,
    fail,
    profile_overrides,
    progress_bar,
)
from mmpa.cli.perception import perception_app
from mmpa.cli.tasks import tasks_app
from mmpa.core.errors import MMPAError

if TYPE_CHECKING:
    from mmpa.apps.demo import DemoConfig

app = typer.Typer(
    help="mmpa: precise mobile manipulation with a MuJoCo digital twin.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
sim_app = typer.Typer(help="The digital twin: pictures and checks.", no_args_is_help=True)
app.add_typer(sim_app, name="sim")
app.add_typer(tasks_app, name="tasks")
app.add_typer(perception_app, name="perception")

ConfigOpt = Annotated[Path | None, typer.Option("--config", "-c", help="YAML config file.")]
SetOpt = Annotated[list[str] | None, typer.Option("--set", help="Override: key=value (repeat).")]


def _demo_config(
    config: Path | None, seed: int, set_: list[str] | None, profile: str | None = None
) -> DemoConfig:
    """DemoConfig from defaults, the YAML file, ``--profile``, ``--seed`` and ``--set`` (in
    that order)."""
    from mmpa.apps.demo import DemoConfig
    from mmpa.core.config import load_config

    sets = [*profile_overrides(profile), f"errors.seed={seed}", *(set_ or [])]
    return load_config(DemoConfig, config, sets)


def _show(summary: dict, title: str) -> None:
    t = Table(title=title, show_header=False)
    for k, v in summary.items():
        t.add_row(k, str(v))
    console.print(t)


@app.command()
def version() -> None:
    """Print the mmpa version."""
    from mmpa import __version__

    typer.echo(__version__)


def _print_version(value: bool) -> None:
    if value:
        version()
        raise typer.Exit()


@app.callback()
def _root(
    show_version: Annotated[
        bool,
        typer.Option(
            "--version", help="Print the version and exit.", callback=_print_version, is_eager=True
        ),
    ] = False,
    verbose: Annotated[
        int, typer.Option("--verbose", "-v", count=True, help="Log progress (-vv: debug).")
    ] = 0,
    log_level: Annotated[
        str | None, typer.Option(help="Log level: debug, info, warning, error.")
    ] = None,
    robot: Annotated[
        Path | None,
        typer.Option(help="Robot file (YAML; `mmpa robot show` prints a template)."),
    ] = None,
) -> None:
    """mmpa: precise mobile manipulation with a MuJoCo digital twin."""
    if robot is not None:
        _robot.use_robot_file(robot)
    from mmpa.core.log import setup_logging

    level = log_level or ("debug" if verbose > 1 else "info" if verbose else None)
    if level is not None:
        try:
            setup_logging(level)
        except MMPAError as e:
            fail(e)


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Run folder to write.")] = Path("runs/demo"),
    seed: Annotated[int, typer.Option(help="Robot instance / noise seed.", min=0)] = 0,
    profile: ProfileOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    record: Annotated[
        Path | None,
        typer.Option(help="Record the run to this ROS 2 bag (FILE.mcap, or a rosbag2 folder)."),
    ] = None,
    view: Annotated[
        int | None,
        typer.Option(
            help="Serve the run live to Foxglove on ws://127.0.0.1:PORT (0: a free port).",
            min=0,
            max=65535,
        ),
    ] = None,
) -> None:
    """Drive Site 0 -> Site 1 in the built-in world, capture RGB-D and a scan, write pictures."""
    from mmpa.apps.demo import run_demo

    try:
        cfg = _demo_config(config, seed, set_, profile)
        with progress_bar("building world") as progress:
            summary = run_demo(cfg, out, progress, record=record, view=view)
    except MMPAError as e:
        fail(e)
    _show(summary, f"mmpa demo -> {out}")
    if not summary["reached"]:
        console.print("[yellow]the base did not reach the goal within the timeout[/]")
        raise typer.Exit(1)


@sim_app.command("snapshot")
def sim_snapshot(
    site: Annotated[str, typer.Option(help="Site name of the scene (e.g. 0, 1, 2, 2').")] = "1",
    out: Annotated[Path, typer.Option(help="Folder to write.")] = Path("runs/snapshot"),
    seed: Annotated[int, typer.Option(help="Robot instance / noise seed.", min=0)] = 0,
    profile: ProfileOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """Place the robot at a site and write the camera, depth and top-down pictures."""
    from mmpa.apps.demo import snapshot

    try:
        cfg = _demo_config(config, seed, set_, profile)
        summary = snapshot(cfg, site, out)
    except MMPAError as e:
        fail(e)
    _show(summary, f"snapshot of site {site} -> {out}")


@app.command()
def experiment(
    name: Annotated[
        str | None, typer.Argument(help="Experiment to run; leave out to list them.")
    ] = None,
    trials: Annotated[int | None, typer.Option(help="Trials (default: the paper's count).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of every random draw.", min=0)] = 0,
    out: Annotated[Path | None, typer.Option(help="Run folder (default runs/NAME).")] = None,
    profile: ProfileOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    workers: WorkersOpt = 1,
    executor: ExecutorOpt = "local",
    ray_address: RayAddressOpt = None,
    resume: Annotated[
        bool, typer.Option("--resume", help="Keep the finished trials in --out; run the rest.")
    ] = False,
    compare_profile: Annotated[
        list[str] | None,
        typer.Option(
            "--compare-profile",
            help="Also run under this error model profile (repeatable; into "
            "OUT/profile-NAME) and print its figures beside this run's in report.md.",
        ),
    ] = None,
    record: Annotated[
        Path | None,
        typer.Option(
            help="Record every trial to its own ROS 2 bag in this folder "
            "(<label>site-<site>-trial-<n>.mcap; the paper 000 twin experiments).",
        ),
    ] = None,
) -> None:
    """Reproduce a paper table or figure: writes results.csv, report.md, plots, config.yaml."""
    from mmpa.harness.runner import EXPERIMENTS, run_experiment

    if name is None:
        t = Table(title="experiments", show_header=True)
        t.add_column("name")
        t.add_column("module")
        for k, v in EXPERIMENTS.items():
            t.add_row(k, v)
        console.print(t)
        return
    out = out or Path("runs") / name
    try:
        with progress_bar(name) as progress:
            outcome = run_experiment(
                name,
                out,
                seed=seed,
                trials=trials,
                profile=profile,
                config=config,
                overrides=set_ or [],
                progress=progress,
                workers=workers,
                executor=executor,
                ray_address=ray_address,
                resume=resume,
                compare=compare_profile or (),
                record=record,
            )
    except MMPAError as e:
        fail(e)
    _show(outcome.summary, f"mmpa experiment {name} -> {out} (report.md, results.csv)")


from mmpa.cli import bags as _bags  # noqa: E402  (registers localize)
from mmpa.cli import calibrate as _calibrate  # noqa: E402  (registers calibrate)
from mmpa.cli import datasets as _datasets  # noqa: E402  (registers convert, benchmark)
from mmpa.cli import grasp as _grasp  # noqa: E402  (registers grasp)
from mmpa.cli import navigation as _navigation  # noqa: E402  (registers navigate, map)
from mmpa.cli import register as _register  # noqa: E402  (registers register)
from mmpa.cli import robot as _robot  # noqa: E402  (registers robot)
from mmpa.cli import ros2 as _ros2  # noqa: E402  (registers the ros2 group)
from mmpa.cli import sweep as _sweep  # noqa: E402  (registers sweep)
from mmpa.cli import tasks as _tasks  # noqa: E402  (registers teach, run)

_navigation.register(app)
_bags.register(app)
_robot.register(app)
_calibrate.register(app)
_register.register(app)
_sweep.register(app)
_datasets.register(app)
_ros2.register(app)
_grasp.register(app)
_tasks.register(app)


def main() -> None:
    """The ``mmpa`` console script: the app, with errors that escape a command (a file in
    the way of an output folder, a full disk, a refused input) printed as one clear line
    instead of a traceback. A traceback still means a bug."""
    import sys

    try:
        app()
    except MMPAError as e:
        console.print(f"[bold red]error:[/] {e}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except OSError as e:
        where = f": {e.filename}" if e.filename else ""
        console.print(f"[bold red]error:[/] {e.strerror or e}{where}", highlight=False)
        sys.exit(1)
    except KeyboardInterrupt:
        console.print("[yellow]interrupted[/]")
        sys.exit(130)


if __name__ == "__main__":  # pragma: no cover
    main()
