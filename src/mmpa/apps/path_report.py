"""What a person sees before the arm moves on hardware: the adapted path against the taught
one (clearance, limits) and the files a dry run writes (the path as CSV and JSON, a picture).

Frames: tool poses are ``T_arm_base_tool`` (4x4) in the arm base ``B`` (taught: ``B_o`` at
teaching; adapted: ``B_k`` now, eq. 11 ``T_Bk_tool = dT_B T_Bo_tool``); positions in m,
angles in rad in the data, mm and degrees in the text.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from mmpa.core.geometry import Array, T_to_vec6
from mmpa.planning import JointPath
from mmpa.robot.limits import JointLimits, check_path, path_accelerations, path_velocities

__all__ = ["PathCheck", "check_adapted_path", "write_dry_run"]


@dataclass(frozen=True)
class PathCheck:
    """The adapted path against the taught one and the arm's limits.

    ``clearance_mm``: per waypoint, the distance between the adapted and the taught tool
    positions in the arm base (the largest and the mean); ``rotation_deg`` the largest angle
    between their orientations; ``approach_rad`` the largest joint move from the arm's
    current joints to the path's start (done first, by a limited point-to-point move);
    ``velocity_use`` / ``acceleration_use`` the path's peak joint speed and acceleration as a
    fraction of the limits (the largest over the joints); ``limits_ok`` / ``limits_reason``
    the verdict of :func:`mmpa.robot.limits.check_path` (what the arm checks again before it
    moves)."""

    clearance_mm: tuple[float, float]
    rotation_deg: float
    approach_rad: float
    velocity_use: float
    acceleration_use: float
    limits_ok: bool
    limits_reason: str
    duration_s: float
    time_scale: float

    def lines(self) -> list[str]:
        """The check as text lines."""
        verdict = "ok" if self.limits_ok else f"REFUSED: {self.limits_reason}"
        return [
            f"adapted vs taught tool path: {self.clearance_mm[0]:.1f} mm at most, "
            f"{self.clearance_mm[1]:.1f} mm mean, {self.rotation_deg:.2f} deg at most",
            f"approach to the path start: {np.rad2deg(self.approach_rad):.1f} deg (largest joint)",
            f"limits: {verdict}; peak joint speed {100 * self.velocity_use:.0f} % and "
            f"acceleration {100 * self.acceleration_use:.0f} % of the limits; "
            f"{self.duration_s:.2f} s (time scale {self.time_scale:.2f})",
        ]


def check_adapted_path(
    taught: Array, adapted: Array, path: JointPath, q_now: Array, limits: JointLimits
) -> PathCheck:
    """The :class:`PathCheck` of the adapted tool poses ``adapted`` (N, 4, 4) against the
    taught ``taught`` (N, 4, 4), the joint path ``path`` and the arm at ``q_now`` (6,)."""
    d = np.linalg.norm(adapted[:, :3, 3] - taught[:, :3, 3], axis=1)
    cos = (np.einsum("nij,nij->n", adapted[:, :3, :3], taught[:, :3, :3]) - 1.0) / 2.0
    rot = float(np.rad2deg(np.arccos(np.clip(cos, -1.0, 1.0)).max()))
    ok, reason = True, ""
    try:
        check_path(path.t, path.q, limits, "adapted joint path")
    except ValueError as e:  # InvalidInputError, JointLimitError
        ok, reason = False, str(e)
    v = np.abs(path_velocities(path.t, path.q)) / limits.qd_max if len(path.t) > 1 else [0.0]
    a = np.abs(path_accelerations(path.t, path.q)) / limits.qdd_max if len(path.t) > 2 else [0.0]
    return PathCheck(
        clearance_mm=(float(1e3 * d.max()), float(1e3 * d.mean())),
        rotation_deg=rot,
        approach_rad=float(np.max(np.abs(np.asarray(q_now, float) - path.q[0]))),
        velocity_use=float(np.max(v)),
        acceleration_use=float(np.max(a)),
        limits_ok=ok,
        limits_reason=reason,
        duration_s=path.duration,
        time_scale=float(path.time_scale),
    )


def write_dry_run(
    out: Path,
    task_name: str,
    taught: Array,
    adapted: Array,
    path: JointPath,
    dT_B: Array,
    check: PathCheck,
) -> dict[str, str]:
    """Write ``out/adapted_path.csv`` (per waypoint: t s, the six joints rad, the adapted and
    the taught tool positions m in the arm base), ``out/adapted_path.json`` (the same, the
    estimate ``dT_B`` and the check) and ``out/adapted_path.png`` (taught vs adapted tool
    path, top and side views, mm). Returns the three paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    p_new, p_old = adapted[:, :3, 3], taught[:, :3, 3]
    header = "t,q1,q2,q3,q4,q5,q6,x,y,z,taught_x,taught_y,taught_z"
    rows = np.column_stack([path.t, path.q, p_new, p_old])
    csv = out / "adapted_path.csv"
    np.savetxt(csv, rows, delimiter=",", header=header, comments="", fmt="%.9g")
    js = out / "adapted_path.json"
    doc = {
        "task": task_name,
        "dT_B": np.asarray(dT_B).tolist(),
        "dT_B_xyz_rpy": T_to_vec6(dT_B).tolist(),
        "check": check.__dict__,
        "t": path.t.tolist(),
        "q": path.q.tolist(),
        "T_arm_base_tool": np.asarray(adapted).tolist(),
        "taught_T_arm_base_tool": np.asarray(taught).tolist(),
    }
    js.write_text(json.dumps(doc, indent=1))
    png = out / "adapted_path.png"
    _picture(png, task_name, p_old, p_new, check)
    return {"csv": str(csv), "json": str(js), "png": str(png)}


def _picture(path: Path, name: str, p_old: Array, p_new: Array, check: PathCheck) -> None:
    fig = Figure(figsize=(10, 4.6), dpi=100)
    FigureCanvasAgg(fig)
    for i, (a, b, title) in enumerate(((0, 1, "top (x, y)"), (0, 2, "side (x, z)"))):
        ax = fig.add_subplot(1, 2, i + 1)
        ax.plot(1e3 * p_old[:, a], 1e3 * p_old[:, b], "-", color="0.5", label="taught")
        ax.plot(1e3 * p_new[:, a], 1e3 * p_new[:, b], "-", color="C3", label="adapted")
        ax.plot(1e3 * p_new[0, a], 1e3 * p_new[0, b], "o", color="C3", ms=4)
        ax.set_xlabel(f"{'xyz'[a]} (mm, arm base)")
        ax.set_ylabel(f"{'xyz'[b]} (mm, arm base)")
        ax.set_title(title)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    fig.suptitle(
        f"task {name}: adapted vs taught tool path "
        f"({check.clearance_mm[0]:.1f} mm at most; limits {'ok' if check.limits_ok else 'REFUSED'})"
    )
    fig.savefig(path)
