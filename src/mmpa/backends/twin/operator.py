"""The twin's human operator: one-shot teaching demonstrations (paper 000 §3.1).

On a real robot an operator guides the gravity-compensated arm by hand while the robot records
its encoders. In the twin the operator is this module: it knows the TRUE world (it sees where
the dot is), turns a demonstration's desk-frame waypoints into a joint trajectory of the TRUE
arm, and plays it on the simulated arm while the encoders are recorded at ``rate_hz``. The
recording is all that mmpa's teaching keeps; this module's truth is for evaluation only.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from itertools import pairwise
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from scipy.spatial.transform import Rotation, Slerp

from mmpa.backends.twin.lidar_noise import rough_pose
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import ConfigError, UnknownNameError
from mmpa.core.geometry import Array, inv, make_T, rot_z, rpy_to_R
from mmpa.core.yamlio import load_yaml
from mmpa.robot.kinematics import fk, ik_nearest

__all__ = [
    "Demonstration",
    "Recording",
    "Waypoint",
    "demonstrate",
    "load_demonstrations",
    "rough_initial_pose",
    "sampling_joints",
    "true_tcp_in_map",
]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, coerce_numbers_to_str=True)


class Waypoint(_Model):
    xyz: tuple[float, float, float]  # desk-top frame, m
    rpy_deg: tuple[float, float, float] = (180.0, 0.0, 0.0)  # tool frame in the desk frame
    twist_deg: float = 0.0  # extra rotation about the tool z axis
    t: float = Field(ge=0)  # s from the start
    gripper: float | None = Field(None, ge=0, le=1)  # applied on arrival
    key: bool = False

    def T_desk_tool(self) -> Array:
        R = rpy_to_R(*np.deg2rad(self.rpy_deg)) @ rot_z(np.deg2rad(self.twist_deg))
        return make_T(R, self.xyz)


class View(_Model):
    """Sampling pose: the camera looks at ``target`` (desk frame) from ``distance`` m, from the
    robot's side of the desk, ``elevation_deg`` below the horizontal."""

    target: tuple[float, float, float]
    distance: float = Field(0.42, gt=0.2, lt=1.5)
    elevation_deg: float = Field(60.0, gt=0, lt=90)


class Demonstration(_Model):
    name: str = ""
    site: str
    bench: str
    description: str = ""
    view: View
    waypoints: list[Waypoint] = Field(min_length=2)
    rate_hz: float = Field(50.0, gt=0)

    @model_validator(mode="after")
    def _times(self) -> Demonstration:
        t = [w.t for w in self.waypoints]
        if t[0] != 0.0 or any(b <= a for a, b in pairwise(t)):
            raise ValueError("waypoint times must start at 0 and increase strictly")
        if sum(w.key for w in self.waypoints) > 1:
            raise ValueError("at most one waypoint can be the key pose")
        return self

    @property
    def key_index(self) -> int:
        """Index of the key waypoint (default: the first)."""
        return next((i for i, w in enumerate(self.waypoints) if w.key), 0)


def load_demonstrations(path: str | Path | None = None) -> dict[str, Demonstration]:
    """Demonstrations by name (default: the built-in ``worlds/demonstrations.yaml``)."""
    if path is None:
        path = Path(str(resources.files("mmpa.backends.twin") / "worlds" / "demonstrations.yaml"))
    data = load_yaml(path)  # no aliases, bounded size; errors name the file
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: must map demonstration names to definitions")
    out = {}
    for name, d in data.items():
        try:
            out[str(name)] = Demonstration.model_validate({**d, "name": str(name)})
        except (ValidationError, TypeError) as e:
            raise ConfigError(f"{path}: demonstration {name!r} is invalid: {e}") from None
    return out


def get_demonstration(name: str, path: str | Path | None = None) -> Demonstration:
    demos = load_demonstrations(path)
    if name not in demos:
        raise UnknownNameError("demonstration", name, sorted(demos))
    return demos[name]


def T_map_desk(world: SimWorld, bench: str) -> Array:
    b = world.scene.workbench(bench)
    return make_T(rot_z(np.deg2rad(b.yaw_deg)), (*b.center, b.size[2]))


def _true_ik(world: SimWorld, T_map_point: Array, q_ref: Array, T_flange_point: Array) -> Array:
    arm = world.true_robot.arm
    T_B_point = inv(world.truth.T_map_arm_base()) @ T_map_point
    lo, hi = arm.q_limits
    return ik_nearest(arm.dh, T_B_point, q_ref, lo, hi, T_flange_point=T_flange_point, refine=True)


def sampling_joints(world: SimWorld, demo: Demonstration) -> Array:
    """The joints at which the operator holds the camera to sample the scene, shape (6,)."""
    v = demo.view
    T_md = T_map_desk(world, demo.bench)
    target = T_md[:3, :3] @ np.asarray(v.target) + T_md[:3, 3]
    # horizontal direction from the robot toward the desk (desk +y), then tilted down
    fwd = T_md[:3, 1]
    el = np.deg2rad(v.elevation_deg)
    z = np.cos(el) * fwd + np.sin(el) * np.array([0.0, 0.0, -1.0])
    y = np.array([0.0, 0.0, -1.0]) - z * (-z[2])
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    T_map_camera = make_T(np.column_stack([x, y, z]), target - v.distance * z)
    q_ref = np.asarray(world.nominal.arm.view_bench)
    return _true_ik(world, T_map_camera, q_ref, world.true_robot.camera.T_flange_camera)


@dataclass(frozen=True)
class Recording:
    """What the teach-in recorder saw: encoder samples at ``rate_hz``.

    ``t`` (M,) s from 0; ``q`` (M, 6) rad; ``gripper`` (M,) 0 open .. 1 closed;
    ``key_index``: sample at the end of the dwell at the key waypoint (evaluation).
    """

    t: Array
    q: Array
    gripper: Array
    rate_hz: float
    key_index: int


def _min_jerk(s: Array) -> Array:
    return 10 * s**3 - 15 * s**4 + 6 * s**5


def dense_tool_poses(
    T_map_desk_: Array, demo: Demonstration, dt: float = 0.01
) -> tuple[Array, Array, Array]:
    """Minimum-jerk interpolation of the waypoints: times (K,), ``T_map_tool`` (K, 4, 4) and the
    waypoint index each sample belongs to (K,)."""
    wps = demo.waypoints
    poses = [T_map_desk_ @ w.T_desk_tool() for w in wps]
    times, Ts, seg = [0.0], [poses[0]], [0]
    for i in range(len(wps) - 1):
        t0, t1 = wps[i].t, wps[i + 1].t
        n = max(int(np.ceil((t1 - t0) / dt)), 1)
        s = _min_jerk(np.arange(1, n + 1) / n)
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix([poses[i][:3, :3], poses[i + 1][:3, :3]]))
        R = slerp(s).as_matrix()
        p = poses[i][:3, 3] + s[:, None] * (poses[i + 1][:3, 3] - poses[i][:3, 3])
        for k in range(n):
            times.append(t0 + (k + 1) * (t1 - t0) / n)
            Ts.append(make_T(R[k], p[k]))
            seg.append(i + 1)
    return np.array(times), np.array(Ts), np.array(seg)


def demonstrate(world: SimWorld, demo: Demonstration) -> Recording:
    """Play ``demo`` on the simulated arm (TRUE kinematics) and record the encoders.

    The arm first moves (unrecorded) to the first waypoint. The path is played in segments
    that end at waypoints with a gripper action; the recorder keeps its clock running through
    the gripper's motion, so recorded times have a gap there.
    """
    tcp = world.true_robot.gripper.T_flange_tcp
    times, T_map_tool, _ = dense_tool_poses(T_map_desk(world, demo.bench), demo)
    q_prev = world.arm.joint_positions()
    Q = np.empty((len(times), 6))
    for k, T in enumerate(T_map_tool):
        Q[k] = q_prev = _true_ik(world, T, q_prev, tcp)
    world.arm.move_joints(Q[0])
    wps = demo.waypoints
    stops = [i for i, w in enumerate(wps) if w.gripper is not None and i > 0]
    if not stops or stops[-1] != len(wps) - 1:
        stops.append(len(wps) - 1)
    dt = 1.0 / demo.rate_hz
    g = 0.0 if wps[0].gripper is None else float(wps[0].gripper)
    if g > 0.5:
        world.gripper.close()
    t_parts, td_parts, q_parts, g_parts = [], [], [], []
    t_clock, start = 0.0, 0
    for wi in stops:
        end = int(np.searchsorted(times, wps[wi].t - 1e-9)) + 1
        rec = world.arm.follow(times[start:end], Q[start:end], record_hz=demo.rate_hz)
        assert rec is not None
        t_rec, q_rec = rec
        t_parts.append(t_clock + t_rec)
        td_parts.append(times[start] + t_rec)
        q_parts.append(q_rec)
        g_parts.append(np.full(len(t_rec), g))
        w = wps[wi]
        gap = 0.2
        if w.gripper is not None and float(w.gripper) != g:
            g = float(w.gripper)
            (world.gripper.close if g > 0.5 else world.gripper.open)()
            gap += 0.8 if g > 0.5 else 0.6
        t_clock = t_parts[-1][-1] + max(gap, dt)
        start = end - 1
    td = np.concatenate(td_parts)
    key_t = wps[min(demo.key_index + 1, len(wps) - 1)].t  # end of the dwell at the key pose
    key_index = int(np.argmin(np.abs(td - key_t)))
    return Recording(
        np.concatenate(t_parts),
        np.concatenate(q_parts),
        np.concatenate(g_parts),
        demo.rate_hz,
        key_index,
    )


def true_tcp_in_map(world: SimWorld, q: Array) -> Array:
    """TRUE tcp positions (M, 3) in ``map`` for joint samples ``q`` (M, 6) at the current base."""
    arm = world.true_robot.arm
    T = world.truth.T_map_arm_base() @ fk(arm.dh, q, world.true_robot.gripper.T_flange_tcp)
    return T[..., :3, 3]


def rough_initial_pose(world: SimWorld, rng: np.random.Generator | None = None) -> Array:
    """The rough pose ``[x, y, theta]`` the operator gives the localizer ('2D Pose Estimate'):
    the TRUE base pose (the person sees the robot) plus ``N(0, initial_pos_sigma)`` m per axis
    and ``N(0, initial_yaw_sigma_deg)`` on the heading (the error model's ``operator``
    section, DESIGN.md "Error model v2"). ``rng``: default the world's ``operator_pose``
    stream of its episode (the same draw on every call: pass a generator for several)."""
    op = world.error_model.config.operator
    gen = rng if rng is not None else world.error_model.rng("operator_pose", world.episode)
    return rough_pose(
        world.truth.base_pose2d(),
        gen,
        op.initial_pos_sigma,
        float(np.deg2rad(op.initial_yaw_sigma_deg)),
    )
