"""``mmpa calibrate lidar-mount`` in the twin: one turn on the spot, every scan matched
against the map, a circle fit (:func:`mmpa.navigation.mount_calibration.calibrate_lidar_mount`,
from the operator's rough pose); compared with the TRUE mount. Units: m in the files, mm in
the summary's errors.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from mmpa.apps.calibrate.files import write_robot_file_lidar, write_summary
from mmpa.backends.twin.error_model import ErrorModelConfig, ProfileName
from mmpa.backends.twin.operator import rough_initial_pose
from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import MMPAError
from mmpa.core.geometry import T_to_se2
from mmpa.navigation.mount_calibration import calibrate_lidar_mount

__all__ = ["run_lidar_mount"]


def run_lidar_mount(
    site: str = "0",
    seed: int = 0,
    profile: ProfileName = "realistic",
    out: str | Path | None = None,
) -> dict[str, Any]:
    """Calibrate the lidar mount in the twin: the robot instance ``seed`` turns once on the
    spot at ``site`` and fits its mount translation from its odometry and scans against the
    map (:func:`mmpa.navigation.mount_calibration.calibrate_lidar_mount`, from the operator's
    rough pose); compared with the TRUE mount. With ``out``: ``summary.json`` and a
    ``robot.yaml`` with the calibrated ``lidar.T_base_link_laser_vec`` (the nominal height,
    roll, pitch and yaw kept: a turn on the spot observes the translation only)."""

    t0 = time.perf_counter()
    errors = ErrorModelConfig.from_profile(profile, seed=seed)
    with SimWorld(errors=errors, site=site) as w:
        grid = twin_map(w)
        nominal = laser_pose2d(w)
        true = T_to_se2(w.true_robot.lidar.T_base_link_laser)
        guess = rough_initial_pose(w, np.random.default_rng([seed, 1]))
        cal = calibrate_lidar_mount(w, grid, nominal, guess, rng=np.random.default_rng([seed, 2]))
    if cal.mount is None:
        raise MMPAError(
            f"the lidar mount fit was not trusted (circle fit RMS {1e3 * cal.fit.rms:.1f} mm): "
            "turn where the map is rich in walls, or check the map"
        )
    summary: dict[str, Any] = {
        "profile": profile,
        "seed": seed,
        "site": site,
        "mount": [float(v) for v in cal.mount],
        "mount_nominal": [float(v) for v in nominal],
        "mount_true": [float(v) for v in true],
        "error_mm": float(1e3 * np.hypot(*(cal.mount[:2] - true[:2]))),
        "nominal_error_mm": float(1e3 * np.hypot(*(nominal[:2] - true[:2]))),
        "fit_rms_mm": float(1e3 * cal.fit.rms),
        "scans": len(cal.poses),
        "wall_s": time.perf_counter() - t0,
    }
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        summary["robot_file"] = str(write_robot_file_lidar(cal.mount, out / "robot.yaml"))
        write_summary(out, summary)
    return summary
