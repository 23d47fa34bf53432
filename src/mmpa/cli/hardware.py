"""What the mission commands share on a hardware backend (``mmpa --robot R ...`` with a
``ros2`` or ``direct`` robot file): the robot file's backend, opening the robot
(:func:`mmpa.apps.robots.open_robot`) and the question asked before the arm moves
(``--yes`` skips it, as does the robot file's ``backend.safety.confirm: false``)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any

import typer

from mmpa.cli.common import fail
from mmpa.cli.robot import robot_file
from mmpa.core.errors import MMPAError

__all__ = ["YesOpt", "backend_in_use", "confirmer", "open_hardware"]

YesOpt = Annotated[
    bool,
    typer.Option("--yes", "-y", help="On a hardware backend: move without asking first."),
]


def backend_in_use() -> tuple[Path | None, Any]:
    """The robot file of this process (``mmpa --robot FILE``; None: the twin) and its
    ``backend`` section (:class:`~mmpa.robot.backend_config.BackendConfig`)."""
    from mmpa.robot.robot_file import robot_backend

    path = robot_file()
    try:
        return path, robot_backend(path)
    except MMPAError as e:
        fail(e)


def confirmer(yes: bool, backend: Any) -> Callable[[str], bool] | None:
    """The question before the arm moves (``typer.confirm``, default no), or None when
    ``--yes`` is given or the robot file says ``safety.confirm: false``."""
    if yes or not backend.safety.confirm:
        return None
    return lambda question: typer.confirm(question, default=False)


@contextmanager
def open_hardware(path: Path, devices: tuple[str, ...] | None = None) -> Iterator[Any]:
    """The hardware robot of robot file ``path`` (:func:`mmpa.apps.robots.open_robot`) with
    ``devices`` waited for (None: all it has; absent ones are skipped), closed after."""
    from mmpa.apps.robots import open_robot

    with open_robot(path, devices) as robot:
        yield robot
