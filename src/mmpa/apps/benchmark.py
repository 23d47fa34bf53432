"""``mmpa benchmark localization DATA``: a localizer over a real log or bag, judged against
its reference trajectory (kiss-icp's pipeline is the model: a data set loader, a pipeline
that runs the method over it, an evaluation, a results folder).

:func:`run_pipeline` builds the localizer of a :class:`BenchmarkConfig`
(:func:`~mmpa.localization.settings.build_localizer`, monitored: each estimate carries its
``ok``), starts it at the reference pose of scan ``start`` moved by ``initial_offset`` (in
that pose's frame), or with particles over the whole map (``global_localization``), and feeds
it every scan with its odometry pose, timing each ``update`` call (the health monitor
included). :func:`run_benchmark` evaluates the estimates
(:func:`~mmpa.localization.evaluation.error_statistics`: mean, median, p95, max position and
heading error, the share within 5 and 10 cm, divergence: the first scan after the first 30
over 0.5 m, time per update) and writes the folder:

- ``results.json``: the data set (format, scans, map, the lidar mount and its source), the
  method, the figures, the ``ok=False`` count and first reasons, the localizer's own
  refusals (Hector's refused matches; null for the others);
- ``estimate.csv``: per scan ``t``, estimate, reference, odometry, errors, ``ok``,
  ``update_ms``;
- ``trajectory.png``: the map with the reference and the estimate, and the error per scan;
- ``config.yaml``: the final settings (rerun with ``--config config.yaml``).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from pydantic import Field

from mmpa.apps.benchmark_data import LocalizationDataset
from mmpa.backends.bag.reader import BagTopics
from mmpa.core.config import save_config
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, se2_compose
from mmpa.localization.evaluation import error_statistics, trajectory_errors
from mmpa.localization.settings import (
    LocalizationConfig,
    build_localizer,
    initial_covariance,
    start_localizer,
)

__all__ = ["BenchmarkConfig", "BenchmarkRun", "run_benchmark", "run_pipeline"]


class BenchmarkConfig(LocalizationConfig):
    """The localizer's settings and the run's. Units: m, rad."""

    method: str = "amcl"  # a real log has no reflectors: enhanced refuses such a map
    seed: int = Field(0, ge=0)  # the localizer's random stream
    start: int = Field(0, ge=0)  # first scan
    max_scans: int | None = Field(None, ge=1)
    # [dx, dy, dyaw] added to the reference pose of the first scan, in its frame
    initial_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    global_localization: bool = False  # particles over the whole map (amcl, enhanced)
    force: bool = False  # force every filter update
    map_resolution: float = Field(0.05, gt=0)  # m: a CARMEN log's map built from it
    divergence: float = Field(0.5, gt=0)  # m
    divergence_after: int = Field(30, ge=0)  # scans
    laser_pose: tuple[float, float, float] | None = None  # bags: --laser-pose
    topics: BagTopics = BagTopics()


@dataclass
class BenchmarkRun:
    """Per scan: ``t`` (N,) s, ``estimate`` / ``truth`` / ``odom`` (N, 3), ``ok`` (N,),
    ``reason`` (N,), ``update_s`` (N,) wall time of each update."""

    t: Array
    estimate: Array
    truth: Array
    odom: Array
    ok: Array
    reason: list[str]
    update_s: Array
    refused: Array | None = None  # per scan: the localizer refused its match (Hector); None
    # for localizers without refusals of their own


def _initial_pose(ds: LocalizationDataset, cfg: BenchmarkConfig) -> Array:
    return se2_compose(ds[cfg.start].truth, np.asarray(cfg.initial_offset, float))


def run_pipeline(ds: LocalizationDataset, cfg: BenchmarkConfig) -> BenchmarkRun:
    """Run ``cfg``'s localizer over ``ds`` (module docstring)."""
    if cfg.start >= len(ds):
        raise InvalidInputError(f"start {cfg.start}: the data set has {len(ds)} scans")
    stop = len(ds) if cfg.max_scans is None else min(len(ds), cfg.start + cfg.max_scans)
    loc = build_localizer(cfg, ds.grid, ds.laser_pose, np.random.default_rng(cfg.seed))
    pose0 = None if cfg.global_localization else _initial_pose(ds, cfg)
    start_localizer(loc, cfg.method, pose0, initial_covariance(cfg), cfg.global_localization)
    rows: list[tuple[float, Array, Array, Array, bool, str, float]] = []
    counts = hasattr(loc, "refusals")  # Hector counts the matches it refused
    refused: list[bool] = []
    for i in range(cfg.start, stop):
        f = ds[i]
        before = int(getattr(loc, "refusals", 0))
        t0 = time.perf_counter()
        est = loc.update(f.odom, f.scan, force=cfg.force)
        dt = time.perf_counter() - t0
        refused.append(int(getattr(loc, "refusals", 0)) > before)
        rows.append((f.t, loc.pose_at(f.odom), f.truth, f.odom, bool(est.ok), est.reason, dt))
    return BenchmarkRun(
        t=np.array([r[0] for r in rows]),
        estimate=np.array([r[1] for r in rows]),
        truth=np.array([r[2] for r in rows]),
        odom=np.array([r[3] for r in rows]),
        ok=np.array([r[4] for r in rows]),
        reason=[r[5] for r in rows],
        update_s=np.array([r[6] for r in rows]),
        refused=np.array(refused) if counts else None,
    )


def _write_csv(path: Path, run: BenchmarkRun) -> None:
    pos, yaw = trajectory_errors(run.estimate, run.truth)
    cols = "t,x,y,theta,truth_x,truth_y,truth_theta,odom_x,odom_y,odom_theta"
    cols += ",error_mm,heading_error_deg,ok,update_ms"
    table = np.column_stack(
        [
            run.t,
            run.estimate,
            run.truth,
            run.odom,
            pos * 1e3,
            np.rad2deg(yaw),
            run.ok.astype(float),
            run.update_s * 1e3,
        ]
    )
    np.savetxt(path, table, delimiter=",", header=cols, comments="", fmt="%.9g")


def _plot(path: Path, run: BenchmarkRun, ds: LocalizationDataset, stats: dict, title: str) -> None:
    fig = Figure(figsize=(12, 5.5))
    FigureCanvasAgg(fig)
    ax, ax2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.3, 1]})
    g = ds.grid
    x0, y0 = g.origin[0], g.origin[1]
    ext = (x0, x0 + g.width * g.resolution, y0, y0 + g.height * g.resolution)
    ax.imshow(g.occupied, origin="lower", extent=ext, cmap="Greys", alpha=0.6)
    ax.plot(*run.truth[:, :2].T, "-", color="green", lw=3, alpha=0.5, label="reference")
    ax.plot(*run.estimate[:, :2].T, ".-", color="C0", ms=2, lw=0.8, label="estimate")
    k = stats.get("diverged_at_scan")
    if k is not None:
        ax.plot(*run.estimate[k, :2], "x", color="red", ms=10, label=f"diverged (scan {k})")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title)
    pos, _ = trajectory_errors(run.estimate, run.truth)
    ax2.semilogy(np.maximum(pos, 1e-4), ".", ms=2, color="C0")
    for v, c in ((0.05, "C2"), (0.10, "C1"), (stats["divergence_m"], "C3")):
        ax2.axhline(v, color=c, lw=0.8, ls="--", label=f"{v:g} m")
    ax2.set_xlabel("scan")
    ax2.set_ylabel("position error (m)")
    ax2.legend(loc="best", fontsize=8)
    ax2.set_title(
        f"median {stats['error_median_mm']:.0f} mm, p95 {stats['error_p95_mm']:.0f} mm, "
        f"within 10 cm {100 * stats['within_10cm']:.0f} %"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def run_benchmark(ds: LocalizationDataset, cfg: BenchmarkConfig, out: str | Path) -> dict:
    """Run, evaluate and write the folder ``out`` (module docstring); returns the results."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    run = run_pipeline(ds, cfg)
    stats = error_statistics(
        run.estimate, run.truth, run.t, run.update_s, cfg.divergence, cfg.divergence_after
    )
    results: dict = {
        "dataset": ds.name,
        "format": ds.format,
        "scans_in_dataset": len(ds),
        "map": ds.map_source,
        "laser_pose": [round(float(v), 6) for v in ds.laser_pose],
        "laser_pose_source": ds.laser_pose_source,
        "method": cfg.method,
        "seed": cfg.seed,
        "start": "global" if cfg.global_localization else list(cfg.initial_offset),
        "first_scan": cfg.start,
        **stats,
        "not_ok": int(np.sum(~run.ok)),
        "refusals": None if run.refused is None else int(np.sum(run.refused)),
        "not_ok_reasons": list(dict.fromkeys(r for r in run.reason if r))[:5],
        "compute_s": round(float(np.sum(run.update_s)), 3),
    }
    _write_csv(out / "estimate.csv", run)
    title = f"{ds.name}: {cfg.method} ({len(run.t)} scans)"
    _plot(out / "trajectory.png", run, ds, stats, title)
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    save_config(cfg, out / "config.yaml")
    return results
