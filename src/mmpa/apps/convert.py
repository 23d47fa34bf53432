"""``mmpa convert carmen LOG --out BAG.mcap``: a CARMEN laser log as a ROS 2 bag.

The bag holds what ``mmpa localize`` and ``mmpa benchmark localization`` read from a robot's
recording (:mod:`mmpa.backends.bag.reader`), one message of each per scan ``k``, stamped at
the scan's time ``t_k``:

- ``/scan`` (``sensor_msgs/LaserScan``, frame ``laser``): the ``FLASER`` ranges with the log's
  beam geometry (:mod:`mmpa.backends.bag.carmen`: angles counter-clockwise from the robot's
  right, ``inf`` for no return; ranges as float32, as the message has them);
- ``/odom`` (``nav_msgs/Odometry``, ``odom -> base_link``) and the same transform on ``/tf``:
  the wheel odometry pose, the log's increments chained from the first corrected pose
  (:attr:`CarmenLog.odometry`), so the increment between two scans is the log's; the twist
  is the constant-twist arc between the two poses over their time step (zero for the first);
- ``/truth/base_pose`` (``geometry_msgs/PoseStamped`` in ``map``): the corrected (SLAM) pose;
- once, at the first stamp: ``/tf_static`` ``base_link -> laser`` (the mount, default the
  identity, below), ``/initialpose`` at the first corrected pose with a zero covariance (the
  localizer's default applies), and, when a map is given, ``/map``.

The mount: in these corrected logs the ``FLASER`` pose is the pose the scan was taken from.
Projecting each log's odd scans onto a map built from its even scans (2.5 cm cells), the
share of endpoints within 5 cm of an occupied cell is highest with the scan at the pose
itself (freiburg-079: 0.871; with the ``robot_frontlaser_offset`` of -0.04 m its ``PARAM``
line declares: 0.805, +0.04 m: 0.842; intel: 0.942 against 0.910 / 0.916 at -/+0.04 m). So
``base_link`` is that pose and ``base_link -> laser`` the identity unless ``laser_pose`` says
otherwise (then ``base_link = pose * inv(laser_pose)``, the scans unchanged in the map).

Stamps: a bag's readers match odometry to scans by time, so the stamps must increase. The
CSAIL log writes its times with 6 significant digits (every scan at 1.13486e9 s) and the
Intel log has 4 stamps that step back (by up to 0.86 s); such a stamp (at or before the one
before it) is moved to the previous one plus ``min_dt`` and counted (``stamps_moved``, with
a warning); stamps that increase are kept. ``min_dt`` is 1 s: the health monitor judges an
odometry increment against the time it took (2 m/s, 4 rad/s at most,
:mod:`mmpa.localization.health`), and these logs' scans are up to ~1 m / 20 degrees apart
(with 1 ms, every CSAIL increment was refused as a jump). The benchmark's CARMEN loader uses
the same stamps (:func:`increasing_stamps`), so a log and its bag are judged alike.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from mmpa.backends.bag import messages as rm
from mmpa.backends.bag.carmen import CarmenLog, read_carmen
from mmpa.backends.bag.writer import BagWriter
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, se2_compose, se2_inv, wrap_angle
from mmpa.maps.from_scans import occupancy_from_scans
from mmpa.maps.map_server import save_map
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import Odometry

__all__ = ["carmen_map", "carmen_to_bag", "convert_carmen", "increasing_stamps"]

_log = logging.getLogger(__name__)


def increasing_stamps(stamps: Array, min_dt: float = 1.0) -> tuple[Array, int]:
    """``stamps`` (s) made strictly increasing: a stamp at or before the one before it is
    moved to that one plus ``min_dt``; stamps that increase are kept. Returns the stamps and
    how many moved."""
    out = np.asarray(stamps, float).copy()
    moved = 0
    for k in range(1, len(out)):
        if out[k] <= out[k - 1]:
            out[k] = out[k - 1] + min_dt
            moved += 1
    return out, moved


def _twist(prev: Array, pose: Array, dt: float) -> Array:
    """Body twist ``[v, w]`` of the constant-twist arc from ``prev`` to ``pose`` in ``dt``
    s (the arc's length ``|d| (dth / 2) / sin(dth / 2)``, signed by the forward motion)."""
    if dt <= 0:
        return np.zeros(2)
    d = se2_compose(se2_inv(prev), pose)
    dth = float(wrap_angle(d[2]))
    half = 0.5 * dth
    arc = half / np.sin(half) if abs(half) > 1e-9 else 1.0
    return np.array([float(np.copysign(np.hypot(d[0], d[1]) * arc, d[0])) / dt, dth / dt])


def carmen_map(
    log: CarmenLog, resolution: float = 0.05, laser_pose: Array | None = None
) -> OccupancyGrid:
    """The occupancy map of ``log``: every scan at its corrected pose
    (:func:`~mmpa.maps.from_scans.occupancy_from_scans`, ``resolution`` m cells)."""
    return occupancy_from_scans(log.poses, log.scans, resolution, laser_pose=laser_pose)


def carmen_to_bag(
    log: CarmenLog,
    out: str | Path,
    grid: OccupancyGrid | None = None,
    laser_pose: Array | None = None,
    overwrite: bool = False,
    min_dt: float = 1.0,
) -> dict:
    """Write ``log`` to the bag ``out`` (module docstring); ``grid`` goes on ``/map``,
    ``laser_pose`` ``[x, y, yaw]`` (base_link) on ``/tf_static`` (None: the identity).
    Returns the message counts per topic and ``stamps_moved``."""
    F = rm.FRAMES
    mount = np.zeros(3) if laser_pose is None else np.asarray(laser_pose, float).reshape(3)
    if not np.all(np.isfinite(mount)):
        raise InvalidInputError(f"the laser pose must be finite, got {mount.tolist()}")
    back = se2_inv(mount)  # base_link = the scan's pose * inv(mount)
    base = np.array([se2_compose(p, back) for p in log.poses])
    odo = np.array([se2_compose(p, back) for p in log.odometry])
    t, moved = increasing_stamps(log.stamps, min_dt)
    if moved:
        _log.warning("%d scan stamps did not increase; moved by >= %g s", moved, min_dt)
    with BagWriter(out, overwrite=overwrite) as bag:
        tf = rm.transform_stamped(t[0], F["base"], F["laser"], mount)
        bag.write("/tf_static", rm.tf_message([tf]), t[0])
        bag.write("/initialpose", rm.pose_cov_stamped(t[0], F["map"], base[0], None))
        if grid is not None:
            bag.write("/map", rm.occupancy_grid(grid, t[0]))
        for k, scan in enumerate(log.scans):
            tw = _twist(odo[k - 1], odo[k], t[k] - t[k - 1]) if k else np.zeros(2)
            o = Odometry(pose=odo[k], twist=tw, stamp=float(t[k]))
            bag.write("/odom", rm.odometry(o))
            odom_tf = rm.transform_stamped(t[k], F["odom"], F["base"], odo[k])
            bag.write("/tf", rm.tf_message([odom_tf]), t[k])
            bag.write("/scan", rm.laser_scan(replace(scan, stamp=float(t[k])), F["laser"]))
            bag.write("/truth/base_pose", rm.pose_stamped(t[k], F["map"], base[k]))
        counts = dict(bag.counts)
    return {"messages": counts, "stamps_moved": moved}


def convert_carmen(
    log_path: str | Path,
    out: str | Path,
    map_yaml: str | Path | None = None,
    resolution: float = 0.05,
    overwrite: bool = False,
) -> dict:
    """Read the CARMEN log ``log_path`` and write it as the bag ``out``; with ``map_yaml``,
    also the map built from the log (``resolution`` m cells) as a map_server YAML + PGM
    there and on the bag's ``/map``. Returns a summary (scans, messages, the map's size)."""
    log = read_carmen(log_path)
    grid = carmen_map(log, resolution) if map_yaml is not None else None
    if grid is not None and map_yaml is not None:
        Path(map_yaml).parent.mkdir(parents=True, exist_ok=True)
        save_map(grid, map_yaml)
    res = carmen_to_bag(log, out, grid, overwrite=overwrite)
    summary: dict = {
        "log": str(log_path),
        "bag": str(out),
        "scans": len(log),
        "beams": len(log.scans[0].ranges),
        "duration_s": round(float(log.stamps[-1] - log.stamps[0]), 3),
        "path_m": round(float(np.sum(np.hypot(*np.diff(log.poses[:, :2], axis=0).T))), 2),
        **res,
    }
    if grid is not None:
        summary["map"] = str(map_yaml)
        summary["map_cells"] = [grid.width, grid.height]
    return summary
