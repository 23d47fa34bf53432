"""``mmpa teach`` and ``mmpa run`` in the twin: one task, one automation run, with the truth.

``teach_task`` plays a demonstration (``backends/twin/worlds/demonstrations.yaml``) at its site and
saves
the recorded task in the store; ``run_task`` loads it, parks the robot with a paper Table 2
offset at the automation site (default: the task's site; Site 2' reuses Site 2's tasks), runs
the automation stage and reports the estimate and its error against the simulator's truth.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from mmpa.backends.bag.record import ARM_RATE_HZ
from mmpa.core.geometry import T_to_vec6
from mmpa.harness.ipe_eval import ipe_rows, offset_row
from mmpa.harness.twin_site import MMPAExperimentConfig, TwinSite
from mmpa.tasks import TaskStore

__all__ = ["RECORD_MIN_JOINT_HZ", "run_task", "teach_task"]

Progress = Callable[[str, float], None]

#: Hz: the least rate of the arm's /joint_states (and its /tf) in a recorded run; it runs at
#: the task path's rate (the rate the path is commanded and its execution's encoders are
#: read, 50 Hz in the twin's tasks) when that is higher
RECORD_MIN_JOINT_HZ = ARM_RATE_HZ


def teach_task(
    site: str,
    demo: str,
    *,
    db: str | Path | None = None,
    cfg: MMPAExperimentConfig | None = None,
    overwrite: bool = False,
) -> dict:
    """Teach demonstration ``demo`` at ``site`` in the twin and store it (name = ``demo``)."""
    cfg = cfg or MMPAExperimentConfig()
    with TwinSite(cfg, site, demo=demo) as ts, TaskStore(db) as store:
        task = ts.taught.task
        store.save(task, overwrite=overwrite)
        return {
            "profile": cfg.errors.profile,
            "task": task.name,
            "site": task.site,
            "store": str(store.path),
            "cloud_points": len(task.cloud),
            "path_waypoints": len(task.path.t),
            "path_seconds": round(float(task.path.t[-1]), 2),
            "rate_hz": task.path.rate_hz,
        }


def run_task(
    name: str,
    *,
    site: str | None = None,
    db: str | Path | None = None,
    cfg: MMPAExperimentConfig | None = None,
    trial: int = 0,
    tmma: bool = False,
    progress: Progress | None = None,
    record: str | Path | None = None,
) -> dict:
    """Park at ``site`` (default: the task's), run IPE + adapted path; errors vs the truth.

    ``record``: also record the run (parking, IPE, the executed path) to this ROS 2 bag
    (``FILE.mcap`` or a rosbag2 folder; overwritten; :meth:`TwinSite.recording`): the
    scans and camera frames as the algorithms read them, ``/joint_states`` and the arm's
    ``/tf`` at the task's path rate (at least :data:`RECORD_MIN_JOINT_HZ`) through every
    arm motion, ``/map`` and the parking localization (``/initialpose``, ``/amcl_pose``,
    ``/particlecloud``, ``map -> odom``), ``/tf_static`` and the ground truth on
    ``/truth/...``. The recorder draws nothing and steps the same physics, so the run and
    its summary are those of the run without ``record`` (plus ``bag``: the path)."""
    cfg = cfg or MMPAExperimentConfig()
    with TaskStore(db) as store:
        task = store.load(name)
    site = site or task.site
    with TwinSite(cfg, site, task=task) as ts, ExitStack() as stack:
        if record is not None:
            stack.enter_context(ts.recording(record))
        for _ in range(trial + 1):  # the trial-th parking draw of this seed
            ts.park()
        out: dict = {"profile": cfg.errors.profile, "task": name, "site": site, "trial": trial}
        if tmma:
            out["tmma_tool_error_mm"] = round(ts.run_tmma() * 1e3, 2)
            scale = ts.tmma_time_scale
            assert scale is not None
            out["tmma_time_scale"] = round(scale, 3)  # > 1: slowed down to the joint limits
            ts.world.reset(site=site, pose2d=ts.parked_pose2d)
        res = ts.run_ipe(execute=False)
        truth = ts.parking_truth()
        row, _ = ipe_rows(res.ipe, truth)
        park = offset_row(truth)
        out["parking_offset_6d"] = _vec(truth)
        out["parking_E_t_mm"] = round(park["park_E_t"] * 1e3, 1)
        out["ipe_ok"] = res.ipe.ok
        out["ipe_iterations"] = res.ipe.n_iterations
        out["ipe_compute_s"] = round(res.ipe.seconds_compute, 3)
        if res.ipe.dT_B is not None:
            out["estimate_6d"] = _vec(res.ipe.dT_B)
            out["estimate_E_t_mm"] = round(row["E_t"] * 1e3, 3)
            out["estimate_E_R"] = round(row["E_R"], 5)
        if res.ok:
            assert res.joint_path is not None
            out["path_time_scale"] = round(res.joint_path.time_scale, 3)  # > 1: slowed down
            out["tool_error_mm"] = round(ts.execute(res) * 1e3, 3)
            out["executed"] = True
        else:
            out["executed"] = False
            out["reason"] = res.reason
        if record is not None:
            out["bag"] = str(record)
        return out


def _vec(T: np.ndarray) -> str:
    v = T_to_vec6(T)
    return (
        f"[{v[0] * 1e3:.1f}, {v[1] * 1e3:.1f}, {v[2] * 1e3:.1f}] mm, "
        f"[{np.rad2deg(v[3]):.2f}, {np.rad2deg(v[4]):.2f}, {np.rad2deg(v[5]):.2f}] deg"
    )
