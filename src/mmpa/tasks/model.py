"""What one-shot teaching records (paper 000 §3.1): the task ``tk_i`` and its tool path.

A task holds the park pose ``L_i(vehicle)`` in ``map``, the sampling joint configuration, the
nominal camera pose ``T_B_C`` at sampling, the colored cloud ``X_i(O)`` in the camera frame
and the end-effector path ``Path_i(O)`` recorded at ``f_i(O)`` Hz in the arm base frame.
Every field is validated at construction (:class:`~mmpa.core.errors.InvalidInputError` naming
the field); arrays are copied to float64 and made read-only, so a task cannot change after
its checksums were computed.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from datetime import UTC, datetime

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, as_transform
from mmpa.robot.interfaces import PointCloud

__all__ = ["FORMAT_VERSION", "NAME_PATTERN", "Task", "TaskInfo", "ToolPath"]

#: Version of the task record (fields and their meaning). Bump on any change; readers refuse
#: newer versions and migrate older ones. History: 1 the first; 2 ``header_sha256`` also
#: covers the path duration (``has_colors`` was covered from 1, but the store now also checks
#: the column against the cloud). A version-1 record is verified by the version-1 rules and
#: read as a version-2 task (no field changed meaning).
FORMAT_VERSION = 2
#: Allowed task names: they become file and directory names and CLI arguments.
NAME_PATTERN = re.compile(r"[A-Za-z0-9_.-]+")
_NAME_MAX = 128
_ROT_TOL = 1e-6  # |R^T R - I| and |det R - 1| bound for a valid rotation

MetaValue = float | int | str


def _frozen(a: np.ndarray) -> Array:
    a = np.array(a, dtype=np.float64, copy=True)
    a.setflags(write=False)
    return a


def _finite_array(value: object, shape: tuple[int | None, ...], name: str) -> Array:
    """``value`` as a read-only float64 copy of ``shape`` (None: any length), finite."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InvalidInputError(f"{name} must be a numeric array: {e}") from None
    if a.ndim != len(shape) or any(
        s is not None and s != n for s, n in zip(shape, a.shape, strict=True)
    ):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape)
        want += ",)" if len(shape) == 1 else ")"
        raise InvalidInputError(f"{name} must have shape {want}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise InvalidInputError(f"{name} contains NaN or inf (first at index {tuple(bad)})")
    return _frozen(a)


def _check_rigid(T: Array, name: str) -> None:
    """Homogeneous rigid transforms ``(..., 4, 4)``: last row [0 0 0 1], R orthonormal, det 1."""
    Ts = T.reshape(-1, 4, 4)
    for i, Ti in enumerate(Ts):
        label = name if T.ndim == 2 else f"{name}[{i}]"
        as_transform(Ti, label)
        if not np.array_equal(Ti[3], [0.0, 0.0, 0.0, 1.0]):
            raise InvalidInputError(f"{label} last row must be [0, 0, 0, 1], got {Ti[3]}")
    R = Ts[:, :3, :3]
    ortho = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    det = np.abs(np.linalg.det(R) - 1.0)
    bad = np.flatnonzero((ortho > _ROT_TOL) | (det > _ROT_TOL))
    if bad.size:
        i = int(bad[0])
        label = name if T.ndim == 2 else f"{name}[{i}]"
        raise InvalidInputError(
            f"{label} rotation is not a proper rotation (|R^T R - I| = {ortho[i]:.2e}, "
            f"|det R - 1| = {det[i]:.2e}, tolerance {_ROT_TOL:g})"
        )


@dataclass(frozen=True, eq=False)
class ToolPath:
    """``Path_i(O)``: tool (TCP) poses in ``arm_base`` recorded at ``rate_hz`` (paper 000 §3.1).

    ``t`` (N,) s, strictly increasing from exactly 0; ``q`` (N, 6) rad, the joint encoders;
    ``T_arm_base_tool`` (N, 4, 4) the tool poses through the NOMINAL kinematics; ``rate_hz``
    the recording frequency ``f_i(O)``; ``gripper`` (N,) the commanded gripper state
    (0 open .. 1 closed) or None when the task has no gripper action.
    """

    t: Array
    q: Array
    T_arm_base_tool: Array
    rate_hz: float
    gripper: Array | None = None

    def __post_init__(self) -> None:
        t = _finite_array(self.t, (None,), "path.t")
        n = t.shape[0]
        if n < 1:
            raise InvalidInputError("path.t is empty: a tool path needs at least one waypoint")
        if t[0] != 0.0:
            raise InvalidInputError(f"path.t must start at 0 s, starts at {t[0]!r}")
        steps = np.diff(t)
        if np.any(steps <= 0.0):
            i = int(np.flatnonzero(steps <= 0.0)[0])
            raise InvalidInputError(
                f"path.t must be strictly increasing: t[{i}] = {t[i]!r}, t[{i + 1}] = {t[i + 1]!r}"
            )
        q = _finite_array(self.q, (n, 6), "path.q")
        T = _finite_array(self.T_arm_base_tool, (n, 4, 4), "path.T_arm_base_tool")
        _check_rigid(T, "path.T_arm_base_tool")
        try:
            rate = float(self.rate_hz)
        except (TypeError, ValueError):
            raise InvalidInputError(
                f"path.rate_hz must be a number, got {self.rate_hz!r}"
            ) from None
        if not (math.isfinite(rate) and rate > 0.0):
            raise InvalidInputError(f"path.rate_hz must be finite and > 0 Hz, got {rate!r}")
        g = None
        if self.gripper is not None:
            g = _finite_array(self.gripper, (n,), "path.gripper")
            if np.any((g < 0.0) | (g > 1.0)):
                raise InvalidInputError("path.gripper must lie in [0, 1] (0 open .. 1 closed)")
        for k, v in (("t", t), ("q", q), ("T_arm_base_tool", T), ("rate_hz", rate), ("gripper", g)):
            object.__setattr__(self, k, v)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def duration(self) -> float:
        """Time of the last waypoint, s."""
        return float(self.t[-1])


def _validate_cloud(cloud: object) -> PointCloud:
    if not isinstance(cloud, PointCloud):
        raise InvalidInputError(f"cloud must be a PointCloud, got {type(cloud).__name__}")
    p = _finite_array(cloud.points, (None, 3), "cloud.points")
    if p.shape[0] == 0:
        raise InvalidInputError("cloud.points is empty: a task needs the cloud X_i(O)")
    c = None
    if cloud.colors is not None:
        c = _finite_array(cloud.colors, (p.shape[0], 3), "cloud.colors")
        if np.any((c < 0.0) | (c > 1.0)):
            raise InvalidInputError("cloud.colors must lie in [0, 1]")
    if not isinstance(cloud.frame, str) or not cloud.frame:
        raise InvalidInputError(f"cloud.frame must be a non-empty string, got {cloud.frame!r}")
    return PointCloud(p, c, cloud.frame)


def _validate_meta(meta: object) -> dict[str, MetaValue]:
    if not isinstance(meta, dict):
        raise InvalidInputError(f"meta must be a dict of scalars, got {type(meta).__name__}")
    out: dict[str, MetaValue] = {}
    for k, v in meta.items():
        if not isinstance(k, str) or not k:
            raise InvalidInputError(f"meta keys must be non-empty strings, got {k!r}")
        if isinstance(v, np.bool_):
            v = bool(v)
        elif isinstance(v, np.integer):
            v = int(v)
        elif isinstance(v, np.floating):
            v = float(v)
        if isinstance(v, float) and not math.isfinite(v):
            raise InvalidInputError(f"meta[{k!r}] must be finite, got {v!r}")
        if not isinstance(v, int | float | str):
            raise InvalidInputError(
                f"meta[{k!r}] must be a float, int or str, got {type(v).__name__}"
            )
        out[k] = v
    return out


def _check_str(value: object, name: str, *, empty_ok: bool = False) -> str:
    if not isinstance(value, str) or (not empty_ok and not value):
        raise InvalidInputError(f"{name} must be a {'' if empty_ok else 'non-empty '}string")
    return value


@dataclass(frozen=True, eq=False)
class Task:
    """One taught task ``tk_i`` (paper 000 §3.1).

    ``name`` the unique key (``[A-Za-z0-9_.-]+``); ``site`` where it was taught;
    ``T_map_base_park`` 4x4 the park pose ``L_i(vehicle)`` of ``base_link`` in ``map`` from the
    localization estimate; ``q_sample`` (6,) rad the sampling joint configuration;
    ``T_arm_base_camera`` 4x4 the NOMINAL camera pose ``T_B_C`` at sampling; ``cloud`` the
    colored cloud ``X_i(O)`` in the camera frame (colors None: colorless); ``path`` the tool
    path ``Path_i(O)``; ``meta`` free-form scalars (e.g. a target point for evaluation).
    ``created`` is stored in UTC (a naive datetime is read as local time).
    """

    name: str
    site: str
    T_map_base_park: Array
    q_sample: Array
    T_arm_base_camera: Array
    cloud: PointCloud
    path: ToolPath
    robot_id: str = "twin"
    created: datetime = field(default_factory=lambda: datetime.now(UTC))
    description: str = ""
    meta: dict[str, MetaValue] = field(default_factory=dict)
    format_version: int = FORMAT_VERSION

    def __post_init__(self) -> None:
        name = _check_str(self.name, "name")
        if not NAME_PATTERN.fullmatch(name) or len(name) > _NAME_MAX or name in (".", ".."):
            raise InvalidInputError(
                f"name {name!r} is not a valid task name: use 1-{_NAME_MAX} characters of "
                "A-Z a-z 0-9 _ . - (not '.' or '..')"
            )
        _check_str(self.site, "site")
        _check_str(self.robot_id, "robot_id")
        _check_str(self.description, "description", empty_ok=True)
        T_park = _finite_array(self.T_map_base_park, (4, 4), "T_map_base_park")
        _check_rigid(T_park, "T_map_base_park")
        T_bc = _finite_array(self.T_arm_base_camera, (4, 4), "T_arm_base_camera")
        _check_rigid(T_bc, "T_arm_base_camera")
        q = _finite_array(self.q_sample, (6,), "q_sample")
        if not isinstance(self.path, ToolPath):
            raise InvalidInputError(f"path must be a ToolPath, got {type(self.path).__name__}")
        if not isinstance(self.created, datetime):
            raise InvalidInputError(f"created must be a datetime, got {self.created!r}")
        fv = self.format_version
        if isinstance(fv, bool) or not isinstance(fv, int) or not 1 <= fv <= FORMAT_VERSION:
            raise InvalidInputError(
                f"format_version must be an int in [1, {FORMAT_VERSION}], got {fv!r}"
            )
        object.__setattr__(self, "T_map_base_park", T_park)
        object.__setattr__(self, "T_arm_base_camera", T_bc)
        object.__setattr__(self, "q_sample", q)
        object.__setattr__(self, "cloud", _validate_cloud(self.cloud))
        object.__setattr__(self, "created", self.created.astimezone(UTC))
        object.__setattr__(self, "meta", _validate_meta(self.meta))

    @property
    def has_colors(self) -> bool:
        """False for a colorless cloud (registration then uses geometric ICP)."""
        return self.cloud.colors is not None


@dataclass(frozen=True)
class TaskInfo:
    """One row of :meth:`TaskStore.list`: what a listing shows without loading the blobs."""

    name: str
    site: str
    created: datetime
    n_points: int
    n_waypoints: int
    duration: float  # s, the last path time stamp
    robot_id: str = "twin"
    description: str = ""
    has_colors: bool = True
    rate_hz: float = 0.0
