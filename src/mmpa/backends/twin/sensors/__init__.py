"""Simulated sensors: the hardware interfaces of ``mmpa.robot.interfaces`` on a MuJoCo model,
with the error model of DESIGN.md (its profiles, "Error model v2").

Sensors only READ the simulation state: the world owns stepping and calls ``mj_forward`` (or
steps) before a sensor is read, so ``data`` holds current poses. Each sensor draws its noise
from the ``numpy.random.Generator`` it is given (see ``ErrorModel.rng``).

Model contract (names in the generated MJCF):

- camera ``wrist_camera`` (MuJoCo camera frame: looks along -z, y up; the optical frame is
  that frame rotated by ``diag(1, -1, -1)``), ``fovy`` from the intrinsics;
- site ``laser`` (scan plane = its x-y plane, x forward, z up);
- site ``photosensor`` (beam along its +z axis);
- geom groups: 0 static world, 1 movable objects, 2 reflectors and fiducials, 3 robot
  collision, 4 robot visuals. Lidar and photosensor rays see groups 0-2 only;
- laser reflectors ``reflector_<i>``; fiducial reflectors ``fiducial_<i>_reflector`` at the
  bottom of tubes walled by ``fiducial_<i>_wall_<k>``.

One module per sensor: :mod:`~mmpa.backends.twin.sensors.camera`,
:mod:`~mmpa.backends.twin.sensors.lidar`, :mod:`~mmpa.backends.twin.sensors.odometry`,
:mod:`~mmpa.backends.twin.sensors.photosensor`; the names and lookups they share in
:mod:`~mmpa.backends.twin.sensors.common`. Units: m, rad, s.
"""

from __future__ import annotations

from mmpa.backends.twin.sensors.camera import SimCamera
from mmpa.backends.twin.sensors.common import (
    CAMERA_NAME,
    LASER_SITE,
    PHOTOSENSOR_SITE,
    RAY_GEOMGROUP,
    T_world_camera_optical,
    is_retroreflector,
)
from mmpa.backends.twin.sensors.lidar import SimLidar
from mmpa.backends.twin.sensors.odometry import SimOdometry
from mmpa.backends.twin.sensors.photosensor import SimPhotoSensor

__all__ = [
    "CAMERA_NAME",
    "LASER_SITE",
    "PHOTOSENSOR_SITE",
    "RAY_GEOMGROUP",
    "SimCamera",
    "SimLidar",
    "SimOdometry",
    "SimPhotoSensor",
    "T_world_camera_optical",
    "is_retroreflector",
]
