"""``mmpa ros2 ...``: mmpa's ROS 2 nodes (the extra ``ros2``; docs/ros2.md). Each command
passes what follows it (``--ros-args -p name:=value --params-file FILE ...``) to rclpy."""

from __future__ import annotations

import typer

from mmpa.cli.common import fail
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
