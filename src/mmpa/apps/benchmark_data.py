"""Data sets for ``mmpa benchmark localization``, one loader per format (kiss-icp's
``datasets`` are the model): each gives the map, the lidar mount and, per scan, the scan, the
wheel odometry pose a live robot had when it arrived and the reference pose.

- :class:`CarmenDataset`: a CARMEN log (``.log``, ``.log.gz``, ``.clf``;
  :mod:`mmpa.backends.bag.carmen`): odometry chained from the log's increments, the
  corrected pose as the reference, the stamps made increasing as in its bag, the map built
  from the log's scans at their corrected poses (or one given), the mount the identity (the
  ``FLASER`` pose is the scan's pose: :mod:`mmpa.apps.convert`).
- :class:`BagDataset`: a ROS 1 / ROS 2 bag (:mod:`mmpa.backends.bag.reader`): ``/scan``, the
  odometry at each scan's stamp (``/odom``, else ``/tf``), ``/truth/base_pose`` as the
  reference (required), the bag's ``/map`` (or one given), the mount as ``mmpa localize``
  finds it (:func:`~mmpa.apps.localize.lidar_mount`: ``--laser-pose``, the bag's
  ``/tf_static`` by the scans' ``frame_id``, the robot file, else refused).

:func:`open_dataset` picks the loader by the file name.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from mmpa.apps.convert import carmen_map, increasing_stamps
from mmpa.apps.localize import LocalizeConfig, grid_from_bag, lidar_mount
from mmpa.backends.bag.carmen import read_carmen
from mmpa.backends.bag.reader import BagPlayback, BagTopics
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.maps.map_server import load_map
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import LaserScan

__all__ = ["BagDataset", "CarmenDataset", "Frame", "LocalizationDataset", "open_dataset"]

CARMEN_SUFFIXES = (".log", ".log.gz", ".clf", ".clf.gz")


@dataclass(frozen=True)
class Frame:
    """One scan of a data set: ``t`` s, the scan, ``odom`` ``[x, y, theta]`` in ``odom``,
    ``truth`` the reference base pose ``[x, y, theta]`` in ``map``."""

    t: float
    scan: LaserScan
    odom: Array
    truth: Array


class LocalizationDataset(Protocol):
    """What the benchmark pipeline reads (see the module docstring)."""

    name: str
    format: str
    grid: OccupancyGrid
    map_source: str
    laser_pose: Array
    laser_pose_source: str

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Frame: ...


class CarmenDataset:
    """A CARMEN log (module docstring); ``map_yaml`` replaces the map built from the log
    (``resolution`` m cells)."""

    format = "carmen"

    def __init__(
        self, path: str | Path, map_yaml: str | Path | None = None, resolution: float = 0.05
    ) -> None:
        self.path = Path(path)
        self.name = self.path.name.split(".")[0]
        self.log = read_carmen(self.path)
        # the bag's stamps (mmpa.apps.convert): increasing, so the health monitor's odometry
        # check sees a time step (the CSAIL log stamps every scan alike)
        self.stamps, self.stamps_moved = increasing_stamps(self.log.stamps)
        self.laser_pose = np.zeros(3)
        self.laser_pose_source = "carmen (the FLASER pose is the scan's pose)"
        if map_yaml is not None:
            self.grid, self.map_source = load_map(map_yaml), str(map_yaml)
        else:
            self.grid = carmen_map(self.log, resolution, self.laser_pose)
            self.map_source = f"built from the log's scans at their poses ({resolution} m cells)"

    def __len__(self) -> int:
        return len(self.log)

    def __getitem__(self, i: int) -> Frame:
        log = self.log
        scan = replace(log.scans[i], stamp=float(self.stamps[i]))
        return Frame(float(self.stamps[i]), scan, log.odometry[i], log.poses[i])


class BagDataset:
    """A bag with ``/truth/base_pose`` (module docstring); ``laser_pose`` (``--laser-pose``)
    and ``robot_laser_pose`` (the robot file's) as :func:`lidar_mount` takes them."""

    format = "bag"

    def __init__(
        self,
        path: str | Path,
        map_yaml: str | Path | None = None,
        topics: BagTopics | None = None,
        laser_pose: tuple[float, float, float] | None = None,
        robot_laser_pose: tuple[float, float, float] | None = None,
    ) -> None:
        self.path = Path(path)
        self.name = self.path.stem
        tp = topics or BagTopics()
        self.pb = BagPlayback.open(self.path, tp)
        if not self.pb.scans:
            raise InvalidInputError(f"{path}: no scans on {tp.scan}")
        if self.pb.truth_base is None:
            raise InvalidInputError(
                f"{path}: no reference trajectory on {tp.truth_base} (geometry_msgs/PoseStamped "
                "in map); the benchmark needs one"
            )
        if map_yaml is not None:
            self.grid, self.map_source = load_map(map_yaml), str(map_yaml)
        else:
            self.grid, self.map_source = grid_from_bag(self.path, tp), f"{path} ({tp.map})"
        mount_cfg = LocalizeConfig(
            laser_pose=laser_pose, robot_laser_pose=robot_laser_pose, topics=tp
        )
        self.laser_pose, self.laser_pose_source = lidar_mount(self.pb, mount_cfg)

    def __len__(self) -> int:
        return len(self.pb.scans)

    def __getitem__(self, i: int) -> Frame:
        scan = self.pb.scans[i]
        odom = self.pb.odometry_at(scan.stamp).pose
        truth = self.pb.truth_at(scan.stamp)
        assert truth is not None  # checked in __init__
        return Frame(float(scan.stamp), scan, np.asarray(odom, float), truth)


def open_dataset(
    path: str | Path,
    map_yaml: str | Path | None = None,
    *,
    resolution: float = 0.05,
    topics: BagTopics | None = None,
    laser_pose: tuple[float, float, float] | None = None,
    robot_laser_pose: tuple[float, float, float] | None = None,
) -> LocalizationDataset:
    """The loader of ``path``: a CARMEN log by its suffix (``.log``, ``.log.gz``, ``.clf``),
    else a bag."""
    p = Path(path)
    if not p.exists():
        raise InvalidInputError(f"{p} does not exist")
    if p.name.endswith(CARMEN_SUFFIXES):
        if laser_pose is not None:
            raise InvalidInputError(
                f"{p}: a CARMEN log's scans are at its poses; --laser-pose is for bags"
            )
        return CarmenDataset(p, map_yaml, resolution)
    return BagDataset(p, map_yaml, topics, laser_pose, robot_laser_pose)
