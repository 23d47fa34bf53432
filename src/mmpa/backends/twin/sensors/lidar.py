"""The simulated 2D lidar: every beam cast from site ``laser`` in its x-y plane (geom groups
0-2), ranges and intensities with the error model's noise, retroreflector biases and beam
footprint (:mod:`mmpa.backends.twin.lidar_noise`). Units: m, rad, s.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import mujoco
import numpy as np

from mmpa.backends.twin.error_model import LidarNoise
from mmpa.backends.twin.lidar_noise import (
    beam_subrays,
    footprint_beams,
    incidence_bias,
    reflector_biases,
    strongest_echo,
)
from mmpa.backends.twin.noise import range_noise
from mmpa.backends.twin.sensors.common import (
    LASER_SITE,
    RAY_GEOMGROUP,
    is_retroreflector,
    lookup_id,
    model_names,
)
from mmpa.core.geometry import Array
from mmpa.robot.description import LidarDescription
from mmpa.robot.interfaces import LaserScan

__all__ = ["SimLidar"]

# Lidar intensity model: relative noise on returns, reference range of the diffuse falloff.

_REFLECTOR_INTENSITY_REL_SIGMA = 0.02
_SURFACE_INTENSITY_REL_SIGMA = 0.05
_SURFACE_FALLOFF_RANGE = 2.0  # m; diffuse returns fall as (r0 / r)^2 beyond it


class SimLidar:
    """2D lidar: casts every beam from site ``laser`` in its x-y plane (groups 0-2 only).

    Ranges get ``N(0, noise.range_sigma)``; no return within ``range_max`` is ``inf``.
    Intensities: retroreflectors (``reflector_<i>``, ``fiducial_<i>_reflector``) return
    ``noise.reflector_intensity`` (2 % noise); other surfaces ``noise.surface_intensity``
    times ``|cos(incidence)|`` times ``min(1, (2 m / r)^2)`` (5 % noise); no return is 0.

    Error model v2 (:mod:`mmpa.backends.twin.lidar_noise`): a retroreflective return is off by its
    reflector's fixed bias ``noise.reflector_bias_mean + N(0, noise.reflector_bias_sd)``
    (drawn once from ``bias_rng``, the robot instance's stream) plus
    ``noise.reflector_incidence_bias (1 - cos incidence)``. With a beam footprint
    (``noise.beam_width`` or ``noise.beam_divergence`` > 0) the beams whose spot can reach an
    edge or a reflector are resolved by :data:`~mmpa.backends.twin.lidar_noise.SUBRAYS` sub-rays,
    and
    the reported range and intensity are those of the strongest echo of the summed pulses
    (:func:`~mmpa.backends.twin.lidar_noise.strongest_echo`: mixed returns at depth edges, partial
    intensity at a reflector's edge). With all these fields 0 (profile ``reference``) the
    scan is the single-ray model above, draw for draw. :meth:`scan_truth` is always the
    noise-free single-ray cast.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        desc: LidarDescription,
        noise: LidarNoise,
        rng: np.random.Generator,
        clock: Callable[[], float],
        site: str = LASER_SITE,
        bias_rng: np.random.Generator | None = None,
    ) -> None:
        self._model, self._data, self._desc = model, data, desc
        self._noise, self._rng, self._clock = noise, rng, clock
        self._site = lookup_id(model, mujoco.mjtObj.mjOBJ_SITE, site, "site", model.nsite)
        a = desc.angles
        self._local_angles = a
        self._local_dirs = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
        n = desc.num_beams
        self._geomid = np.empty(n, dtype=np.int32)
        self._dist = np.empty(n, dtype=np.float64)
        self._normal = np.empty((n, 3), dtype=np.float64)
        names = model_names(model, mujoco.mjtObj.mjOBJ_GEOM, model.ngeom)
        # index ngeom (= geomid -1) means "no hit"
        # index ngeom + 1 (= geomid -2, an occluder) and ngeom (-1, no hit): not retroreflective
        self._retro = np.array([is_retroreflector(s) for s in names] + [False, False], dtype=bool)
        #: vertical cylinders ``(x, y, radius)`` in ``map`` that block beams (e.g. people)
        self.occluders: list[tuple[float, float, float]] = []
        # error model v2: per-reflector range bias (fixed per robot; indexed like _retro)
        self._biased = (
            noise.reflector_bias_mean != 0
            or noise.reflector_bias_sd > 0
            or noise.reflector_incidence_bias != 0
        )
        self._bias = np.zeros(model.ngeom + 2)
        if self._biased:
            gen = bias_rng if bias_rng is not None else np.random.default_rng(0)
            self._bias[: model.ngeom] = reflector_biases(
                names,
                self._retro[: model.ngeom],
                gen,
                noise.reflector_bias_mean,
                noise.reflector_bias_sd,
            )
        self._footprint = noise.beam_width > 0 or noise.beam_divergence > 0
        self._sub_u, self._sub_w = beam_subrays()
        self._circular = desc.num_beams * desc.angle_increment >= 2 * math.pi - 1e-9

    def cast(self) -> tuple[Array, Array, Array]:
        """Noise-free ray cast: ``(ranges, geom ids, cos incidence)``, each (num_beams,);
        ``inf`` / -1 / 0 where nothing is hit within ``range_max``."""
        return self._cast_local(self._local_dirs, self._geomid, self._dist, self._normal)

    def _cast_local(
        self, local_dirs: Array, geomid: np.ndarray, dist: np.ndarray, normal: np.ndarray
    ) -> tuple[Array, Array, Array]:
        """Cast rays from the laser site along ``local_dirs`` (n, 3) (laser frame) into the
        buffers ``geomid`` (n,) int32, ``dist`` (n,), ``normal`` (n, 3); see :meth:`cast`."""
        m, d, desc = self._model, self._data, self._desc
        R = d.site_xmat[self._site].reshape(3, 3)
        dirs = np.ascontiguousarray(local_dirs @ R.T)
        mujoco.mj_multiRay(
            m,
            d,
            np.array(d.site_xpos[self._site], dtype=np.float64),
            dirs.reshape(-1),
            RAY_GEOMGROUP,
            1,
            -1,
            geomid,
            dist,
            normal.reshape(-1),
            dirs.shape[0],
            desc.range_max,
        )
        gid = geomid.copy()
        hit = (gid >= 0) & (dist >= 0) & (dist <= desc.range_max)
        gid[~hit] = -1
        ranges = np.where(hit, dist, np.inf)
        cos_inc = np.where(hit, np.abs(np.einsum("ij,ij->i", dirs, normal)), 0.0)
        if self.occluders:
            origin = d.site_xpos[self._site]
            ranges, gid, cos_inc = self._occlude(origin, dirs, ranges, gid, cos_inc)
        return ranges, gid, cos_inc

    def _occlude(
        self, origin: Array, dirs: Array, ranges: Array, gid: Array, cos_inc: Array
    ) -> tuple[Array, Array, Array]:
        """Cut beams at the vertical cylinders of :attr:`occluders` (people, carts): a plain
        surface (no retroreflection) wherever a cylinder is nearer than the first hit."""
        ranges, gid, cos_inc = ranges.copy(), gid.copy(), cos_inc.copy()
        gid_surface = -2  # hit, not a retroreflector (index -2 is never a retroreflector)
        dxy = dirs[:, :2]
        n2 = np.maximum(np.einsum("ij,ij->i", dxy, dxy), 1e-12)
        for cx, cy, rad in self.occluders:
            oc = np.array([cx - origin[0], cy - origin[1]])
            b = dxy @ oc
            disc = b * b - n2 * (oc @ oc - rad * rad)
            ok = disc >= 0
            t = np.where(ok, (b - np.sqrt(np.maximum(disc, 0.0))) / n2, np.inf)
            nearer = ok & (t > 0) & (t < ranges)
            ranges[nearer] = t[nearer]
            gid[nearer] = gid_surface
            cos_inc[nearer] = 1.0
        return ranges, gid, cos_inc

    def _intensities(self, ranges: Array, gid: Array, cos_inc: Array, noisy: bool) -> Array:
        n = self._noise
        hit = gid != -1  # -2: an occluder (a plain surface)
        retro = self._retro[gid]  # gid -1 / -2 index the trailing False entries
        r = np.where(hit, ranges, 1.0)
        falloff = np.minimum(1.0, (_SURFACE_FALLOFF_RANGE / np.maximum(r, 1e-6)) ** 2)
        surface = n.surface_intensity * cos_inc * falloff
        if noisy:
            e = self._rng.standard_normal((2, ranges.shape[0]))
            refl = n.reflector_intensity * (1.0 + _REFLECTOR_INTENSITY_REL_SIGMA * e[0])
            surface = surface * (1.0 + _SURFACE_INTENSITY_REL_SIGMA * e[1])
        else:
            refl = np.full(ranges.shape, n.reflector_intensity)
        out = np.where(retro, refl, surface)
        return np.where(hit, np.maximum(out, 0.0), 0.0)

    def _reflectivity(self, ranges: Array, gid: Array, cos_inc: Array) -> tuple[Array, Array]:
        """Noise-free echo strength of single rays, split into the retroreflective part and
        the plain-surface part (the intensity model of the class docstring; 0: no hit)."""
        n = self._noise
        hit = gid != -1
        retro = self._retro[gid]
        r = np.where(hit, ranges, 1.0)
        falloff = np.minimum(1.0, (_SURFACE_FALLOFF_RANGE / np.maximum(r, 1e-6)) ** 2)
        surface = np.where(hit & ~retro, n.surface_intensity * cos_inc * falloff, 0.0)
        return np.where(retro, n.reflector_intensity, 0.0), surface

    def _walked(self, ranges: Array, gid: Array, cos_inc: Array) -> Array:
        """Ranges with the reflector range walk: ``+ b_reflector + c (1 - cos incidence)`` on
        retroreflective hits (class docstring)."""
        if not self._biased:
            return ranges
        walk = self._bias[gid] + incidence_bias(cos_inc, self._noise.reflector_incidence_bias)
        return np.where(self._retro[gid], ranges + walk, ranges)

    def _returns(self, ranges: Array, gid: Array, cos_inc: Array) -> tuple[Array, Array, Array]:
        """Noise-free measured ranges and intensity parts (retroreflective, plain) under the
        error model v2: range walk, and the beam footprint where it can reach an edge or a
        reflector (sub-rays fanned by ``D(r_ref) / r_ref``, strongest echo; see
        :mod:`mmpa.backends.twin.lidar_noise`)."""
        out_r = self._walked(ranges, gid, cos_inc)
        refl, surf = self._reflectivity(ranges, gid, cos_inc)
        if not self._footprint:
            return out_r, refl, surf
        n, desc = self._noise, self._desc
        need, r_ref = footprint_beams(
            ranges,
            gid,
            self._retro[gid],
            desc.angle_increment,
            n.beam_width,
            n.beam_divergence,
            desc.range_max,
            self._circular,
        )
        idx = np.flatnonzero(need)
        if idx.size == 0:
            return out_r, refl, surf
        u, w = self._sub_u, self._sub_w
        side = np.flatnonzero(u != 0)
        spread = (n.beam_width + n.beam_divergence * r_ref[idx]) / r_ref[idx]  # rad, D / r
        ang = self._local_angles[idx, None] + u[None, side] * spread[:, None]  # (m, K-1)
        a = ang.reshape(-1)
        local = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
        k = a.size
        sr, sg, sc = self._cast_local(local, np.empty(k, np.int32), np.empty(k), np.empty((k, 3)))
        shape = (idx.size, u.size)
        R_all, G_all, C_all = np.empty(shape), np.empty(shape, np.int64), np.empty(shape)
        mid = u.size // 2
        R_all[:, mid], G_all[:, mid], C_all[:, mid] = ranges[idx], gid[idx], cos_inc[idx]
        R_all[:, side] = sr.reshape(idx.size, -1)
        G_all[:, side] = sg.reshape(idx.size, -1)
        C_all[:, side] = sc.reshape(idx.size, -1)
        walked = self._walked(R_all, G_all, C_all)
        s_refl, s_surf = self._reflectivity(R_all, G_all, C_all)
        echo, gain = strongest_echo(walked, w * (s_refl + s_surf))
        out_r, refl, surf = out_r.copy(), refl.copy(), surf.copy()
        out_r[idx] = echo
        refl[idx] = np.sum(w * s_refl * gain, axis=1)
        surf[idx] = np.sum(w * s_surf * gain, axis=1)
        return out_r, refl, surf

    def _make(self, ranges: Array, intensities: Array) -> LaserScan:
        desc = self._desc
        scan_time = 1.0 / desc.rate
        return LaserScan(
            angle_min=desc.angle_min,
            angle_max=desc.angle_max,
            angle_increment=desc.angle_increment,
            time_increment=scan_time / desc.num_beams,
            scan_time=scan_time,
            range_min=desc.range_min,
            range_max=desc.range_max,
            ranges=ranges,
            intensities=intensities,
            stamp=float(self._clock()),
        )

    def scan(self) -> LaserScan:
        """One noisy scan (all beams at the current state)."""
        ranges, gid, cos_inc = self.cast()
        if self._biased or self._footprint:  # error model v2 (class docstring)
            ranges, refl, surf = self._returns(ranges, gid, cos_inc)
            e = self._rng.standard_normal((2, ranges.shape[0]))
            inten = refl * (1.0 + _REFLECTOR_INTENSITY_REL_SIGMA * e[0]) + surf * (
                1.0 + _SURFACE_INTENSITY_REL_SIGMA * e[1]
            )
            inten = np.where(np.isfinite(ranges), np.maximum(inten, 0.0), 0.0)
        else:
            inten = self._intensities(ranges, gid, cos_inc, noisy=True)
        noisy = range_noise(ranges, self._rng, self._noise.range_sigma, self._desc.range_max)
        inten[np.isinf(noisy)] = 0.0  # pushed beyond range_max by the noise: no echo
        return self._make(noisy, inten)

    def scan_truth(self) -> LaserScan:
        """Noise-free scan (ground truth, for evaluation only)."""
        ranges, gid, cos_inc = self.cast()
        return self._make(ranges, self._intensities(ranges, gid, cos_inc, noisy=False))
