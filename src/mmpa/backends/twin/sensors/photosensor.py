"""The simulated retroreflective photoelectric sensor on the tool: one ray along site
``photosensor``'s +z axis (geom groups 0-2). Units: m.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from mmpa.backends.twin.sensors.common import (
    FIDUCIAL_REFLECTOR_RE,
    PHOTOSENSOR_SITE,
    RAY_GEOMGROUP,
    lookup_id,
    model_names,
)
from mmpa.robot.description import PhotoSensorDescription

__all__ = ["SimPhotoSensor"]


class SimPhotoSensor:
    """Retroreflective photoelectric sensor on the tool: one ray along site ``photosensor``'s
    +z axis (groups 0-2 only). It triggers iff the first surface hit within
    ``desc.max_range`` is a fiducial reflector ``fiducial_<i>_reflector``, i.e. the beam
    entered a collimator tube and reached its bottom without touching a wall."""

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        desc: PhotoSensorDescription,
        site: str = PHOTOSENSOR_SITE,
    ) -> None:
        self._model, self._data, self._desc = model, data, desc
        self._site = lookup_id(model, mujoco.mjtObj.mjOBJ_SITE, site, "site", model.nsite)
        self._geomid = np.empty(1, dtype=np.int32)
        self._names = model_names(model, mujoco.mjtObj.mjOBJ_GEOM, model.ngeom)
        self._fiducial = np.array(
            [bool(FIDUCIAL_REFLECTOR_RE.match(s)) for s in self._names], dtype=bool
        )

    def hit(self) -> tuple[str | None, float]:
        """``(geom name, distance)`` of the first surface on the beam within ``max_range``;
        ``(None, inf)`` when none (an unnamed geom reads ``"#<geom id>"``)."""
        g, dist = self._hit_id()
        if g < 0:
            return None, math.inf
        return self._names[g] or f"#{g}", dist

    def _hit_id(self) -> tuple[int, float]:
        d = self._data
        pnt = np.array(d.site_xpos[self._site], dtype=np.float64)
        vec = np.array(d.site_xmat[self._site].reshape(3, 3)[:, 2], dtype=np.float64)
        dist = mujoco.mj_ray(self._model, d, pnt, vec, RAY_GEOMGROUP, 1, -1, self._geomid)
        g = int(self._geomid[0])
        if dist < 0 or g < 0 or dist > self._desc.max_range:
            return -1, math.inf
        return g, float(dist)

    def triggered(self) -> bool:
        """True iff the beam reaches a fiducial reflector."""
        g, _ = self._hit_id()
        return g >= 0 and bool(self._fiducial[g])
