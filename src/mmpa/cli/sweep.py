"""``mmpa sweep FILE.yaml --out DIR``: a parameter sweep over experiments (the runner logic
lives in :mod:`mmpa.harness.sweep`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mmpa.cli.common import (
    ExecutorOpt,
    RayAddressOpt,
    WorkersOpt,
    console,
    fail,
    out_dir,
    progress_bar,
)
from mmpa.core.errors import MMPAError

__all__ = ["register", "sweep_cmd"]


def sweep_cmd(
    file: Annotated[Path, typer.Argument(help="Sweep file (YAML; see docs/sweep_example.yaml).")],
    out: Annotated[
        Path | None, typer.Option(help="Sweep folder (default runs/sweep-FILE_STEM).")
    ] = None,
    workers: WorkersOpt = 1,
    executor: ExecutorOpt = "local",
    ray_address: RayAddressOpt = None,
    resume: Annotated[
        bool,
        typer.Option(
            "--resume", help="Keep the finished points and trials in --out; run the rest."
        ),
    ] = False,
) -> None:
    """Sweep config fields over experiments: sweep.csv, sweep.md and one plot per field."""
    from mmpa.harness.sweep import check_run_options, load_sweep, run_sweep

    out = out or Path("runs") / f"sweep-{file.stem}"
    try:
        spec = load_sweep(file)
        check_run_options(workers, executor)
        out_dir(out)
        with progress_bar("sweep", max_chars=100) as progress:
            result = run_sweep(
                spec,
                out,
                workers=workers,
                executor=executor,
                ray_address=ray_address,
                resume=resume,
                progress=progress,
            )
    except MMPAError as e:
        fail(e)
    console.print(
        f"mmpa sweep: {len(result.points)} points -> {out} ({', '.join(result.files)})",
        highlight=False,
    )


def register(app: typer.Typer) -> None:
    """Add ``sweep`` to the root app."""
    app.command("sweep")(sweep_cmd)
