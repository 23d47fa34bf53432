"""``mmpa robot``: the robot file (see :mod:`mmpa.robot.robot_file`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mmpa.cli.common import console, fail
from mmpa.core.errors import MMPAError

__all__ = ["register"]

robot_app = typer.Typer(help="The robot file: arm model, mounts, sensors, frames.")

#: the frame names of the robot file given with ``mmpa --robot FILE`` (None: defaults)
_frames = None
#: the robot file given with ``mmpa --robot FILE`` (None: the twin's robot)
_path: Path | None = None


def use_robot_file(path: Path) -> None:
    """Load ``path`` and make it the robot of every command of this process."""
    global _frames, _path
    from mmpa.apps.localization_settings import check_robot_localization
    from mmpa.robot.description import set_default_robot
    from mmpa.robot.robot_file import load_robot

    try:
        robot, _frames = load_robot(path)  # the backend section is checked here too
        check_robot_localization(path)  # a malformed localization section: refused now
    except MMPAError as e:
        fail(e)
    set_default_robot(robot)
    _path = path


def robot_file() -> Path | None:
    """The robot file of this process (``mmpa --robot FILE``), or None (the twin)."""
    return _path


@robot_app.command("show")
def show(
    out: Annotated[Path | None, typer.Option(help="Also write the robot file here.")] = None,
) -> None:
    """Print the robot in use (``mmpa --robot FILE robot show``; without ``--robot``, the
    twin's) as a complete robot file: a template to edit for your robot."""
    from mmpa.robot.description import default_robot
    from mmpa.robot.robot_file import frame_names, robot_backend, robot_to_yaml, save_robot

    robot = default_robot()
    try:
        backend = robot_backend(_path)
    except MMPAError as e:
        fail(e)
    typer.echo(robot_to_yaml(robot, _frames, backend=backend), nl=False)
    names = frame_names(_frames)
    typer.echo("# ROS frames: " + ", ".join(f"{k} -> {v}" for k, v in names.items()))
    if out is not None:
        try:
            save_robot(robot, out, _frames)
        except OSError as e:
            fail(MMPAError(f"cannot write {out}: {e.strerror or e}"))
        console.print(f"wrote {out}")


def register(app: typer.Typer) -> None:
    """Add ``robot`` to the main app."""
    app.add_typer(robot_app, name="robot")
