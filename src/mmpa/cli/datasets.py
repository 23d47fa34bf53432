"""``mmpa convert carmen LOG --out BAG.mcap`` and ``mmpa benchmark localization DATA``: real
logs in, a benchmark out (see :mod:`mmpa.apps.convert`, :mod:`mmpa.apps.benchmark`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from mmpa.cli.bags import (
    ConfigOpt,
    InitialCovOpt,
    SetOpt,
    _pose3,
    _robot_laser_pose,
    parse_cov3,
    robot_file,
)
from mmpa.cli.common import console, fail, in_range, out_dir
from mmpa.core.errors import MMPAError

__all__ = ["register"]

convert_app = typer.Typer(help="Convert recordings to ROS 2 bags.", no_args_is_help=True)
benchmark_app = typer.Typer(help="Benchmarks on real data.", no_args_is_help=True)


def _show(summary: dict, title: str) -> None:
    t = Table(title=title, show_header=False)
    for k, v in summary.items():
        t.add_row(k, str(v))
    console.print(t)


@convert_app.command("carmen")
def convert_carmen_cmd(
    log: Annotated[Path, typer.Argument(help="CARMEN log (.log or .log.gz).")],
    out: Annotated[Path, typer.Option(help="Bag to write: FILE.mcap or a rosbag2 folder.")],
    map_yaml: Annotated[
        Path | None,
        typer.Option(
            "--map", help="Also build the map from the log: map_server YAML (+ PGM) here, /map."
        ),
    ] = None,
    resolution: Annotated[
        float,
        typer.Option(help="Map cell size (m).", callback=in_range(0.005, 1.0, closed=True)),
    ] = 0.05,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing bag.")] = False,
) -> None:
    """A CARMEN laser log as a ROS 2 bag: /scan, /odom, /tf (odom -> base_link), /tf_static
    (base_link -> laser), /truth/base_pose (the corrected pose), /initialpose, /map."""
    from mmpa.apps.convert import convert_carmen

    try:
        with console.status(f"converting {log}"):
            summary = convert_carmen(log, out, map_yaml, resolution, overwrite)
    except MMPAError as e:
        fail(e)
    _show(summary, f"mmpa convert carmen -> {out}")


@benchmark_app.command("localization")
def benchmark_localization_cmd(
    ctx: typer.Context,
    data: Annotated[
        Path, typer.Argument(help="CARMEN log (.log, .log.gz) or bag with /truth/base_pose.")
    ],
    map_yaml: Annotated[
        Path | None,
        typer.Option("--map", help="map_server YAML (default: built from the log / the bag's)."),
    ] = None,
    method: Annotated[
        str | None,
        typer.Option(help="amcl (default) | enhanced | enhanced-paper | tamcl | hector | ..."),
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="Results folder (default runs/benchmark/DATA-METHOD).")
    ] = None,
    seed: Annotated[int | None, typer.Option(help="Localizer seed (default 0).", min=0)] = None,
    start: Annotated[int | None, typer.Option(help="First scan (default 0).", min=0)] = None,
    max_scans: Annotated[int | None, typer.Option(help="Scans to run.", min=1)] = None,
    initial_offset: Annotated[
        str | None,
        typer.Option(help="'dx,dy,dyaw' added to the reference start pose (its frame)."),
    ] = None,
    initial_cov: InitialCovOpt = None,
    global_: Annotated[
        bool | None,
        typer.Option("--global", help="Global localization: no initial pose (amcl, enhanced)."),
    ] = None,
    laser_pose: Annotated[
        str | None, typer.Option(help="Bags: lidar mount 'x,y,yaw' in base_link.")
    ] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """Run a localizer over a real log or bag; report the error against its reference
    trajectory (mean, median, p95, max, heading, within 5 / 10 cm, divergence, time per
    update); write results.json, estimate.csv, trajectory.png and config.yaml."""
    from mmpa.apps.benchmark import BenchmarkConfig, run_benchmark
    from mmpa.apps.benchmark_data import open_dataset
    from mmpa.apps.localization_settings import load_localization_config

    try:
        options = {
            "method": method,
            "seed": seed,
            "start": start,
            "max_scans": max_scans,
            "initial_offset": _pose3(initial_offset, "--initial-offset"),
            "initial_cov": parse_cov3(initial_cov),
            "global_localization": global_,
            "laser_pose": _pose3(laser_pose, "--laser-pose"),
        }
        cfg = load_localization_config(
            BenchmarkConfig, robot_file(ctx), config, options, set_ or []
        )
        with console.status(f"loading {data}"):
            ds = open_dataset(
                data,
                map_yaml,
                resolution=cfg.map_resolution,
                topics=cfg.topics,
                laser_pose=cfg.laser_pose,
                robot_laser_pose=_robot_laser_pose(ctx),
            )
        folder = out or Path("runs/benchmark") / f"{ds.name}-{cfg.method}"
        with console.status(f"{cfg.method} over {ds.name} ({len(ds)} scans)"):
            results = run_benchmark(ds, cfg, out_dir(folder))
    except MMPAError as e:
        fail(e)
    _show(results, f"mmpa benchmark localization -> {folder}")


def register(app: typer.Typer) -> None:
    """Add ``convert`` and ``benchmark`` to the root app."""
    app.add_typer(convert_app, name="convert")
    app.add_typer(benchmark_app, name="benchmark")
