"""Calibrate the lidar mount with the robot's own data: a turn on the spot (improvement).

:func:`calibrate_lidar_mount` localizes the standing robot with the enhanced AMCL (nominal
mount, from the operator's rough pose), turns it on the spot, matches every scan against the
occupancy map (:func:`~mmpa.localization.calibration.match_scan`, the scanner's own pose) and
fits the mount translation (:func:`~mmpa.localization.calibration.fit_turn_mount`). It reads
only what a real robot has: odometry, scans, the map and the nominal mount.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.geometry import Array
from mmpa.localization.amcl import AMCL, compose_odom
from mmpa.localization.calibration import (
    TurnMountFit,
    calibrated_mount,
    fit_turn_mount,
    match_scan,
)
from mmpa.localization.enhanced import EnhancedAMCL, EnhancedConfig
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.interfaces import Base, Lidar

__all__ = ["MountCalibration", "MountCalibrationConfig", "calibrate_lidar_mount"]


class MountCalibrationConfig(BaseModel):
    """Turn and matching settings (rad/s, Hz, rad, m)."""

    model_config = ConfigDict(extra="forbid")

    settle_scans: int = Field(15, ge=1)  # standing scans to localize before the turn
    turn_rate: float = Field(0.3, gt=0)  # rad/s
    turn: float = Field(2 * np.pi, gt=0.5)  # rad turned (one full turn: errors that follow
    # the heading average out over it)
    scan_rate: float = Field(5.0, gt=0)  # Hz
    beams: int = Field(360, ge=10)  # beams matched per scan
    sigma: float = Field(0.03, gt=0)  # m, per-beam SD of the likelihood field
    max_rms: float = Field(0.01, gt=0)  # m: a worse circle fit is not trusted (None returned)


class _World(Protocol):
    """What the calibration drives: a base, odometry through it, a lidar and a clock."""

    @property
    def base(self) -> Base: ...

    @property
    def lidar(self) -> Lidar: ...

    def step(self, duration: float) -> None: ...


@dataclass(frozen=True)
class MountCalibration:
    """``mount`` (3,) the calibrated ``[x, y, theta]`` (None if the fit was not trusted),
    ``fit`` the circle fit, ``poses`` (K, 3) the matched scanner poses."""

    mount: Array | None
    fit: TurnMountFit
    poses: Array


def calibrate_lidar_mount(
    world: _World,
    grid: OccupancyGrid,
    nominal: Array,
    initial_pose: Array,
    cfg: MountCalibrationConfig | None = None,
    rng: np.random.Generator | None = None,
) -> MountCalibration:
    """Turn the standing robot on the spot once and fit the lidar mount translation.

    ``nominal`` the nominal mount ``[x, y, theta]`` in ``base_link``; ``initial_pose`` the
    operator's rough pose. Each scan's scanner pose is matched from the previous one moved by
    the odometry increment (nominal mount), so the odometry's heading drift over the turn does
    not matter. The base is stopped at the end."""
    cfg = cfg or MountCalibrationConfig()
    nominal = np.asarray(nominal, float).reshape(3)
    dt = 1.0 / cfg.scan_rate
    loc = EnhancedAMCL(grid, nominal, EnhancedConfig(), rng or np.random.default_rng(0))
    loc.initialize(np.asarray(initial_pose, float))
    odom = world.base.odometry().pose
    for _ in range(cfg.settle_scans):
        world.step(dt)
        odom = world.base.odometry().pose
        loc.update(odom, world.lidar.scan(), force=True)
    base = loc.pose_at(odom)
    matcher = AMCL(grid, np.zeros(3))
    poses = []
    turned = 0.0
    prev_odom = odom
    while True:
        scan = world.lidar.scan()
        odom = world.base.odometry().pose
        base = compose_odom(base, prev_odom, odom)
        prev_odom = odom
        ranges, angles = matcher._beams(scan, cfg.beams)
        c, s = np.cos(base[2]), np.sin(base[2])
        guess = np.array(
            [
                base[0] + c * nominal[0] - s * nominal[1],
                base[1] + s * nominal[0] + c * nominal[1],
                base[2] + nominal[2],
            ]
        )
        S = match_scan(matcher, ranges, angles, guess, cfg.sigma)
        poses.append(S)
        # the matched scanner pose back to the base (nominal mount) for the next prediction
        c, s = np.cos(S[2] - nominal[2]), np.sin(S[2] - nominal[2])
        base = np.array(
            [
                S[0] - (c * nominal[0] - s * nominal[1]),
                S[1] - (s * nominal[0] + c * nominal[1]),
                S[2] - nominal[2],
            ]
        )
        if turned >= cfg.turn:
            break
        world.base.set_velocity(0.0, cfg.turn_rate)
        world.step(dt)
        turned += cfg.turn_rate * dt
    world.base.stop()
    world.step(dt)
    P = np.array(poses)
    fit = fit_turn_mount(P)
    mount = calibrated_mount(fit, nominal) if fit.rms <= cfg.max_rms else None
    return MountCalibration(mount, fit, P)
