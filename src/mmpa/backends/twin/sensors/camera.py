"""The simulated wrist RGB-D camera (D435-like): renders the model's ``wrist_camera``
(:class:`~mmpa.backends.twin.sensors.render.CameraRenderer`) and adds the error model's depth
and colour noise (:mod:`mmpa.backends.twin.noise`), with the session's disparity drift and
colour gain. Units: m, rad, s; depth in m, colour uint8.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import mujoco
import numpy as np

from mmpa.backends.twin.error_model import CameraNoise
from mmpa.backends.twin.noise import color_noise, depth_noise, resample_to
from mmpa.backends.twin.sensors.common import CAMERA_NAME, T_world_camera_optical, lookup_id
from mmpa.backends.twin.sensors.render import CameraRenderer
from mmpa.core.errors import SimulationError
from mmpa.core.geometry import Array
from mmpa.robot.description import CameraDescription, CameraIntrinsics
from mmpa.robot.interfaces import RGBDFrame

__all__ = ["SimCamera"]


class SimCamera:
    """Wrist RGB-D camera (D435-like): renders ``wrist_camera``, adds the depth/color noise.

    Owns a :class:`~mmpa.backends.twin.sensors.render.CameraRenderer` at the color
    resolution: call :meth:`close` when done (or use it as a context manager). Depth is
    aligned to color (same intrinsics ``desc.color``). :meth:`set_resolution` switches to
    another stream profile of the same camera (e.g. 320x240 for the tracking servo loop: a
    quarter of the pixels to render and corrupt).
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
        self._cam_id = lookup_id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera, "camera", model.ncam)
        extent = float(model.stat.extent)
        self._far = float(model.vis.map.zfar) * extent
        self._renderer: CameraRenderer | None = None
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

    def _make_renderer(self, k: CameraIntrinsics) -> CameraRenderer:
        self._check_model(self._model, k)
        try:
            return CameraRenderer(self._model, k.width, k.height, self._cam_id)
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
        color, depth = r.render(self._data)
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
        seg = r.segmentation(self._data)
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
