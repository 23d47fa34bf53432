"""``mmpa navigate --to SITE`` and ``mmpa map export``: localization and navigation in the twin,
or on the robot of ``mmpa --robot FILE`` (a ``ros2`` backend)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from mmpa.cli.bags import ConfigOpt, InitialCovOpt, MethodOpt, SetOpt, parse_cov3, robot_file
from mmpa.cli.common import ProfileOpt, console, fail, in_range, out_dir, robot_reflector_map
from mmpa.core.errors import MMPAError

__all__ = ["register"]

map_app = typer.Typer(help="Occupancy maps (ROS map_server format).", no_args_is_help=True)


def _errors(seed: int, profile: str | None):
    from mmpa.apps.navigate import twin_errors

    return twin_errors(seed, profile)


def navigate_cmd(
    ctx: typer.Context,
    to: Annotated[
        str, typer.Option("--to", help="Goal site (e.g. 1, 2), or x,y,theta on a robot.")
    ],
    start: Annotated[
        str,
        typer.Option(
            "--from", help="Start site; on a robot: where it stands roughly (site or x,y,theta)."
        ),
    ] = "0",
    method: MethodOpt = None,
    seed: Annotated[int, typer.Option(help="Robot instance / noise seed.", min=0)] = 0,
    out: Annotated[
        Path | None, typer.Option(help="Write summary.json and config.yaml here.")
    ] = None,
    timeout: Annotated[
        float,
        typer.Option(
            help="Seconds of the robot's clock (simulated).", callback=in_range(0.0, 86400.0)
        ),
    ] = 120.0,
    profile: ProfileOpt = None,
    record: Annotated[
        Path | None,
        typer.Option(help="Record the drive to this ROS 2 bag (FILE.mcap, or a rosbag2 folder)."),
    ] = None,
    reflectors: Annotated[
        Path | None,
        typer.Option(
            help="Reflector map file (id, x, y, radius) replacing the twin's reflectors "
            "(default: the robot file's reflector_map, e.g. from mmpa calibrate reflectors)."
        ),
    ] = None,
    initial_cov: InitialCovOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """Drive the twin from a site to ``--to`` on the localization estimate (started from the
    operator's rough pose); print the parking error (truth vs goal) and the localization error
    (estimate vs truth) at the end. With ``mmpa --robot R.yaml`` whose backend is ``ros2``,
    drive that robot over ROS 2 instead (its /map, /scan, /odom, /cmd_vel; docs/ros2.md).
    Localization settings, lowest first: defaults, the robot file's localization section,
    --config, the options, --set."""
    from mmpa.apps.localization_settings import LocalizationConfig, load_localization_config
    from mmpa.apps.navigate import navigate_robot, navigate_twin
    from mmpa.core.config import save_config
    from mmpa.core.errors import ConfigError
    from mmpa.robot.robot_file import robot_backend

    try:
        options = {"method": method, "initial_cov": parse_cov3(initial_cov)}
        st = load_localization_config(
            LocalizationConfig, robot_file(ctx), config, options, set_ or []
        )
        refl_map = reflectors or robot_reflector_map(ctx)
        path = robot_file(ctx)
        if path is not None and robot_backend(path).kind != "twin":
            if record is not None:
                raise ConfigError("--record is for the twin: record a robot's topics with ros2 bag")
            with console.status(f"navigating {start} -> {to} over ROS 2 ({st.method})"):
                summary = navigate_robot(path, start, to, st, seed, timeout, refl_map)
        else:
            errors = _errors(seed, profile)
            with console.status(f"navigating site {start} -> site {to} ({st.method})"):
                summary = navigate_twin(
                    errors, start, to, st.method, seed, timeout, refl_map, record, settings=st
                )
    except MMPAError as e:
        fail(e)
    if out is not None:
        out_dir(out)
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        save_config(st, out / "config.yaml")
    t = Table(title=f"mmpa navigate --to {to}", show_header=False)
    for k, v in summary.items():
        t.add_row(k, str(v))
    console.print(t)
    if not summary["reached"]:
        console.print(f"[yellow]not reached: {summary['reason']}[/]")
        raise typer.Exit(1)


@map_app.command("export")
def map_export(
    out: Annotated[Path, typer.Option(help="Map YAML to write (PGM beside it).")] = Path(
        "runs/map/map.yaml"
    ),
    resolution: Annotated[
        float,
        typer.Option(help="m per cell (0.005 to 1).", callback=in_range(0.005, 1.0, closed=True)),
    ] = 0.05,
    seed: Annotated[
        int, typer.Option(help="Robot instance seed (map warp, reflector survey error).")
    ] = 0,
    profile: ProfileOpt = None,
) -> None:
    """Write the twin's occupancy map (warped as mapped, per the error model) with the surveyed
    reflector landmarks (map_server YAML)."""
    from mmpa.apps.navigate import export_twin_map

    out_dir(out.parent)
    try:
        path, grid = export_twin_map(_errors(seed, profile), out, resolution)
    except MMPAError as e:
        fail(e)
    console.print(
        f"wrote {path} and {path.with_suffix('.pgm').name}: {grid.width} x {grid.height} cells, "
        f"{len(grid.reflectors)} reflectors"
    )


def register(app: typer.Typer) -> None:
    """Add ``navigate`` and ``map`` to the main app."""
    app.command("navigate")(navigate_cmd)
    app.add_typer(map_app, name="map")
