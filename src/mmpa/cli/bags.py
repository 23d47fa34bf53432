"""``mmpa localize --bag BAG``: offline localization over a ROS 1 / ROS 2 recording."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mmpa.cli.common import console, fail, out_dir, robot_reflector_map
from mmpa.core.errors import MMPAError

__all__ = ["register"]


def _pose3(text: str | None, what: str) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise typer.BadParameter(f"{what} must be three numbers 'x,y,yaw', got {text!r}") from None
    if len(vals) != 3 or not all(abs(v) < 1e6 for v in vals):
        raise typer.BadParameter(f"{what} must be three finite numbers 'x,y,yaw', got {text!r}")
    return vals  # type: ignore[return-value]


def _robot_laser_pose(ctx: typer.Context) -> tuple[float, float, float] | None:
    """The lidar mount ``[x, y, yaw]`` of the robot file given with ``mmpa --robot FILE``;
    None without one (the twin's mount never stands in for a real robot's)."""
    if ctx.find_root().params.get("robot") is None:
        return None
    from mmpa.core.geometry import T_to_se2
    from mmpa.robot.description import default_robot

    x, y, yaw = (float(v) for v in T_to_se2(default_robot().lidar.T_base_link_laser))
    return x, y, yaw


def parse_cov3(text: str | None) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise typer.BadParameter(f"--initial-cov must be 'xx,yy,aa', got {text!r}") from None
    if len(vals) != 3:
        raise typer.BadParameter(f"--initial-cov must be three variances 'xx,yy,aa', got {text!r}")
    return vals  # type: ignore[return-value]


ConfigOpt = Annotated[
    Path | None,
    typer.Option("--config", "-c", help="YAML settings (method, amcl, enhanced, hector, ...)."),
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option("--set", help="Override: key=value, e.g. amcl.alpha1=0.05 (repeat)."),
]
MethodOpt = Annotated[
    str | None,
    typer.Option(
        help="amcl | enhanced | enhanced-paper | trilateration | tamcl | hector (default: "
        "the robot file's localization.method, else enhanced)."
    ),
]
InitialCovOpt = Annotated[
    str | None,
    typer.Option(
        help="Initial covariance 'xx,yy,aa' (m^2, m^2, rad^2; default: the bag's "
        "/initialpose, else amcl.initial_cov_*)."
    ),
]


def robot_file(ctx: typer.Context) -> Path | None:
    """The robot file given with ``mmpa --robot FILE`` (None: none)."""
    return ctx.find_root().params.get("robot")


def localize_cmd(
    ctx: typer.Context,
    bag: Annotated[Path, typer.Option("--bag", help="ROS 1 .bag, rosbag2 folder, .mcap or .db3.")],
    map_yaml: Annotated[
        Path | None,
        typer.Option("--map", help="map_server YAML with reflectors (default: the bag's /map)."),
    ] = None,
    reflectors: Annotated[
        Path | None,
        typer.Option(
            help="Reflector map file (id, x, y, radius) replacing the map's reflectors "
            "(default: the robot file's reflector_map, mmpa --robot FILE)."
        ),
    ] = None,
    method: MethodOpt = None,
    out: Annotated[Path, typer.Option(help="Run folder to write.")] = Path("runs/localize"),
    seed: Annotated[
        int | None, typer.Option(help="Seed of the localizer's random stream (default 0).", min=0)
    ] = None,
    force: Annotated[
        bool | None, typer.Option(help="Force every filter update (also while standing).")
    ] = None,
    initial_pose: Annotated[
        str | None, typer.Option(help="'x,y,yaw' (default: the bag's /initialpose).")
    ] = None,
    initial_cov: InitialCovOpt = None,
    global_: Annotated[
        bool | None,
        typer.Option(
            "--global",
            help="Global localization: particles over the whole map, no initial pose "
            "(amcl, enhanced; e.g. --set amcl.max_particles=10000).",
        ),
    ] = None,
    laser_pose: Annotated[
        str | None,
        typer.Option(
            help="Lidar mount 'x,y,yaw' in base_link (default: the bag's /tf_static from "
            "base_link to the scans' frame_id, else the robot file's lidar mount)."
        ),
    ] = None,
    scan_topic: Annotated[str | None, typer.Option(help="LaserScan topic (/scan).")] = None,
    odom_topic: Annotated[str | None, typer.Option(help="Odometry topic (/odom).")] = None,
    max_scans: Annotated[
        int | None, typer.Option(help="Stop after this many scans.", min=1)
    ] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """Run a localizer over a bag's scans and odometry; write estimate.csv, estimate.mcap
    (/amcl_pose), trajectory.png, summary.json (with the error when the bag has
    /truth/base_pose, and the lidar mount used) and config.yaml (the final settings).
    Settings, lowest first: defaults, the robot file's localization section, --config, the
    options, --set."""
    from mmpa.apps.localization_settings import load_localization_config
    from mmpa.apps.localize import LocalizeConfig, run_localize

    topics = {"scan": scan_topic, "odom": odom_topic}
    try:
        options = {
            "method": method,
            "seed": seed,
            "force": force,
            "initial_pose": _pose3(initial_pose, "--initial-pose"),
            "initial_cov": parse_cov3(initial_cov),
            "global_localization": global_,
            "laser_pose": _pose3(laser_pose, "--laser-pose"),
            "robot_laser_pose": _robot_laser_pose(ctx),
            "max_scans": max_scans,
            "topics": {k: v for k, v in topics.items() if v is not None} or None,
        }
        cfg = load_localization_config(LocalizeConfig, robot_file(ctx), config, options, set_ or [])
        with console.status(f"localizing over {bag}"):
            refl = reflectors or robot_reflector_map(ctx)
            summary = run_localize(bag, out_dir(out), map_yaml, cfg, reflectors=refl)
    except MMPAError as e:
        fail(e)
    from rich.table import Table

    t = Table(title=f"mmpa localize -> {out}", show_header=False)
    for k, v in summary.items():
        t.add_row(k, str(v))
    console.print(t)


def register(app: typer.Typer) -> None:
    """Add ``localize`` to the root app."""
    app.command("localize")(localize_cmd)
