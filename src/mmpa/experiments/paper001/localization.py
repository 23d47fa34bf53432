"""Paper 001 Table 2 / Fig. 9: localization accuracy at the target after driving there.

Each trial: the robot starts at a random pose in the corridor, is told a rough initial pose
(truth + N(0, ``init_sigma_xy``) per axis, N(0, ``init_sigma_theta``); by default the
operator's error of the twin's error model, ``errors.operator``), and navigates to the
target site in the lobby (A* + pure pursuit + final approach) steering on the method's OWN
estimate. At the end we compare the estimate with the truth (the paper's position error,
success = error < 12 mm) and also report the parking error (truth vs goal).

Second part (``kidnap_trials``): kidnapped-robot recovery. The robot, well localized at the
target, is carried to another site without the localizer knowing; it then turns slowly on the
spot and we measure the time until the estimate is within 5 cm of the truth again.

The twin's error model is ``errors`` (profile ``realistic`` by default); its seed, the robot
instance, follows ``seed`` unless ``errors.seed`` is given.

Lidar mount self-calibration (``calibrate_mount``, improvement): before the trials the robot
turns once on the spot at the goal site (:func:`twin_mount_calibration`, the robot's own
odometry and scans against the map) and the methods in ``calibrated_methods`` (ours) get the
calibrated mount; the others (the paper's methods) keep the nominal one.
"""

from __future__ import annotations

import json
import time
from contextlib import ExitStack
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from pydantic import BaseModel, ConfigDict, Field, model_validator

from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.lidar_noise import rough_pose
from mmpa.backends.twin.operator import rough_initial_pose
from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map, twin_nav_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.geometry import wrap_angle
from mmpa.harness.recording import recording_folder, trial_recorder
from mmpa.harness.runner import Context, Outcome, markdown_table, run_trials, stats
from mmpa.harness.twin_localization import errors_follow_seed, twin_localizer
from mmpa.localization.amcl import AMCLConfig
from mmpa.localization.hector import HectorConfig
from mmpa.localization.localizer import METHODS
from mmpa.missions.navigate import NavigateConfig, navigate
from mmpa.navigation.mount_calibration import MountCalibrationConfig, calibrate_lidar_mount
from mmpa.navigation.planner import CostMap

PAPER = "paper 001 (Zhou et al. 2020) §4.3.1, Table 2 and Fig. 9"
#: the runner may run this experiment's trials on an executor (``--workers``, ``--executor``)
PARALLEL_TRIALS = True
#: every navigation trial can record itself to a bag of its own (``--record DIR``)
RECORDS_TRIALS = True

PAPER_TABLE2 = {
    "amcl": {"x": 3.91, "y": 3.32, "pos": 5.14, "theta": 0.027, "success": 0.20},
    "hector": {"x": 4.63, "y": 3.84, "pos": 6.12, "theta": 0.032, "success": 0.35},
    "enhanced": {"x": 0.82, "y": 0.73, "pos": 1.09, "theta": 0.017, "success": 0.90},
}
LABELS = {
    "amcl": "AMCL [5]",
    "hector": "Hector-SLAM [35]",
    "enhanced": "Ours (enhanced AMCL)",
    "enhanced-paper": "Ours, Algorithm 1 as printed",
    "trilateration": "Trilateration only",
    "tamcl": "T-AMCL",
}


class TwinLocalization(BaseModel):
    """The fields the localization experiments share: the twin's error model (its seed, the
    robot instance, follows the experiment's ``seed`` unless given) and the lidar mount
    calibration of the methods in ``calibrated_methods``."""

    errors: ErrorModelConfig = ErrorModelConfig()
    # improvement: lidar mount calibrated by a turn on the spot, for these methods
    calibrate_mount: bool = True
    calibrated_methods: list[str] = Field(default_factory=lambda: ["enhanced"])
    mount_calibration: MountCalibrationConfig = MountCalibrationConfig()

    @model_validator(mode="after")
    def _robot_seed(self) -> TwinLocalization:
        return errors_follow_seed(self)


class Config(TwinLocalization):
    model_config = ConfigDict(extra="forbid", coerce_numbers_to_str=True)

    seed: int = Field(0, ge=0)  # every random draw flows from it (numpy: >= 0)
    trials: int | None = None  # paper: 20 per method
    methods: list[str] = Field(
        default_factory=lambda: ["amcl", "hector", "enhanced", "enhanced-paper"]
    )
    goal_site: str = "1"
    corridor_x: tuple[float, float] = (-10.5, -4.0)
    corridor_y: tuple[float, float] = (0.75, 1.65)
    start_clearance: float = Field(0.55, gt=0)  # m from obstacles (circumscribed radius 0.48)
    # the rough initial pose's error (m, rad); None: the error model's operator section
    init_sigma_xy: float | None = Field(None, ge=0)
    init_sigma_theta: float | None = Field(None, ge=0)
    success_threshold: float = Field(0.012, gt=0)  # m (paper: 12 mm)
    resolution: float = Field(0.05, gt=0)
    navigate: NavigateConfig = NavigateConfig(scan_rate=5.0, timeout=150.0)
    kidnap_trials: int = Field(3, ge=0)
    kidnap_site: str = "2"
    kidnap_duration: float = Field(30.0, gt=0)
    kidnap_amcl: AMCLConfig = AMCLConfig.paper().model_copy(
        update={"recovery_alpha_slow": 0.001, "recovery_alpha_fast": 0.1}
    )
    # the paper's baseline "AMCL [5]" (and the AMCL inside the other methods): Nav2's AMCL as
    # the paper ran it (AMCLConfig.paper()); mmpa's own defaults (scan refinement,
    # docs/localization.md "Real logs"): `amcl: {}` in a --config file
    amcl: AMCLConfig = Field(default_factory=AMCLConfig.paper)
    # the paper's baseline "Hector-SLAM [35]" as published (Kohlbrecher et al. 2011); mmpa's
    # own Hector (distance field, damped steps, a search; docs/localization.md): `hector: {}`
    # in a --config file (HectorConfig's defaults)
    hector: HectorConfig = Field(default_factory=HectorConfig.paper)


#: twin_mount_calibration's results in this process, by its arguments
_MOUNTS: dict[str, tuple[np.ndarray | None, float]] = {}


def twin_mount_calibration(
    errors: ErrorModelConfig,
    site: str,
    seed: int,
    resolution: float = 0.05,
    cfg: MountCalibrationConfig | None = None,
) -> tuple[np.ndarray | None, float]:
    """The robot instance ``errors`` turns once on the spot at ``site`` (its own episode,
    so no trial's draws change) and fits its lidar mount from its odometry and scans against
    the map (:func:`~mmpa.navigation.mount_calibration.calibrate_lidar_mount`), from the
    operator's rough pose. Returns the calibrated mount ``[x, y, theta]`` (None if the fit was
    not trusted) and the fit's RMS (m). A function of its arguments alone (its own seeded
    episode), so it is remembered per process: the experiments of one run or sweep on the
    same robot instance calibrate it once."""
    settings = None if cfg is None else cfg.model_dump(mode="json")
    key = json.dumps(
        [errors.model_dump(mode="json"), site, seed, resolution, settings], sort_keys=True
    )
    if key not in _MOUNTS:
        _MOUNTS[key] = _calibrate_mount(errors, site, seed, resolution, cfg)
    mount, rms = _MOUNTS[key]
    return (None if mount is None else mount.copy()), rms


def _calibrate_mount(
    errors: ErrorModelConfig,
    site: str,
    seed: int,
    resolution: float,
    cfg: MountCalibrationConfig | None,
) -> tuple[np.ndarray | None, float]:
    with SimWorld(errors=errors, site=site, episode=1_000_000) as w:
        grid = twin_map(w, resolution)
        guess = rough_initial_pose(w, np.random.default_rng([seed, 1_000_000]))
        cal = calibrate_lidar_mount(
            w, grid, laser_pose2d(w), guess, cfg, np.random.default_rng([seed, 1_000_001])
        )
    return cal.mount, cal.fit.rms


def method_mounts(cfg: Any, methods: list[str], site: str) -> dict[str, np.ndarray | None]:
    """Per method the mount to give its localizer: the calibrated one
    (:func:`twin_mount_calibration` at ``site``, once) for ``cfg.calibrated_methods`` when
    ``cfg.calibrate_mount``, else None (the nominal mount)."""
    want = [m for m in methods if cfg.calibrate_mount and m in cfg.calibrated_methods]
    mount = None
    if want:
        mount, _ = twin_mount_calibration(cfg.errors, site, cfg.seed, cfg=cfg.mount_calibration)
    return {m: (mount if m in want else None) for m in methods}


def initial_sigmas(cfg: Any) -> tuple[float, float]:
    """``(sigma_xy m, sigma_theta rad)`` of the rough initial pose: ``cfg.init_sigma_xy`` /
    ``cfg.init_sigma_theta`` where given, else the error model's operator error."""
    op = cfg.errors.operator
    xy = op.initial_pos_sigma if cfg.init_sigma_xy is None else cfg.init_sigma_xy
    th = (
        np.deg2rad(op.initial_yaw_sigma_deg)
        if cfg.init_sigma_theta is None
        else cfg.init_sigma_theta
    )
    return float(xy), float(th)


def corridor_start(nav: CostMap, rng: np.random.Generator, cfg: Any) -> np.ndarray:
    """A random start ``[x, y, theta]`` in the corridor (``cfg.corridor_x``, ``cfg.corridor_y``)
    whose whole footprint is clear: obstacle distance >= ``cfg.start_clearance`` (m)."""
    start = np.zeros(3)
    for _ in range(1000):
        start = np.array(
            [
                rng.uniform(*cfg.corridor_x),
                rng.uniform(*cfg.corridor_y),
                rng.uniform(-np.pi, np.pi),
            ]
        )
        c, r = nav.grid.world_to_cell(start[:2])
        if nav.dist[r, c] >= cfg.start_clearance:
            break
    return start


def _trial(
    cfg: Config,
    k: int,
    method: str,
    mount: np.ndarray | None = None,
    record: str | None = None,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Navigation trial ``k`` of ``method``: its row and trace. ``record``: a folder for the
    trial's ROS 2 bag (``method-M-site-0-trial-k.mcap``: scans, odometry, the map, the
    estimates, the particles, the truth; ``mmpa experiment --record``)."""
    rng = np.random.default_rng([cfg.seed, k])
    with SimWorld(errors=cfg.errors, site="0", episode=k) as world, ExitStack() as stack:
        nav = CostMap(twin_nav_map(world, cfg.resolution))
        start = corridor_start(nav, rng, cfg)
        guess = rough_pose(start, rng, *initial_sigmas(cfg))  # the operator's rough pose
        world.reset(pose2d=start)
        grid = twin_map(world, cfg.resolution)
        rng_k = np.random.default_rng([cfg.seed, k, 7])
        loc = twin_localizer(
            world, method, rng_k, grid=grid, mount=mount, amcl=cfg.amcl, hector=cfg.hector
        )
        robot: Any = world
        if record is not None:  # the same trial, observed (mmpa.backends.bag.Recorder)
            label = {"method": method}
            rec = stack.enter_context(trial_recorder(record, label, "0", k, world))
            robot, loc = rec.world(), rec.localizer(loc)
            rec.write_map(grid)
        loc.initialize(guess)
        goal = world.scene.site(cfg.goal_site).pose2d
        t0 = time.perf_counter()
        res = navigate(
            robot,
            loc,
            grid,
            goal,
            cfg.navigate,
            costmap=CostMap(twin_nav_map(world, cfg.resolution)),
            truth=world.truth.base_pose2d,
        )
        wall = time.perf_counter() - t0
    e = res.localization_error
    exy = float(np.hypot(e[0], e[1]))
    row = {
        "trial": k,
        "method": method,
        "start_x": start[0],
        "start_y": start[1],
        "start_theta": start[2],
        "err_x_m": abs(float(e[0])),
        "err_y_m": abs(float(e[1])),
        "err_pos_m": exy,
        "err_theta_rad": abs(float(e[2])),
        "success": bool(exy < cfg.success_threshold),
        "parking_err_m": res.parking_error_xy,
        "parking_err_yaw_rad": res.parking_error_yaw,
        "reached": res.reached,
        "sim_seconds": res.sim_time,
        "wall_seconds": wall,
    }
    return row, res.trace


def _kidnap(cfg: Config, k: int, method: str, mount: np.ndarray | None = None) -> dict[str, Any]:
    """Localize at the goal site (from the operator's rough pose, 5 standing scans), carry the
    robot to ``kidnap_site``, turn slowly; time to recover (estimate within 5 cm / 0.05 rad
    of the truth for 1 s)."""
    with SimWorld(errors=cfg.errors, site=cfg.goal_site, episode=100 + k) as w:
        grid = twin_map(w, cfg.resolution)
        amcl = cfg.kidnap_amcl
        rng_k = np.random.default_rng([cfg.seed, k, 9])
        loc = twin_localizer(w, method, rng_k, grid=grid, mount=mount, amcl=amcl, hector=cfg.hector)
        guess_rng = np.random.default_rng([cfg.seed, k, 10])
        loc.initialize(rough_pose(w.truth.base_pose2d(), guess_rng, *initial_sigmas(cfg)))
        dt = 1.0 / cfg.navigate.scan_rate
        for _ in range(5):
            w.step(dt)
            loc.update(w.odometry.odometry().pose, w.lidar.scan(), force=True)
        w.reset(cfg.kidnap_site)  # kidnapped: the localizer is not told
        t0 = w.time
        good_since: float | None = None
        recovered = float("nan")
        while w.time - t0 < cfg.kidnap_duration:
            w.base.set_velocity(0.0, 0.25)
            w.step(dt)
            odom = w.odometry.odometry().pose
            loc.update(odom, w.lidar.scan())
            est, tru = loc.pose_at(odom), w.truth.base_pose2d()
            ok = np.hypot(*(est[:2] - tru[:2])) < 0.05 and abs(wrap_angle(est[2] - tru[2])) < 0.05
            if ok:
                good_since = w.time if good_since is None else good_since
                if w.time - good_since >= 1.0:
                    recovered = good_since - t0
                    break
            else:
                good_since = None
    return {"kidnap_trial": k, "method": method, "recovery_s": recovered}


def trial_job(
    cfg_json: str, k: int, method: str, mount: list[float] | None, record: str | None
) -> dict[str, Any]:
    """Navigation trial ``k`` of ``method`` (a worker job): ``{"row", "trace"}`` (the trace
    only for trial 0, the one plotted). Its world, map and generators are its own."""
    cfg = Config.model_validate_json(cfg_json)
    m = None if mount is None else np.asarray(mount, float)
    row, trace = _trial(cfg, k, method, m, record)
    return {"row": row, "trace": trace if k == 0 else None}


def kidnap_job(cfg_json: str, k: int, method: str, mount: list[float] | None) -> dict[str, Any]:
    """Kidnap trial ``k`` of ``method`` (a worker job): its row."""
    cfg = Config.model_validate_json(cfg_json)
    return _kidnap(cfg, k, method, None if mount is None else np.asarray(mount, float))


def run(cfg: Config, ctx: Context) -> Outcome:
    """The navigation and kidnap trials (:func:`run_localization_trials`), the summary per
    method beside Table 2, Fig. 9 and the report."""
    for m in cfg.methods:
        if m not in METHODS:
            raise ValueError(f"unknown method {m!r}; valid: {', '.join(METHODS)}")
    n = cfg.trials if cfg.trials is not None else 20
    mounts = method_mounts(cfg, cfg.methods, cfg.goal_site)
    rows, traces, kid_rows = run_localization_trials(cfg, ctx, n, mounts)
    summary: dict[str, Any] = {"trials_per_method": n, "methods": {}}
    cal = next((v for v in mounts.values() if v is not None), None)
    summary["calibrated_mount"] = None if cal is None else [float(x) for x in cal]
    table = _method_table(cfg, rows, kid_rows, summary)
    figs = _plots(ctx, traces)
    report = _report(cfg, n, mounts, table)
    if kid_rows:
        report += _kidnap_report(cfg, summary)
    if figs:
        report += "\n" + "\n".join(f"![{f}]({f})" for f in figs) + "\n"
    return Outcome(rows + kid_rows, summary, report, figs)


def run_localization_trials(
    cfg: Config, ctx: Context, n: int, mounts: dict[str, np.ndarray | None]
) -> tuple[list[dict[str, Any]], dict[str, dict[str, np.ndarray]], list[dict[str, Any]]]:
    """``n`` navigation trials and ``cfg.kidnap_trials`` kidnap trials per method on
    ``ctx``'s executor: the navigation rows, trial 0's trace per method, the kidnap rows."""
    ml = {m: None if v is None else [float(x) for x in v] for m, v in mounts.items()}
    cfg_json = cfg.model_dump_json()
    rec = recording_folder()  # mmpa experiment --record
    jobs: list = [
        ({"method": m, "trial": k}, trial_job, (cfg_json, k, m, ml[m], rec))
        for k in range(n)
        for m in cfg.methods
    ]
    jobs += [
        ({"method": m, "kidnap_trial": k}, kidnap_job, (cfg_json, k, m, ml[m]))
        for k in range(cfg.kidnap_trials)
        for m in cfg.methods
    ]
    recs = run_trials(ctx, jobs, "trials")
    rows: list[dict[str, Any]] = []
    traces: dict[str, dict[str, np.ndarray]] = {}
    for r in recs[: n * len(cfg.methods)]:
        res = r["result"]
        rows.append({**res["row"], "trial_s": r["trial_s"], "worker_rss_mb": r["worker_rss_mb"]})
        if res["trace"] is not None:
            traces[res["row"]["method"]] = {k: np.asarray(v) for k, v in res["trace"].items()}
    kid_rows = [r["result"] for r in recs[n * len(cfg.methods) :]]
    return rows, traces, kid_rows


def _method_table(
    cfg: Config,
    rows: list[dict[str, Any]],
    kid_rows: list[dict[str, Any]],
    summary: dict[str, Any],
) -> list[list[Any]]:
    """Per method into ``summary["methods"]``: mean errors (cm, rad), success, parking,
    reached, the kidnap recovery; the table's lines beside the paper's Table 2."""
    table = []
    for m in cfg.methods:
        r = [x for x in rows if x["method"] == m]
        s = {
            "err_x_cm": stats(100 * x["err_x_m"] for x in r)["mean"],
            "err_y_cm": stats(100 * x["err_y_m"] for x in r)["mean"],
            "err_pos_cm": stats(100 * x["err_pos_m"] for x in r)["mean"],
            "err_pos_cm_max": stats(100 * x["err_pos_m"] for x in r)["max"],
            "err_theta_rad": stats(x["err_theta_rad"] for x in r)["mean"],
            "success": float(np.mean([x["success"] for x in r])),
            "parking_err_cm": stats(100 * x["parking_err_m"] for x in r)["mean"],
            "reached": float(np.mean([x["reached"] for x in r])),
        }
        kr = [x["recovery_s"] for x in kid_rows if x["method"] == m]
        if kr:
            s["kidnap_recovered"] = float(np.mean(np.isfinite(kr)))
            s["kidnap_recovery_s_median"] = stats(kr)["median"]
        summary["methods"][m] = s
        p = PAPER_TABLE2.get(m)
        table.append(
            [
                LABELS.get(m, m),
                s["err_x_cm"],
                s["err_y_cm"],
                s["err_pos_cm"],
                s["err_theta_rad"],
                s["success"],
                s["parking_err_cm"],
                *(
                    [p["x"], p["y"], p["pos"], p["theta"], p["success"]]
                    if p
                    else [float("nan")] * 5
                ),
            ]
        )
    return table


def _report(
    cfg: Config, n: int, mounts: dict[str, np.ndarray | None], table: list[list[Any]]
) -> str:
    """report.md's first part: the set-up, the mount, the table beside Table 2."""
    cal = next((v for v in mounts.values() if v is not None), None)
    cal_methods = ", ".join(k for k, v in mounts.items() if v is not None)
    sxy, sth = initial_sigmas(cfg)
    return (
        f"{n} runs per method, random corridor start, rough initial pose "
        f"(sigma {sxy * 100:.0f} cm / {sth:.2f} rad), target: site "
        f"{cfg.goal_site}. Position error = final estimate vs truth (paper's measure); success = "
        f"position error < {cfg.success_threshold * 1000:.0f} mm. Parking = truth vs goal. "
        + (
            f"Lidar mount calibrated by one turn on the spot for {cal_methods}"
            f" (x, y = {1000 * cal[0]:.1f}, {1000 * cal[1]:.1f} mm); the others use the nominal "
            "mount.\n\n"
            if cal is not None
            else "Nominal lidar mount.\n\n"
        )
        + markdown_table(
            [
                "method",
                "x (cm)",
                "y (cm)",
                "position (cm)",
                "theta (rad)",
                "success",
                "parking (cm)",
                "paper x",
                "paper y",
                "paper position",
                "paper theta",
                "paper success",
            ],
            table,
            digits=3,
        )
    )


def _kidnap_report(cfg: Config, summary: dict[str, Any]) -> str:
    """report.md's kidnapped-robot part."""
    return (
        "\n## Kidnapped robot\n\n"
        + markdown_table(
            ["method", "recovered", "median recovery (s)"],
            [
                [
                    LABELS.get(m, m),
                    summary["methods"][m].get("kidnap_recovered", float("nan")),
                    summary["methods"][m].get("kidnap_recovery_s_median", float("nan")),
                ]
                for m in cfg.methods
            ],
        )
        + f"\nCarried from site {cfg.goal_site} to site {cfg.kidnap_site} unannounced, then "
        f"turning at 0.25 rad/s for up to {cfg.kidnap_duration:.0f} s; AMCL runs with "
        "recovery_alpha_slow/fast = "
        f"{cfg.kidnap_amcl.recovery_alpha_slow}/{cfg.kidnap_amcl.recovery_alpha_fast}.\n"
    )


def _plots(ctx: Context, traces: dict[str, dict[str, np.ndarray]]) -> list[str]:
    if not traces:
        return []
    fig = Figure(figsize=(8, 6))
    FigureCanvasAgg(fig)
    ax = fig.subplots(2, 1, sharex=True)
    for m, tr in traces.items():
        e = tr["estimate"] - tr["truth"]
        ax[0].plot(tr["t"], 100 * np.hypot(e[:, 0], e[:, 1]), label=LABELS.get(m, m))
        ax[1].plot(tr["t"], np.abs(wrap_angle(e[:, 2])), label=LABELS.get(m, m))
    ax[0].set_ylabel("position error (cm)")
    ax[1].set_ylabel("yaw error (rad)")
    ax[1].set_xlabel("time (s)")
    ax[0].set_yscale("log")
    ax[1].set_yscale("log")
    ax[0].legend(fontsize=8)
    ax[0].set_title("Fig. 9: error vs time, trial 0")
    fig.tight_layout()
    fig.savefig(ctx.out / "fig9_error_vs_time.png", dpi=100)
    return ["fig9_error_vs_time.png"]
