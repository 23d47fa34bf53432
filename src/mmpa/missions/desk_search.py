"""Find a desk by turning on the spot, and turn to a heading, on the localization estimate
(paper 001 §4.2.2, Fig. 15 c: the mobile manipulator at its work area).

The base turns on the spot while scans go into the localizer; the desk is found when its
centre is within ``face_tol`` rad of the ESTIMATED heading and both of its front legs, where
the map puts them, return at least ``leg_points`` scan points within ``leg_radius`` m
(:func:`desk_in_scan`): the desk is there and the estimate agrees with it. Frames: poses
``[x, y, theta]`` in ``map`` (m, rad); the lidar mount ``[x, y, theta]`` in ``base_link``."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mmpa.core.geometry import Array, se2_to_T, wrap_angle
from mmpa.localization.localizer import Localizer
from mmpa.missions.navigate import MobileRobot
from mmpa.robot.interfaces import LaserScan

__all__ = ["desk_in_scan", "search_desk", "turn_on_the_spot", "turn_to_heading"]


def desk_in_scan(
    scan: LaserScan, T_map_laser: Array, legs_map: Array, radius: float, min_points: int
) -> bool:
    """Both desk legs ``legs_map`` (2, 2) seen: at least ``min_points`` scan points (mapped
    with ``T_map_laser`` (4, 4), the laser in the map) within ``radius`` m of each."""
    r = np.asarray(scan.ranges, float)
    a = scan.angle_min + scan.angle_increment * np.arange(len(r))
    ok = np.isfinite(r) & (r > scan.range_min)
    pts = np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])])
    pts_map = pts @ T_map_laser[:2, :2].T + T_map_laser[:2, 3]
    for leg in legs_map:
        if int(np.sum(np.linalg.norm(pts_map - leg, axis=1) < radius)) < min_points:
            return False
    return True


def turn_on_the_spot(
    robot: MobileRobot,
    localizer: Localizer,
    rate: Callable[[Array, LaserScan], float | None],
    dt: float,
    timeout: float,
) -> tuple[bool, float]:
    """Turn on the spot on the localization estimate: every ``dt`` s, scan into
    ``localizer`` and command ``w = rate(estimate, scan)`` rad/s until ``rate`` returns None
    (done) or ``timeout`` s pass; then stop and settle 0.3 s. Returns ``(done, seconds)``."""
    t0 = robot.time
    done = False
    while robot.time - t0 < timeout:
        odom = robot.odometry.odometry().pose
        scan = robot.lidar.scan()
        localizer.update(odom, scan, force=False)
        w = rate(localizer.pose_at(odom), scan)
        if w is None:
            done = True
            break
        robot.base.set_velocity(0.0, w)
        robot.step(dt)
    robot.base.stop()
    robot.step(0.3)
    return done, float(robot.time - t0)


def search_desk(
    robot: MobileRobot,
    localizer: Localizer,
    legs_map: Array,
    desk_center: Array,
    laser_pose: Array,
    face_tol: float,
    leg_radius: float,
    leg_points: int,
    w: float,
    timeout: float,
) -> tuple[bool, float]:
    """Turn on the spot at ``w`` rad/s (toward the desk side first, on the estimate) until the
    desk's front legs ``legs_map`` (2, 2) are in the scan with its centre ``desk_center``
    within ``face_tol`` of the heading (module docstring); returns ``(found, seconds)``."""
    T_base_laser = se2_to_T(*laser_pose)
    center = np.asarray(desk_center, float)

    def rate(est: Array, scan: LaserScan) -> float | None:
        off = float(wrap_angle(np.arctan2(*(center - est[:2])[::-1]) - est[2]))
        T_map_laser = se2_to_T(*est) @ T_base_laser
        if abs(off) <= face_tol and desk_in_scan(
            scan, T_map_laser, legs_map, leg_radius, leg_points
        ):
            return None
        return w * (1.0 if off >= 0 else -1.0)

    return turn_on_the_spot(robot, localizer, rate, 0.1, timeout)


def turn_to_heading(
    robot: MobileRobot, localizer: Localizer, heading: float, tol: float, timeout: float
) -> tuple[bool, float]:
    """Turn on the spot until the ESTIMATED heading is within ``tol`` rad of ``heading``
    (``w = clip(1.5 e, +-0.3)`` rad/s, at least 0.02 rad/s; scans into ``localizer`` every
    0.05 s); returns ``(aligned, seconds)``."""

    def rate(est: Array, scan: LaserScan) -> float | None:
        e = float(wrap_angle(heading - est[2]))
        if abs(e) <= tol:
            return None
        w = float(np.clip(1.5 * e, -0.3, 0.3))
        return w if abs(w) >= 0.02 else 0.02 * float(np.sign(e))

    return turn_on_the_spot(robot, localizer, rate, 0.05, timeout)
