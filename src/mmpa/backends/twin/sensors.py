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

Units: m, rad, s.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import mujoco
import numpy as np

from mmpa.backends.twin.error_model import CameraNoise, LidarNoise, OdometryNoise
from mmpa.backends.twin.lidar_noise import (
    beam_subrays,
    footprint_beams,
    incidence_bias,
    reflector_biases,
    strongest_echo,
)
from mmpa.backends.twin.mjcf import OPTICAL_FROM_MUJOCO
from mmpa.backends.twin.noise import (
    angle_diff,
    color_noise,
    depth_noise,
    odometry_increment_noise,
    range_noise,
    resample_to,
)
from mmpa.core.errors import SimulationError, UnknownNameError
from mmpa.core.geometry import Array
from mmpa.robot.description import (
    BaseDescription,
    CameraDescription,
    CameraIntrinsics,
    LidarDescription,
    PhotoSensorDescription,
)
from mmpa.robot.interfaces import LaserScan, Odometry, RGBDFrame

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

CAMERA_NAME = "wrist_camera"
LASER_SITE = "laser"
PHOTOSENSOR_SITE = "photosensor"
# Groups 0 (static world), 1 (movable objects), 2 (reflectors, fiducials); never the robot.
RAY_GEOMGROUP = np.array([1, 1, 1, 0, 0, 0], dtype=np.uint8)

_REFLECTOR_RE = re.compile(r"^reflector_\d+$")
_FIDUCIAL_REFLECTOR_RE = re.compile(r"^fiducial_\d+_reflector$")

# Lidar intensity model: relative noise on returns, reference range of the diffuse falloff.
_REFLECTOR_INTENSITY_REL_SIGMA = 0.02
_SURFACE_INTENSITY_REL_SIGMA = 0.05
_SURFACE_FALLOFF_RANGE = 2.0  # m; diffuse returns fall as (r0 / r)^2 beyond it


def is_retroreflector(name: str | None) -> bool:
    """True for geoms that return a retroreflective (high-intensity) laser echo."""
    return bool(name) and bool(
        _REFLECTOR_RE.match(name) or _FIDUCIAL_REFLECTOR_RE.match(name)  # type: ignore[arg-type]
    )


def _names(model: mujoco.MjModel, obj: mujoco.mjtObj, count: int) -> list[str]:
    return [mujoco.mj_id2name(model, obj, i) or "" for i in range(count)]


def _lookup(model: mujoco.MjModel, obj: mujoco.mjtObj, name: str, kind: str, count: int) -> int:
    i = mujoco.mj_name2id(model, obj, name)
    if i < 0:
        raise UnknownNameError(f"MuJoCo {kind}", name, [n for n in _names(model, obj, count) if n])
    return int(i)


def T_world_camera_optical(model: mujoco.MjModel, data: mujoco.MjData, camera: str) -> Array:
    """TRUE pose of a MuJoCo camera's optical frame (z forward, x right, y down) in the world."""
    cid = _lookup(model, mujoco.mjtObj.mjOBJ_CAMERA, camera, "camera", model.ncam)
    T = np.eye(4)
    T[:3, :3] = data.cam_xmat[cid].reshape(3, 3) @ OPTICAL_FROM_MUJOCO
    T[:3, 3] = data.cam_xpos[cid]
    return T


# --------------------------------------------------------------------------------------------
# camera


class SimCamera:
    """Wrist RGB-D camera (D435-like): renders ``wrist_camera``, adds the depth/color noise.

    Owns a ``mujoco.Renderer`` at the color resolution: call :meth:`close` when done (or use
    it as a context manager). Depth is aligned to color (same intrinsics ``desc.color``).
    :meth:`set_resolution` switches to another stream profile of the same camera (e.g.
    320x240 for the tracking servo loop: a quarter of the pixels to render and corrupt).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        desc: CameraDescription,
        noise: CameraNoise,
        rng: np.random.Generator,
        clock: Callable[[], float],
        camera: str = CAMERA_NAME,
    ) -> None:
        self._model, self._data, self._desc = model, data, desc
        self._noise, self._rng, self._clock = noise, rng, clock
        self._camera = camera
        self._native = desc.color
        self._cam_id = _lookup(model, mujoco.mjtObj.mjOBJ_CAMERA, camera, "camera", model.ncam)
        extent = float(model.stat.extent)
        self._far = float(model.vis.map.zfar) * extent
        self._renderer: mujoco.Renderer | None = None
        self._renderer = self._make_renderer(desc.color)
        # the session's fixed errors at the native resolution, and at the streamed one
        self._session: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
        self._session_at: tuple[np.ndarray | None, np.ndarray | None] = (None, None)

    def set_session(self, disparity: np.ndarray | None, color_gain: np.ndarray | None) -> None:
        """The errors fixed for this session (see
        :class:`~mmpa.backends.twin.error_model.CameraNoise`):
        ``disparity`` (H, W) px, the disparity error of every native pixel (correlated noise,
        drift, bias pattern; :func:`~mmpa.backends.twin.noise.session_disparity`), and
        ``color_gain``
        (H, W, 3), the multiplicative colour gain; both at the native resolution, ``None``
        for none. Streamed at another resolution, each pixel takes its nearest native pixel."""
        k = self._native
        for a, name in ((disparity, "disparity"), (color_gain, "color_gain")):
            if a is not None and tuple(a.shape[:2]) != (k.height, k.width):
                raise SimulationError(
                    f"session {name} must be {k.height}x{k.width} (native), got {a.shape}"
                )
        self._session = (disparity, color_gain)
        self._resample_session()

    def _resample_session(self) -> None:
        k = self._desc.color
        shape = (k.height, k.width)
        self._session_at = tuple(  # type: ignore[assignment]
            None if a is None else resample_to(a, shape) for a in self._session
        )

    def _make_renderer(self, k: CameraIntrinsics) -> mujoco.Renderer:
        self._check_model(self._model, k)
        try:
            return mujoco.Renderer(self._model, height=k.height, width=k.width)
        except Exception as e:  # no GL context, framebuffer too small, ...
            raise SimulationError(
                f"cannot create the MuJoCo renderer for {self._camera!r} ({k.width}x{k.height}): "
                f"{e}. Headless machines need MUJOCO_GL=egl or MUJOCO_GL=osmesa "
                "(with PYOPENGL_PLATFORM=osmesa)."
            ) from e

    @property
    def resolution(self) -> tuple[int, int]:
        """``(width, height)`` of the frames now streamed (pixels)."""
        k = self._desc.color
        return k.width, k.height

    def set_resolution(self, width: int, height: int) -> None:
        """Stream ``width`` x ``height`` frames from now on: the camera's native intrinsics
        :meth:`~mmpa.robot.description.CameraIntrinsics.resized` (same field of view and
        rays; depth stays aligned to color). The noise model is per pixel and unchanged."""
        if self._renderer is None:
            raise SimulationError(f"camera {self._camera!r} was closed")
        k = self._native.resized(int(width), int(height))
        if k == self._desc.color:
            return
        renderer = self._make_renderer(k)
        self._renderer.close()
        self._renderer = renderer
        self._desc = self._desc.model_copy(update={"color": k, "depth": k})
        self._resample_session()

    def _check_model(self, model: mujoco.MjModel, k: CameraIntrinsics) -> None:
        g = model.vis.global_
        if g.offwidth < k.width or g.offheight < k.height:
            raise SimulationError(
                f"offscreen framebuffer {g.offwidth}x{g.offheight} is smaller than the camera "
                f'image {k.width}x{k.height}; set <visual><global offwidth="{k.width}" '
                f'offheight="{k.height}"/></visual> (or larger) in the model'
            )
        extent = float(model.stat.extent)
        near = float(model.vis.map.znear) * extent
        far = float(model.vis.map.zfar) * extent
        if near > self._desc.min_range:
            raise SimulationError(
                f"near clipping plane at {near:.3f} m (znear {model.vis.map.znear} x extent "
                f"{extent:.2f} m) is beyond the camera's min range {self._desc.min_range} m; "
                "lower <visual><map znear=.../></visual>"
            )
        if far < self._desc.max_range:
            raise SimulationError(
                f"far clipping plane at {far:.2f} m is closer than the camera's max range "
                f"{self._desc.max_range} m; raise <visual><map zfar=.../></visual>"
            )
        cid = self._cam_id
        if np.any(model.cam_sensorsize[cid] > 0):
            return  # physical-intrinsics camera: the model author owns the projection
        fovy = float(model.cam_fovy[cid])
        want = math.degrees(k.fovy)
        if abs(fovy - want) > 0.01:
            raise SimulationError(
                f"camera {self._camera!r} has fovy {fovy:.4f} deg but the intrinsics need "
                f"{want:.4f} deg (fy {k.fy} px, height {k.height} px)"
            )
        if (
            abs(k.fx - k.fy) > 1e-3 * k.fy
            or abs(k.cx - (k.width - 1) / 2) > 0.5
            or abs(k.cy - (k.height - 1) / 2) > 0.5
        ):
            raise SimulationError(
                f"MuJoCo renders square pixels and a centered principal point; intrinsics "
                f"fx={k.fx}, fy={k.fy}, cx={k.cx}, cy={k.cy} for {k.width}x{k.height} differ"
            )

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self._desc.color

    def T_world_camera(self) -> Array:
        """TRUE optical-frame pose in the world (ground truth, for evaluation only)."""
        return T_world_camera_optical(self._model, self._data, self._camera)

    def _render(self) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free color (H, W, 3) uint8 and depth (H, W) float32 m, 0 where no surface."""
        r = self._renderer
        if r is None:
            raise SimulationError(f"camera {self._camera!r} was closed")
        r.update_scene(self._data, camera=self._cam_id)
        color = r.render()
        r.enable_depth_rendering()
        try:
            depth = r.render()
        finally:
            r.disable_depth_rendering()
        depth[depth >= np.float32(self._far * (1.0 - 1e-4))] = 0.0  # background: no surface
        return color, depth

    def capture(self) -> RGBDFrame:
        """One noisy RGB-D frame (the error model, with this session's fixed errors),
        stamped with the sim clock."""
        stamp = float(self._clock())
        color, depth = self._render()
        d, n = self._desc, self._noise
        disparity, gain = self._session_at
        depth = depth_noise(
            depth,
            self._rng,
            n,
            d.depth_focal_native,
            d.baseline,
            d.min_range,
            d.max_range,
            fixed_disparity=disparity,
        )
        color = color_noise(color, self._rng, n, gain=gain)
        return RGBDFrame(color=color, depth=depth, intrinsics=d.color, stamp=stamp)

    def capture_truth(self) -> RGBDFrame:
        """Noise-free frame (ground truth): rendered color and exact depth along the optical
        axis, 0 only where no surface is in view (no range limits applied)."""
        stamp = float(self._clock())
        color, depth = self._render()
        return RGBDFrame(color=color, depth=depth, intrinsics=self._desc.color, stamp=stamp)

    def segmentation(self) -> np.ndarray:
        """Ground-truth segmentation (H, W) int32: the MuJoCo BODY id seen at each pixel,
        -1 where no geom is seen (for labelling rendered training data; evaluation only)."""
        r = self._renderer
        if r is None:
            raise SimulationError(f"camera {self._camera!r} was closed")
        r.update_scene(self._data, camera=self._cam_id)
        r.enable_segmentation_rendering()
        try:
            seg = r.render()
        finally:
            r.disable_segmentation_rendering()
        out = np.full(seg.shape[:2], -1, dtype=np.int32)
        is_geom = (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & (seg[..., 0] >= 0)
        out[is_geom] = self._model.geom_bodyid[seg[..., 0][is_geom]]
        return out

    def close(self) -> None:
        """Free the renderer (idempotent)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> SimCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------------------------
# lidar


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
        self._site = _lookup(model, mujoco.mjtObj.mjOBJ_SITE, site, "site", model.nsite)
        a = desc.angles
        self._local_angles = a
        self._local_dirs = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
        n = desc.num_beams
        self._geomid = np.empty(n, dtype=np.int32)
        self._dist = np.empty(n, dtype=np.float64)
        self._normal = np.empty((n, 3), dtype=np.float64)
        names = _names(model, mujoco.mjtObj.mjOBJ_GEOM, model.ngeom)
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


# --------------------------------------------------------------------------------------------
# odometry


def _relative(a: Array, b: Array) -> Array:
    """Planar pose ``b`` expressed in the frame of planar pose ``a`` (both ``[x, y, theta]``)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, angle_diff(b[2], a[2])])


def _compose(a: Array, rel: Array) -> Array:
    """Planar pose ``a`` followed by ``rel`` (expressed in ``a``'s frame)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array(
        [
            a[0] + c * rel[0] - s * rel[1],
            a[1] + s * rel[0] + c * rel[1],
            angle_diff(a[2] + rel[2], 0),
        ]
    )


class SimOdometry:
    """Wheel odometry: the TRUE planar motion, perturbed by the odometry motion model.

    The world calls :meth:`update` with the true base pose ``[x, y, theta]`` (``map``) and the
    time, as often as it likes. True motion is cut into segments of ``segment_length`` m or
    ``segment_angle`` rad (Nav2 AMCL's ``update_min_d`` / ``update_min_a`` defaults), and each
    finished segment's increment ``(rot1, trans, rot2)`` is perturbed with
    :func:`~mmpa.backends.twin.noise.odometry_increment_noise` and composed onto the odometry pose,
    so
    the error statistics are exactly those AMCL's motion model assumes at its update rate (the
    model's variance is quadratic in the increment, so it depends on where increments are cut).
    Inside a segment the pose follows the true motion exactly; the segment's noise is added
    when it closes. The twist is the true body velocity between the last two updates.

    The odometry frame starts at ``initial_pose`` where the first :meth:`update` finds the base.
    """

    _MIN_TRANS_FOR_HEADING = 0.01  # m; below it rot1's noise is computed as for rot1 = 0 (Nav2)

    def __init__(
        self,
        desc: BaseDescription,
        noise: OdometryNoise,
        rng: np.random.Generator,
        initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
        segment_length: float = 0.25,
        segment_angle: float = 0.2,
    ) -> None:
        self._desc, self._noise, self._rng = desc, noise, rng
        self._seg_len, self._seg_ang = float(segment_length), float(segment_angle)
        self._initial = np.array(initial_pose, dtype=float)
        self._pose = self._initial.copy()  # odometry pose at the start of the open segment
        self._seg_start: Array | None = None  # true pose at the start of the open segment
        self._last: Array | None = None
        self._last_stamp = 0.0
        self._twist = np.zeros(2)

    def reset(self, initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        """Restart: the next :meth:`update` defines the odometry origin anew."""
        self._initial = np.array(initial_pose, dtype=float)
        self._pose = self._initial.copy()
        self._seg_start = self._last = None
        self._twist = np.zeros(2)

    def update(self, true_pose: Array, stamp: float) -> None:
        """Feed the TRUE planar base pose ``[x, y, theta]`` at time ``stamp`` (s)."""
        p = np.asarray(true_pose, dtype=float).reshape(3)
        if self._last is None or self._seg_start is None:
            self._seg_start, self._last, self._last_stamp = p, p, float(stamp)
            return
        step = _relative(self._last, p)
        dt = float(stamp) - self._last_stamp
        if dt > 0:
            self._twist = np.array([step[0] / dt, step[2] / dt])
        self._last, self._last_stamp = p, float(stamp)

        rel = _relative(self._seg_start, p)
        trans = math.hypot(rel[0], rel[1])
        if trans < self._seg_len - 1e-9 and abs(rel[2]) < self._seg_ang - 1e-9:
            return
        # close the segment: exact increment (Thrun's rot1, trans, rot2) plus model noise
        rot1 = math.atan2(rel[1], rel[0]) if trans > 0 else 0.0
        rot2 = angle_diff(rel[2], rot1)
        r1_in = rot1 if trans >= self._MIN_TRANS_FOR_HEADING else 0.0
        r2_in = angle_diff(rel[2], r1_in)
        r1_hat, t_hat, r2_hat = odometry_increment_noise(
            r1_in, trans, r2_in, self._rng, self._noise
        )
        r1 = rot1 + angle_diff(r1_hat, r1_in)
        t = trans + (t_hat - trans)
        r2 = rot2 + angle_diff(r2_hat, r2_in)
        th = self._pose[2]
        self._pose = np.array(
            [
                self._pose[0] + t * math.cos(th + r1),
                self._pose[1] + t * math.sin(th + r1),
                angle_diff(th + r1 + r2, 0.0),
            ]
        )
        self._seg_start = p

    def odometry(self) -> Odometry:
        """The current odometry pose in ``odom`` and body twist ``[v, w]``."""
        pose = self._pose
        if self._seg_start is not None and self._last is not None:
            pose = _compose(self._pose, _relative(self._seg_start, self._last))
        v, w = float(self._twist[0]), float(self._twist[1])
        half = 0.5 * self._desc.track_width
        extra = {
            "wheel_left": (v - w * half) / self._desc.wheel_radius,  # rad/s
            "wheel_right": (v + w * half) / self._desc.wheel_radius,
        }
        return Odometry(
            pose=pose.copy(), twist=self._twist.copy(), stamp=self._last_stamp, extra=extra
        )


# --------------------------------------------------------------------------------------------
# photoelectric sensor


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
        self._site = _lookup(model, mujoco.mjtObj.mjOBJ_SITE, site, "site", model.nsite)
        self._geomid = np.empty(1, dtype=np.int32)
        self._names = _names(model, mujoco.mjtObj.mjOBJ_GEOM, model.ngeom)
        self._fiducial = np.array(
            [bool(_FIDUCIAL_REFLECTOR_RE.match(s)) for s in self._names], dtype=bool
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
