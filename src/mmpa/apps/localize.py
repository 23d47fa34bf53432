"""Offline localization over a bag: ``mmpa localize --bag BAG --map MAP.yaml``.

:func:`localize_bag` feeds a localizer (:func:`~mmpa.localization.settings.build_localizer`)
each recorded scan with the odometry a live robot had when the scan arrived
(:class:`~mmpa.backends.bag.reader.BagOdometry`), from the recorded ``/initialpose`` (or one
given; or, with ``global_localization``, from particles over the whole map), exactly as the
twin's loops do; with the same method, seed and ``force`` as a recorded twin run it
reproduces that run's estimates. Its settings are a :class:`LocalizeConfig`: the
localizer's (:class:`~mmpa.localization.settings.LocalizationConfig`) and the run's, from
the robot file, ``--config``, the options and ``--set``
(:mod:`mmpa.apps.localization_settings`). :func:`run_localize` writes the run folder:
``estimate.csv``, ``estimate.mcap`` (``/amcl_pose``, ``/tf`` map -> odom), a trajectory
plot ``trajectory.png``, ``summary.json`` (with the error against ``/truth/base_pose`` when
the bag has it, and the lidar mount used with its source) and ``config.yaml`` (the final
settings). Each estimate's health
(:mod:`mmpa.localization.health`: ``ok``, ``reason``, explained and crossed shares, spread)
goes into ``estimate.csv`` (columns ``ok`` 1/0, ``explained``, ``crossed``, ``spread_xy``),
``not_ok.csv`` (time and reason of each estimate that was not ok), ``summary.json``
(``health``: the ``ok=False`` count, first reasons, medians and minima) and
``estimate.mcap`` (``/diagnostics``, ``diagnostic_msgs/DiagnosticArray``: level ERROR with
the reason when not ok). A localizer that refuses matches of its own (Hector: ``refusals``,
``last_refusal``) has them in ``estimate.csv`` (column ``refused`` 1/0) and ``summary.json``
(``refusals``: count and first distinct reasons; null for the others).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from pydantic import Field

from mmpa.backends.bag import messages as rm
from mmpa.backends.bag.reader import BagLidar, BagOdometry, BagPlayback, BagTopics, read_messages
from mmpa.backends.bag.writer import BagWriter
from mmpa.core.config import save_config
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, T_to_se2, inv, se2_to_T, wrap_angle
from mmpa.localization.health import Health
from mmpa.localization.settings import (
    LocalizationConfig,
    build_localizer,
    initial_covariance,
    start_localizer,
)
from mmpa.maps.map_server import load_map, replace_reflectors
from mmpa.maps.occupancy import OccupancyGrid

if TYPE_CHECKING:  # pragma: no cover
    from mmpa.maps.occupancy import OccupancyGrid

__all__ = [
    "LocalizeConfig",
    "LocalizeResult",
    "grid_from_bag",
    "lidar_mount",
    "localize_bag",
    "run_localize",
]


class LocalizeConfig(LocalizationConfig):
    """Settings of an offline localization run: the localizer's
    (:class:`~mmpa.localization.settings.LocalizationConfig`: method, amcl, enhanced, hector,
    initial_cov) and the run's."""

    seed: int = Field(0, ge=0)  # the localizer's random stream (the twin's demo: errors.seed)
    force: bool = False  # force every filter update (as localize_standing does)
    initial_pose: tuple[float, float, float] | None = None  # None: the bag's /initialpose
    # [x, y, yaw] of the lidar in base_link; None: the bag's /tf_static (base_frame -> the
    # scan's frame_id), else robot_laser_pose, else refused (lidar_mount)
    laser_pose: tuple[float, float, float] | None = None
    robot_laser_pose: tuple[float, float, float] | None = None  # the robot file's mount
    max_scans: int | None = Field(None, ge=1)
    topics: BagTopics = BagTopics()
    # start with particles uniform over the map's free space (amcl, enhanced): no pose used
    global_localization: bool = False


@dataclass
class LocalizeResult:
    """Estimates per scan: ``t`` (N,) s, ``estimate`` (N, 3) ``[x, y, theta]`` in ``map``,
    ``cov`` (N, 3, 3), ``odom`` (N, 3) the odometry used, ``truth`` (N, 3) or None."""

    t: Array
    estimate: Array
    cov: Array
    odom: Array
    truth: Array | None
    method: str
    seconds: float
    laser_pose: Array | None = None  # [x, y, yaw] of the lidar in base_link, as used
    laser_pose_source: str = ""  # "user" | "tf_static" | "robot_file" (lidar_mount)
    ok: list[bool] | None = None  # per scan: the estimate's ok, reason and Health
    reason: list[str] | None = None
    health: list[Health] | None = None
    refused: list[bool] | None = None  # per scan: the localizer refused its match (Hector)
    refusal_reason: list[str] | None = None

    def refusal_summary(self) -> dict | None:
        """The localizer's own refusals: count, updates, first distinct reasons; None for a
        localizer that has none (no ``refusals`` counter)."""
        if self.refused is None or self.refusal_reason is None:
            return None
        reasons = [r for r, x in zip(self.refusal_reason, self.refused, strict=True) if x]
        return {
            "count": int(sum(self.refused)),
            "updates": len(self.refused),
            "reasons": list(dict.fromkeys(reasons))[:5],
        }

    def health_summary(self) -> dict:
        """Counts of ``ok=False`` estimates, their first distinct reasons, and the median /
        minimum of the health figures (NaN-free)."""
        if self.ok is None or self.health is None or self.reason is None:
            return {}
        out: dict = {"not_ok": int(sum(not o for o in self.ok)), "updates": len(self.ok)}
        out["reasons"] = list(dict.fromkeys(r for r in self.reason if r))[:5]
        for f in ("explained", "crossed", "spread_xy"):
            v = np.array([getattr(h, f) for h in self.health], float)
            v = v[np.isfinite(v)]
            if v.size:
                out[f"{f}_median"] = round(float(np.median(v)), 4)
                out[f"{f}_min"] = round(float(v.min()), 4)
                out[f"{f}_max"] = round(float(v.max()), 4)
        return out

    def errors(self) -> dict[str, float] | None:
        """Position error statistics (mm) and heading error (deg) against the truth."""
        if self.truth is None or len(self.t) == 0:
            return None
        e = np.hypot(*(self.estimate[:, :2] - self.truth[:, :2]).T) * 1e3
        yaw = np.abs(np.rad2deg(wrap_angle(self.estimate[:, 2] - self.truth[:, 2])))
        return {
            "error_mean_mm": round(float(np.mean(e)), 3),
            "error_max_mm": round(float(np.max(e)), 3),
            "error_final_mm": round(float(e[-1]), 3),
            "yaw_error_mean_deg": round(float(np.mean(yaw)), 4),
            "yaw_error_max_deg": round(float(np.max(yaw)), 4),
        }


def grid_from_bag(path: str | Path, topics: BagTopics | None = None) -> OccupancyGrid:
    """The map recorded in a bag: ``/map`` with the landmarks of ``/reflectors`` (cylinder
    markers: centre, radius = half the marker's diameter)."""

    tp = topics or BagTopics()
    raw = read_messages(path, [tp.map, tp.reflectors])
    if not raw[tp.map]:
        raise InvalidInputError(f"{path}: no map on {tp.map}; give one with --map")
    m = raw[tp.map][-1]
    info = m.info
    data = np.asarray(m.data, dtype=np.int8).reshape(int(info.height), int(info.width))
    refl = np.zeros((0, 2))
    radius = 0.0
    if raw[tp.reflectors]:
        mk = raw[tp.reflectors][-1].markers
        refl = np.array([[k.pose.position.x, k.pose.position.y] for k in mk]).reshape(-1, 2)
        radius = float(mk[0].scale.x) / 2 if len(mk) else 0.0
    o = info.origin.position
    # resolution is float32 in the message: take its shortest decimal (0.05, not 0.0500000007)
    res = float(str(np.float32(info.resolution)))
    return OccupancyGrid(data, res, (float(o.x), float(o.y), 0.0), refl, radius)


def lidar_mount(pb: BagPlayback, cfg: LocalizeConfig) -> tuple[Array, str]:
    """The lidar mount ``[x, y, yaw]`` in the base frame and where it came from: ``"user"``
    (``cfg.laser_pose``, ``--laser-pose``), ``"tf_static"`` (the bag's static transforms from
    ``topics.base_frame`` to the scans' own ``frame_id``, chained as tf2 does) or
    ``"robot_file"`` (``cfg.robot_laser_pose``, ``mmpa --robot FILE``). Never the twin's
    mount: without any of the three, InvalidInputError names the options."""
    if cfg.laser_pose is not None:
        return np.asarray(cfg.laser_pose, float), "user"
    base = pb.topics.base_frame
    frames = sorted({s.frame_id.lstrip("/") for s in pb.scans})
    if len(frames) > 1:
        raise InvalidInputError(
            f"{pb.path}: the scans on {pb.topics.scan} come from several frames {frames}; "
            "localize one lidar at a time (--scan-topic) and give its mount (--laser-pose)"
        )
    laser = frames[0] if frames else ""
    T = pb.static_transform(base, laser) if laser else None
    if T is not None:
        mount = T_to_se2(T)
        rob = cfg.robot_laser_pose
        if rob is not None and np.abs(np.subtract(mount, rob)).max() > 1e-3:
            logging.getLogger(__name__).warning(
                "%s: the bag's lidar mount %s (%s -> %s) differs from the robot file's %s; "
                "using the bag's (--laser-pose to choose)",
                pb.path,
                np.round(mount, 4).tolist(),
                base,
                laser,
                list(rob),
            )
        return mount, "tf_static"
    if cfg.robot_laser_pose is not None:
        return np.asarray(cfg.robot_laser_pose, float), "robot_file"
    known = ", ".join(pb.static_frames()) or "none"
    raise InvalidInputError(
        f"{pb.path}: no lidar mount: {pb.topics.tf_static} has no transform from {base!r} to "
        f"the scans' frame {laser!r} (static frames: {known}); give it with --laser-pose "
        "'x,y,yaw' or a robot file (mmpa --robot FILE, lidar.T_base_link_laser_vec)"
    )


_laser_pose = lidar_mount  # the former private name, kept for callers


def localize_bag(
    playback: BagPlayback, grid: OccupancyGrid, cfg: LocalizeConfig | None = None
) -> LocalizeResult:
    """Run ``cfg.method`` over the bag's scans (see the module docstring)."""

    cfg = cfg or LocalizeConfig()
    pb = playback
    if not pb.scans:
        raise InvalidInputError(f"{pb.path}: no scans on {pb.topics.scan}")
    mount, mount_source = lidar_mount(pb, cfg)
    loc = build_localizer(cfg, grid, mount, np.random.default_rng(cfg.seed))
    if cfg.global_localization:
        start_localizer(loc, cfg.method, None, global_localization=True)
    elif cfg.initial_pose is not None:
        start_localizer(loc, cfg.method, cfg.initial_pose, initial_covariance(cfg))
    elif pb.initial_pose is not None:  # a zero covariance: the localizer's default
        _, pose, cov = pb.initial_pose
        start_localizer(loc, cfg.method, pose, initial_covariance(cfg, cov))
    else:
        raise InvalidInputError(
            f"{pb.path}: no initial pose on {pb.topics.initial_pose}; give one "
            "(--initial-pose) or start with --global"
        )
    lidar, odometry = BagLidar(pb), BagOdometry(pb)
    n = len(lidar) if cfg.max_scans is None else min(len(lidar), cfg.max_scans)
    ts, est, covs, odoms, truth = [], [], [], [], []
    oks, reasons, healths = [], [], []
    counts = hasattr(loc, "refusals")  # Hector counts the matches it refused
    refused: list[bool] = []
    refusal_reason: list[str] = []
    t0 = time.perf_counter()
    for _ in range(n):
        scan = lidar.scan()
        odom = odometry.odometry().pose
        before = int(getattr(loc, "refusals", 0))
        res = loc.update(odom, scan, force=cfg.force)
        if counts:
            refused.append(int(loc.refusals) > before)
            refusal_reason.append(str(loc.last_refusal) if refused[-1] else "")
        ts.append(scan.stamp)
        est.append(loc.pose_at(odom))
        covs.append(np.asarray(res.cov, float))
        odoms.append(odom)
        truth.append(pb.truth_at(scan.stamp))
        oks.append(bool(res.ok))
        reasons.append(res.reason)
        healths.append(res.health)
    seconds = time.perf_counter() - t0
    has_truth = pb.truth_base is not None
    return LocalizeResult(
        t=np.array(ts),
        estimate=np.array(est),
        cov=np.array(covs),
        odom=np.array(odoms),
        truth=np.array(truth) if has_truth else None,
        method=cfg.method,
        seconds=seconds,
        laser_pose=mount,
        laser_pose_source=mount_source,
        ok=oks,
        reason=reasons,
        health=healths,
        refused=refused if counts else None,
        refusal_reason=refusal_reason if counts else None,
    )


def _write_csv(path: Path, res: LocalizeResult) -> None:
    cols = ["t", "x", "y", "theta", "odom_x", "odom_y", "odom_theta"]
    rows = [res.t[:, None], res.estimate, res.odom]
    if res.truth is not None:
        cols += ["truth_x", "truth_y", "truth_theta", "error_mm"]
        err = np.hypot(*(res.estimate[:, :2] - res.truth[:, :2]).T) * 1e3
        rows += [res.truth, err[:, None]]
    judged = res.ok is not None and res.health is not None and res.reason is not None
    if judged:
        cols += ["ok", "explained", "crossed", "spread_xy"]
        h = [
            [o, x.explained, x.crossed, x.spread_xy]
            for o, x in zip(res.ok, res.health, strict=True)
        ]
        rows.append(np.array(h, float).reshape(-1, 4))
    if res.refused is not None:
        cols.append("refused")
        rows.append(np.array(res.refused, float).reshape(-1, 1))
    table = np.hstack(rows)
    np.savetxt(path, table, delimiter=",", header=",".join(cols), comments="", fmt="%.9g")
    if not judged:
        return
    # the reasons of the estimates that were not ok, one line each (text: its own file)
    with open(path.with_name("not_ok.csv"), "w", encoding="utf-8") as f:
        f.write("t,reason\n")
        for t, ok, why in zip(res.t, res.ok, res.reason, strict=True):
            if not ok:
                f.write(f'{t:.9g},"{why.replace(chr(34), chr(39))}"\n')


def _write_estimate_bag(path: Path, res: LocalizeResult) -> None:
    F = rm.FRAMES
    with BagWriter(path, overwrite=True) as bag:
        for t, p, c, o in zip(res.t, res.estimate, res.cov, res.odom, strict=True):
            bag.write("/amcl_pose", rm.pose_cov_stamped(t, F["map"], p, c))
            T_map_odom = se2_to_T(*p) @ inv(se2_to_T(*o))
            tf = rm.transform_stamped(t, F["map"], F["odom"], T_map_odom)
            bag.write("/tf", rm.tf_message([tf]), t)
        if res.ok is None or res.health is None or res.reason is None:
            return
        for t, ok, h, why in zip(res.t, res.ok, res.health, res.reason, strict=True):
            vals = {
                "explained": h.explained,
                "crossed": h.crossed,
                "spread_xy": h.spread_xy,
                "odom_ok": h.odom_ok,
                "scan_ok": h.scan_ok,
            }
            msg = rm.diagnostics(t, f"localization/{res.method}", ok, why or "ok", vals)
            bag.write("/diagnostics", msg, t)


def _plot(path: Path, res: LocalizeResult, grid: OccupancyGrid) -> None:
    fig = Figure(figsize=(7, 6))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    x0, y0 = grid.origin[0], grid.origin[1]
    ext = (x0, x0 + grid.width * grid.resolution, y0, y0 + grid.height * grid.resolution)
    ax.imshow(grid.occupied, origin="lower", extent=ext, cmap="Greys", alpha=0.6)
    if len(grid.reflectors):
        ax.plot(*grid.reflectors.T, "o", color="orange", ms=5, label="reflectors (map)")
    if res.truth is not None:
        ax.plot(*res.truth[:, :2].T, "-", color="green", lw=4, alpha=0.5, label="truth")
    ax.plot(res.estimate[:, 0], res.estimate[:, 1], ".-", color="C0", ms=2, lw=1, label=res.method)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"offline localization ({res.method}, {len(res.t)} scans)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def run_localize(
    bag: str | Path,
    out: str | Path,
    map_yaml: str | Path | None = None,
    cfg: LocalizeConfig | None = None,
    reflectors: str | Path | None = None,
) -> dict:
    """Localize over ``bag`` on the map ``map_yaml`` (None: the bag's ``/map`` and
    ``/reflectors``) and write the run folder ``out``; returns the summary. ``reflectors``:
    a reflector map file (:mod:`mmpa.maps.reflector_map`) replacing the map's own
    reflectors (one radius for all)."""
    cfg = cfg or LocalizeConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if map_yaml is not None:
        grid = load_map(map_yaml)
    else:
        grid = grid_from_bag(bag, cfg.topics)
    if reflectors is not None:
        grid = replace_reflectors(grid, reflectors)
    pb = BagPlayback.open(bag, cfg.topics)
    res = localize_bag(pb, grid, cfg)
    _write_csv(out / "estimate.csv", res)
    _write_estimate_bag(out / "estimate.mcap", res)
    _plot(out / "trajectory.png", res, grid)
    summary: dict = {
        "bag": str(bag),
        "map": str(map_yaml) if map_yaml is not None else f"{bag} ({cfg.topics.map})",
        "reflectors": str(reflectors) if reflectors is not None else "the map's",
        "method": cfg.method,
        "seed": cfg.seed,
        "start": "global" if cfg.global_localization else "initial pose",
        "scans": len(res.t),
        "odometry_messages": len(pb.odometry),
        "odometry_source": pb.odometry_source,
        "laser_pose": None
        if res.laser_pose is None
        else [round(float(v), 6) for v in res.laser_pose],
        "laser_pose_source": res.laser_pose_source,
        "duration_s": round(float(res.t[-1] - res.t[0]), 3),
        "compute_s": round(res.seconds, 3),
        "final_estimate": [round(float(v), 6) for v in res.estimate[-1]],
        "truth": res.truth is not None,
        "health": res.health_summary(),
        "refusals": res.refusal_summary(),
    }
    errs = res.errors()
    if errs is not None:
        summary.update(errs)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    save_config(cfg, out / "config.yaml")
    return summary
