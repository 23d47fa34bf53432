"""``mmpa grasp OBJECT``: the tracking grasp (detector + IBVS) in the twin, or on the robot of
``mmpa --robot R`` (a ``ros2`` or ``direct`` backend; see :mod:`mmpa.apps.grasp`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from mmpa.cli.common import ProfileOpt, console, fail, out_dir, profile_overrides
from mmpa.cli.hardware import YesOpt, backend_in_use, confirmer, open_hardware
from mmpa.core.errors import MMPAError

__all__ = ["register"]

ConfigOpt = Annotated[
    Path | None, typer.Option("--config", "-c", help="YAML settings (GraspRunConfig).")
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option("--set", help="Override: key=value, e.g. servo.close.max_attempts=1 (repeat)."),
]


def _settings(
    config: Path | None, options: dict[str, object], profile: str | None, set_: list[str] | None
):
    """Defaults, the YAML file, ``--profile``, the options given, ``--set`` (in that order)."""
    from mmpa.apps.grasp import GraspRunConfig
    from mmpa.core.config import load_config

    given = [f"{k}={v}" for k, v in options.items() if v is not None]
    return load_config(GraspRunConfig, config, [*profile_overrides(profile), *given, *(set_ or [])])


def _show(summary: dict) -> None:
    t = Table(title=f"mmpa grasp {summary['object']} ({summary['backend']})", show_header=False)
    for k, v in summary.items():
        if k not in ("track",):
            t.add_row(k, str(v))
    console.print(t)


def grasp_cmd(
    object_: Annotated[
        str, typer.Argument(metavar="OBJECT", help="What to grasp (a detector class, e.g. cube).")
    ],
    out: Annotated[
        Path | None, typer.Option(help="Write summary.json and config.yaml here.")
    ] = None,
    seed: Annotated[int | None, typer.Option(help="Twin: the scene's draw.", min=0)] = None,
    speed: Annotated[
        float | None,
        typer.Option(help="Twin: m/s the operator moves the object at (0: still).", min=0.0),
    ] = None,
    lighting: Annotated[
        str | None, typer.Option(help="Twin: dark, normal (default) or high.")
    ] = None,
    weights: Annotated[
        str | None, typer.Option(help="Detector weights (default: the shipped model).")
    ] = None,
    profile: ProfileOpt = None,
    yes: YesOpt = False,
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """Grasp OBJECT with the tracking grasp: in the twin (default) the experiment's scene at
    the grasp desk, judged against the truth (held in the physics, the grasp error); with
    `mmpa --robot R` on a ros2 / direct robot from where the arm stands, after a question
    (--yes skips it), reporting what the robot measured. Settings, lowest first: defaults,
    --config, --profile, the options, --set. Exit status 1 when the grasp failed."""
    from mmpa.apps.grasp import grasp_on_robot, grasp_twin
    from mmpa.core.config import save_config

    options = {"seed": seed, "speed": speed, "lighting": lighting, "weights": weights}
    path, backend = backend_in_use()
    try:
        cfg = _settings(config, options, profile, set_)
        if backend.hardware:
            with open_hardware(path, ("clock", "arm", "camera", "gripper", "base")) as robot:
                summary = grasp_on_robot(
                    robot, object_, cfg, kind=backend.kind, confirm=confirmer(yes, backend)
                )
        else:
            with console.status(f"grasping the {object_} in the twin"):
                summary = grasp_twin(object_, cfg)
    except MMPAError as e:
        fail(e)
    if out is not None:
        out_dir(out)
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        save_config(cfg, out / "config.yaml")
    _show(summary)
    if not summary["ok"]:
        console.print(f"[yellow]not grasped: {summary['reason']}[/]", highlight=False)
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    """Add ``grasp`` to the main app."""
    app.command("grasp")(grasp_cmd)
