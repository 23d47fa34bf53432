"""What the twin's sensors share: the model's names they read (camera ``wrist_camera``,
sites ``laser`` and ``photosensor``), the geom groups rays see, the retroreflector names,
name lookups with a helpful error, and the TRUE optical frame of a MuJoCo camera
(MuJoCo camera frame rotated by ``diag(1, -1, -1)``: z forward, x right, y down). Units: m.
"""

from __future__ import annotations

import re

import mujoco
import numpy as np

from mmpa.backends.twin.mjcf import OPTICAL_FROM_MUJOCO
from mmpa.core.errors import UnknownNameError
from mmpa.core.geometry import Array

__all__ = [
    "CAMERA_NAME",
    "FIDUCIAL_REFLECTOR_RE",
    "LASER_SITE",
    "PHOTOSENSOR_SITE",
    "RAY_GEOMGROUP",
    "T_world_camera_optical",
    "is_retroreflector",
    "lookup_id",
    "model_names",
]

CAMERA_NAME = "wrist_camera"
LASER_SITE = "laser"
PHOTOSENSOR_SITE = "photosensor"
# Groups 0 (static world), 1 (movable objects), 2 (reflectors, fiducials); never the robot.
RAY_GEOMGROUP = np.array([1, 1, 1, 0, 0, 0], dtype=np.uint8)

REFLECTOR_RE = re.compile(r"^reflector_\d+$")
FIDUCIAL_REFLECTOR_RE = re.compile(r"^fiducial_\d+_reflector$")


def is_retroreflector(name: str | None) -> bool:
    """True for geoms that return a retroreflective (high-intensity) laser echo."""
    return bool(name) and bool(
        REFLECTOR_RE.match(name) or FIDUCIAL_REFLECTOR_RE.match(name)  # type: ignore[arg-type]
    )


def model_names(model: mujoco.MjModel, obj: mujoco.mjtObj, count: int) -> list[str]:
    """The names of the model's ``count`` objects of type ``obj`` ("" for unnamed ones)."""
    return [mujoco.mj_id2name(model, obj, i) or "" for i in range(count)]


def lookup_id(model: mujoco.MjModel, obj: mujoco.mjtObj, name: str, kind: str, count: int) -> int:
    """The id of the ``kind`` named ``name``; :class:`UnknownNameError` listing the names."""
    i = mujoco.mj_name2id(model, obj, name)
    if i < 0:
        raise UnknownNameError(
            f"MuJoCo {kind}", name, [n for n in model_names(model, obj, count) if n]
        )
    return int(i)


def T_world_camera_optical(model: mujoco.MjModel, data: mujoco.MjData, camera: str) -> Array:
    """TRUE pose of a MuJoCo camera's optical frame (z forward, x right, y down) in the world."""
    cid = lookup_id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera, "camera", model.ncam)
    T = np.eye(4)
    T[:3, :3] = data.cam_xmat[cid].reshape(3, 3) @ OPTICAL_FROM_MUJOCO
    T[:3, 3] = data.cam_xpos[cid]
    return T
