"""``mmpa navigate --to SITE`` and ``mmpa map export``: localization and navigation in the twin."""

from __future__ import annotations

import json
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from mmpa.cli.common import ProfileOpt, console, fail, in_range, out_dir, robot_reflector_map
from mmpa.errors import MMPAError

if TYPE_CHECKING:  # pragma: no cover
    from mmpa.localization.maps import OccupancyGrid

__all__ = ["register"]

map_app = typer.Typer(help="Occupancy maps (ROS map_server format).", no_args_is_help=True)


def _errors(seed: int, profile: str | None):
    """The twin's error model: ``--profile`` (default realistic) for robot instance ``seed``
    (a ``ConfigError`` for an unknown profile)."""
    from mmpa.config import load_config
    from mmpa.sim.error_model import ErrorModelConfig

    sets = [f"seed={seed}"] + ([] if profile is None else [f"profile={profile}"])
    return load_config(ErrorModelConfig, None, sets)


def _with_reflectors(grid: OccupancyGrid, path: Path | None) -> OccupancyGrid:
    """``grid`` with the reflectors of the reflector map file ``path`` (None: as it is)."""
    if path is None:
        return grid
    import dataclasses

    import numpy as np

    from mmpa.errors import ConfigError
    from mmpa.localization.reflector_map import load_reflector_map

    rm = load_reflector_map(path)
    if np.ptp(rm.radius) > 1e-9:
        raise ConfigError(f"{path}: reflectors of different radii; the localizer takes one")
    return dataclasses.replace(grid, reflectors=rm.xy.copy(), reflector_radius=float(rm.radius[0]))


def _health_summary(trace: dict) -> dict:
    """The localizer's health over a drive (:mod:`mmpa.localization.health`): updates that
    said ``ok=False`` and the least explained share (when any was judged)."""
    import numpy as np

    ok, expl = trace["ok"].astype(bool), trace["explained"]
    out: dict = {"localization_updates_not_ok": int(np.sum(~ok))}
    if np.isfinite(expl).any():
        out["localization_explained_min"] = round(float(np.nanmin(expl)), 3)
    return out


def navigate_cmd(
    ctx: typer.Context,
    to: Annotated[str, typer.Option("--to", help="Goal site (e.g. 1, 2).")],
    start: Annotated[str, typer.Option("--from", help="Start site.")] = "0",
    method: Annotated[
        str, typer.Option(help="amcl | enhanced | enhanced-paper | trilateration | tamcl | hector")
    ] = "enhanced",
    seed: Annotated[int, typer.Option(help="Robot instance / noise seed.", min=0)] = 0,
    out: Annotated[Path | None, typer.Option(help="Write summary.json here.")] = None,
    timeout: Annotated[
        float, typer.Option(help="Simulated seconds.", callback=in_range(0.0, 86400.0))
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
) -> None:
    """Drive the twin from a site to ``--to`` on the localization estimate (started from the
    operator's rough pose); print the parking error (truth vs goal) and the localization error
    (estimate vs truth) at the end."""
    import numpy as np

    from mmpa.localization.localizer import make_localizer
    from mmpa.navigation.mission import NavigateConfig, navigate
    from mmpa.navigation.planner import CostMap
    from mmpa.sim.operator import rough_initial_pose
    from mmpa.sim.twin_maps import laser_pose2d, twin_map, twin_nav_map
    from mmpa.sim.world import SimWorld

    bag = None
    try:
        errors = _errors(seed, profile)
        refl_map = reflectors or robot_reflector_map(ctx)
        with SimWorld(errors=errors, site=start) as world, ExitStack() as stack:
            goal = world.scene.site(to).pose2d
            grid = _with_reflectors(twin_map(world), refl_map)
            loc = make_localizer(method, grid, laser_pose2d(world), np.random.default_rng(seed))
            robot = world
            if record is not None:  # the same run, observed (mmpa.bags.Recorder)
                from mmpa.bags import BagWriter, Recorder
                from mmpa.bags.record import ARM_RATE_HZ

                bag = stack.enter_context(BagWriter(record, overwrite=True))
                # /joint_states and the arm's /tf every 20 ms of sim time, as a robot's
                # joint_state_broadcaster publishes them
                recorder = stack.enter_context(Recorder(bag, world, joint_rate_hz=ARM_RATE_HZ))
                robot = recorder.world()
                recorder.write_map(grid)
                loc = recorder.localizer(loc)
            loc.initialize(rough_initial_pose(world))  # the operator's rough pose
            with console.status(f"navigating site {start} -> site {to} ({method})"):
                cm = CostMap(twin_nav_map(world))
                res = navigate(robot, loc, grid, goal, NavigateConfig(timeout=timeout), costmap=cm)
    except MMPAError as e:
        fail(e)
    e = res.localization_error
    summary = {
        "from": start,
        "to": to,
        "method": method,
        "profile": errors.profile,
        "reached": res.reached,
        "corrections": res.corrections,
        "sim_seconds": round(res.sim_time, 2),
        "parking_error_xy_mm": round(1000 * res.parking_error_xy, 2),
        "parking_error_yaw_deg": round(float(np.rad2deg(res.parking_error_yaw)), 3),
        "localization_error_xy_mm": round(1000 * float(np.hypot(e[0], e[1])), 2),
        "localization_error_yaw_deg": round(float(np.rad2deg(abs(e[2]))), 3),
    }
    summary.update(_health_summary(res.trace))
    if not res.reached:
        summary["reason"] = res.reason
    if refl_map is not None:
        summary["reflector_map"] = str(refl_map)
    if bag is not None:
        summary["bag"] = str(record)
        summary["bag_messages"] = sum(bag.counts.values())
    if out is not None:
        out_dir(out)
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    t = Table(title=f"mmpa navigate --to {to}", show_header=False)
    for k, v in summary.items():
        t.add_row(k, str(v))
    console.print(t)
    if not res.reached:
        console.print(f"[yellow]not reached: {res.reason}[/]")
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
    from mmpa.localization.maps import save_map
    from mmpa.sim.twin_maps import twin_map
    from mmpa.sim.world import SimWorld

    out_dir(out.parent)
    try:
        with SimWorld(errors=_errors(seed, profile)) as world:
            grid = twin_map(world, resolution)
        path = save_map(grid, out)
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
