"""``mmpa ros2 ...``: mmpa's ROS 2 nodes (the extra ``ros2``; docs/ros2.md). Each command
passes what follows it (``--ros-args -p name:=value --params-file FILE ...``) to rclpy."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mmpa.cli.common import ProfileOpt, console, fail
from mmpa.core.errors import MMPAError

ros2_app = typer.Typer(help="ROS 2 nodes (Jazzy; the extra ros2).", no_args_is_help=True)


def register(app: typer.Typer) -> None:
    """Add the ``ros2`` group to the ``mmpa`` command."""
    app.add_typer(ros2_app, name="ros2")


ROS_ARGS = {"allow_extra_args": True, "ignore_unknown_options": True}


@ros2_app.command("localization", context_settings=ROS_ARGS)
def localization(ctx: typer.Context) -> None:
    """Nav2 amcl's drop-in: /scan, /map, /initialpose, tf -> /amcl_pose, /particle_cloud,
    map -> odom (parameters: --ros-args -p name:=value or --params-file FILE)."""
    try:
        from mmpa.apps.ros2_localization import main
    except ImportError as e:
        fail(MMPAError(f"the ros2 extra is missing ({e}); make setup installs it"))
    try:
        code = main(list(ctx.args))
    except MMPAError as e:
        fail(e)
    raise typer.Exit(code)


@ros2_app.command("twin", context_settings=ROS_ARGS)
def twin_cmd(
    ctx: typer.Context,
    site: Annotated[str, typer.Option("--site", help="Start site of the scene.")] = "0",
    profile: ProfileOpt = None,
    seed: Annotated[int, typer.Option(help="Robot instance / noise seed.", min=0)] = 0,
    camera: Annotated[
        bool, typer.Option("--camera/--no-camera", help="Publish the wrist RGB-D camera.")
    ] = False,
    camera_rate: Annotated[
        float, typer.Option(help="Camera frames per sim second.", min=0.1, max=60.0)
    ] = 15.0,
    speed: Annotated[
        float,
        typer.Option(help="Sim seconds per wall second (0: as fast as it steps).", min=0.0),
    ] = 1.0,
    rate: Annotated[
        float, typer.Option(help="Ticks per sim second (/clock, /odom, /tf).", min=1.0)
    ] = 50.0,
    duration: Annotated[
        float | None, typer.Option(help="Stop after this many sim seconds (default: Ctrl-C).")
    ] = None,
    pose: Annotated[
        str | None,
        typer.Option(help="Start at x,y,theta (map) near the site instead of its park pose."),
    ] = None,
) -> None:
    """The digital twin as a ROS 2 robot: /clock, /scan, /odom, /tf, /map, the camera; takes
    /cmd_vel and the arm's trajectories (docs/ros2.md; ROS arguments after --ros-args)."""
    try:
        from mmpa.apps.ros2_twin import run_twin_node, twin_node_config
    except ImportError as e:
        fail(MMPAError(f"the ros2 extra is missing ({e}); make setup installs it"))
    try:
        try:
            start = None if pose is None else tuple(float(x) for x in pose.split(","))
        except ValueError:
            raise MMPAError(f"--pose is x,y,theta (3 numbers), got {pose!r}") from None
        cfg = twin_node_config(
            site,
            profile,
            seed,
            start,  # type: ignore[arg-type]
            camera=camera,
            camera_rate_hz=camera_rate,
            speed=speed,
            rate_hz=rate,
        )
        stats = run_twin_node(cfg, ["mmpa", *ctx.args], duration)
    except MMPAError as e:
        fail(e)
    console.print(
        f"twin: {stats.sim_s:.1f} sim s in {stats.wall_s:.1f} s "
        f"(real-time factor {stats.real_time_factor:.2f}), {len(stats.refused)} refused"
    )


@ros2_app.command("play", context_settings=ROS_ARGS)
def play_cmd(
    ctx: typer.Context,
    bag: Annotated[Path, typer.Argument(help="The bag (FILE.mcap, a rosbag2 folder).")],
    rate: Annotated[float, typer.Option(help="Bag seconds per wall second.", min=0.001)] = 1.0,
    loop: Annotated[bool, typer.Option("--loop", help="Play it again and again.")] = False,
    delay: Annotated[
        float, typer.Option(help="Wall seconds to wait before the first message.", min=0.0)
    ] = 0.0,
    topics: Annotated[
        list[str] | None, typer.Option("--topic", help="Only this topic (repeat it).")
    ] = None,
) -> None:
    """Publish a bag's messages as recorded (the stored bytes, the recorded QoS) with /clock
    (docs/ros2.md; ROS arguments after --ros-args)."""
    try:
        from mmpa.apps.ros2_play import PlayConfig, play_bag
    except ImportError as e:
        fail(MMPAError(f"the ros2 extra is missing ({e}); make setup installs it"))
    try:
        cfg = PlayConfig(rate=rate, loop=loop, delay=delay, topics=topics or None)
        stats = play_bag(bag, cfg, ["mmpa", *ctx.args])
    except MMPAError as e:
        fail(e)
    n = sum(stats.published.values())
    console.print(f"played {n} messages on {len(stats.published)} topics in {stats.wall_s:.1f} s")
