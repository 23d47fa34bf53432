"""Offscreen colour + depth rendering of one MuJoCo camera, for the simulated RGB-D camera.

Gives the pixels ``mujoco.Renderer`` gives (colour pass, then a depth pass in segmentation
mode, as ``Renderer.render`` with depth rendering enabled does), bit for bit, at less cost on
a software OpenGL (llvmpipe, OSMesa):

- the offscreen framebuffer is sized to the image (``mjr_resizeOffscreen``), not to the
  model's ``offwidth`` x ``offheight``: the multisample resolve and the stencil clear of the
  floor's reflection touch the image's pixels only;
- geoms that cannot reach a pixel are skipped (:func:`cull_mask`): a model geom whose
  bounding sphere (``modelrbound``, centred at the geom's position) lies outside the view
  frustum and, in the colour pass, outside the frustum mirrored in the reflecting geom.
  A skipped geom covers no sample of the image, so no pixel changes;
- one scene update for both passes, the read-back buffers reused, depth converted to metres
  in place (the float64 arithmetic of ``Renderer.render``, so the same float32 values).

Depth is the distance along the optical axis (m), float32, ``far`` (``zfar * extent``) where
no surface is; colour uint8 RGB; both (H, W), row 0 the top of the image.
"""

from __future__ import annotations

import mujoco
import numpy as np

from mmpa.core.errors import SimulationError

__all__ = ["CameraRenderer", "cull_mask"]

_G = mujoco.mjtGeom
# types drawn from a unit primitive or a mesh inside the geom's bounding sphere
_CULLABLE = np.array(
    [
        int(t)
        for t in (
            _G.mjGEOM_SPHERE,
            _G.mjGEOM_CAPSULE,
            _G.mjGEOM_ELLIPSOID,
            _G.mjGEOM_CYLINDER,
            _G.mjGEOM_BOX,
            _G.mjGEOM_MESH,
        )
    ]
)
_NONE = int(_G.mjGEOM_NONE)  # mjr_render draws nothing for it
_PLANE, _BOX = int(_G.mjGEOM_PLANE), int(_G.mjGEOM_BOX)  # the types that can reflect
_CAT_ALL = int(mujoco.mjtCatBit.mjCAT_ALL)
_OBJ_GEOM = int(mujoco.mjtObj.mjOBJ_GEOM)
_F = mujoco.mjtRndFlag
# bounding-sphere margin: relative, and absolute (m); a larger sphere only culls less
_MARGIN_REL, _MARGIN_ABS = 0.01, 0.005


def _owned(cls: type) -> type:
    """``cls`` without its own ``__del__``: :meth:`CameraRenderer.close` frees the GL
    context after the MuJoCo context made on it (as ``mujoco.Renderer`` does)."""
    return type(f"_Owned{cls.__name__}", (cls,), {"__del__": lambda self: None})


def cull_mask(
    centers: np.ndarray,
    radii: np.ndarray,
    eye: np.ndarray,
    forward: np.ndarray,
    up: np.ndarray,
    frustum: tuple[float, float, float, float, float, float],
) -> np.ndarray:
    """Which spheres (``centers`` (N, 3), ``radii`` (N,), m, world frame) lie wholly outside
    the perspective view frustum of a camera at ``eye`` looking along ``forward`` with
    ``up`` (OpenGL ``lookAt``: ``s = f x up``, ``u = s x f``), ``frustum`` = ``(left, right,
    bottom, top, near, far)`` as ``glFrustum`` takes them (the image-plane extents at
    distance ``near``). Returns (N,) bool, True = outside.

    In the camera frame ``(x, y, z) = (s, u, f) . (c - eye)``, a sphere is outside when its
    centre is farther than its radius beyond one of the six planes: ``z < near - r``,
    ``z > far + r``, or, for a side plane through the eye with inward normal ``n``,
    ``n . (x, y, z) < -r`` (e.g. the right plane ``near x - right z = 0``)."""
    left, right, bottom, top, near, far = frustum
    f = forward / np.linalg.norm(forward)
    s = np.cross(f, up)
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    d = np.asarray(centers, dtype=np.float64) - eye
    x, y, z = d @ s, d @ u, d @ f
    r = np.asarray(radii, dtype=np.float64)
    out = (z < near - r) | (z > far + r)
    for a, w, edge in ((x, 1.0, right), (x, -1.0, left), (y, 1.0, top), (y, -1.0, bottom)):
        # outward signed distance to the plane w (near a - edge z) = 0
        out |= w * (near * a - edge * z) / np.hypot(near, edge) > r
    return out


class CameraRenderer:
    """Renders camera ``camera_id`` of ``model`` at ``width`` x ``height`` (pixels) on an
    OpenGL context of its own (``MUJOCO_GL``). Call :meth:`close` when done."""

    def __init__(self, model: mujoco.MjModel, width: int, height: int, camera_id: int) -> None:
        self._model, self._width, self._height = model, int(width), int(height)
        self._gl = None
        self._con: mujoco.MjrContext | None = None
        try:
            gl_cls = mujoco.GLContext
        except AttributeError as e:  # MUJOCO_GL=disable or no backend
            raise SimulationError(f"MuJoCo has no OpenGL context class: {e}") from e
        self._gl = _owned(gl_cls)(self._width, self._height)
        self._gl.make_current()
        self._con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150.value)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._con)
        mujoco.mjr_resizeOffscreen(self._width, self._height, self._con)
        self._con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scene = mujoco.MjvScene(model, maxgeom=10000)
        self._option = mujoco.MjvOption()
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._cam.fixedcamid = int(camera_id)
        self._rect = mujoco.MjrRect(0, 0, self._width, self._height)
        self.culled = (0, 0)  # geoms skipped in the last colour and depth pass
        h, w = self._height, self._width
        self._rgb = np.empty((h, w, 3), dtype=np.uint8)  # read-back buffers, bottom row first
        self._raw = np.empty((h, w), dtype=np.float32)
        self._z64 = np.empty((h, w), dtype=np.float64)
        # depth-buffer value -> metres, in the float32 constants of mujoco.Renderer.render
        extent = model.stat.extent
        self._znear = np.float32(model.vis.map.znear * extent)
        self._zfar = np.float32(model.vis.map.zfar * extent)
        zn, zf = self._znear, self._zfar
        c = -(zf + zn) / (zf - zn)
        d = -(np.float32(2) * zf * zn) / (zf - zn)
        self._c = np.float64(np.float32(-0.5) * c - np.float32(0.5))  # reverse-Z mapping
        self._d = np.float64(np.float32(-0.5) * d)

    def _update(self, data: mujoco.MjData) -> tuple[mujoco.MjrContext, mujoco.MjvScene]:
        """Make the context current and the scene ``data``'s (default options, all
        categories, as ``mujoco.Renderer.update_scene``)."""
        if self._con is None or self._gl is None:
            raise SimulationError("the camera renderer was closed")
        self._gl.make_current()
        scn = self._scene
        mujoco.mjv_updateScene(self._model, data, self._option, None, self._cam, _CAT_ALL, scn)
        return self._con, scn

    def _render_segments(self, con: mujoco.MjrContext, scn: mujoco.MjvScene) -> None:
        """Render the scene in segmentation mode (flat id colours, no multisampling,
        lighting, reflection or skybox): ``mujoco.Renderer`` 's depth and segmentation."""
        flags = scn.flags.copy()
        scn.flags[_F.mjRND_SEGMENT] = scn.flags[_F.mjRND_IDCOLOR] = 1
        try:
            mujoco.mjr_render(self._rect, scn, con)
        finally:
            np.copyto(scn.flags, flags)

    def render(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """Colour (H, W, 3) uint8 and depth (H, W) float32 m (``far`` where no surface),
        new arrays; equal to ``mujoco.Renderer`` 's colour and depth renders."""
        con, scn = self._update(data)
        geoms = scn.geoms[: scn.ngeom]
        types = [int(g.type) for g in geoms]
        out_view, out_mirror = self._culled(geoms)
        self.culled = (int(out_mirror.sum()), int(out_view.sum()))
        for i in np.flatnonzero(out_view & out_mirror):
            geoms[i].type = _NONE
        mujoco.mjr_render(self._rect, scn, con)
        mujoco.mjr_readPixels(self._rgb, None, self._rect, con)
        color = np.ascontiguousarray(self._rgb[::-1])
        for i in np.flatnonzero(out_view & ~out_mirror):
            geoms[i].type = _NONE
        try:
            self._render_segments(con, scn)  # depth
        finally:
            for g, t in zip(geoms, types, strict=True):
                g.type = t
        mujoco.mjr_readPixels(None, self._raw, self._rect, con)
        return color, self._metric_depth(bool(scn.camera[0].orthographic))

    def _metric_depth(self, orthographic: bool) -> np.ndarray:
        """The read depth buffer (reverse Z, ``mjDEPTH_ZEROFAR``) in metres, top row first:
        perspective ``d / (b + c)``, orthographic ``far - b (far - near)``, in float64,
        rounded to float32."""
        z, raw = self._z64, self._raw[::-1]
        if orthographic:
            np.multiply(raw, np.float64(self._zfar - self._znear), out=z)
            np.subtract(np.float64(self._zfar), z, out=z)
        else:
            np.add(raw, self._c, out=z)
            np.divide(self._d, z, out=z)
        return z.astype(np.float32)

    def _culled(self, geoms: tuple) -> tuple[np.ndarray, np.ndarray]:
        """Per scene geom: outside the view frustum, and outside it mirrored in every
        reflecting geom (both False where unsure: no culling with shadows, stereo, a scene
        transform or an orthographic camera)."""
        n = len(geoms)
        none = np.zeros(n, dtype=bool)
        scn = self._scene
        cam0, cam1 = scn.camera[0], scn.camera[1]
        shadows = scn.flags[_F.mjRND_SHADOW] and any(
            scn.lights[i].castshadow for i in range(scn.nlight)
        )
        if shadows or scn.stereo or scn.enabletransform or cam0.orthographic or n == 0:
            return none, none
        cand = np.array(
            [
                g.objtype == _OBJ_GEOM and g.modelrbound > 0 and g.rgba[3] >= 0.995 and not g.label
                for g in geoms
            ]
        ) & np.isin(np.array([int(g.type) for g in geoms]), _CULLABLE)
        idx = np.flatnonzero(cand)
        if idx.size == 0:
            return none, none
        centers = np.array([geoms[i].pos for i in idx], dtype=np.float64)
        radii = np.array([geoms[i].modelrbound for i in idx], dtype=np.float64)
        radii = radii * (1.0 + _MARGIN_REL) + _MARGIN_ABS
        eye = 0.5 * (np.asarray(cam0.pos, float) + np.asarray(cam1.pos, float))
        fwd = 0.5 * (np.asarray(cam0.forward, float) + np.asarray(cam1.forward, float))
        up = 0.5 * (np.asarray(cam0.up, float) + np.asarray(cam1.up, float))
        half = 0.5 * (cam0.frustum_width + cam1.frustum_width)
        bottom = 0.5 * (cam0.frustum_bottom + cam1.frustum_bottom)
        top = 0.5 * (cam0.frustum_top + cam1.frustum_top)
        if not half:
            half = 0.5 * self._width / self._height * (top - bottom)
        center = 0.5 * (cam0.frustum_center + cam1.frustum_center)
        near = 0.5 * (cam0.frustum_near + cam1.frustum_near)
        far = 0.5 * (cam0.frustum_far + cam1.frustum_far)
        frustum = (center - half, center + half, bottom, top, near, far)
        view = cull_mask(centers, radii, eye, fwd, up, frustum)
        mirror = view.copy()
        if scn.flags[_F.mjRND_REFLECTION]:
            for g in geoms:
                if int(g.type) in (_PLANE, _BOX) and g.reflectance > 0:
                    nrm = np.asarray(g.mat, float).reshape(3, 3)[:, 2]
                    p = np.asarray(g.pos, float)
                    if int(g.type) == _BOX:
                        p = p + g.size[2] * nrm
                    img = centers - 2.0 * ((centers - p) @ nrm)[:, None] * nrm
                    mirror &= cull_mask(img, radii, eye, fwd, up, frustum)
        out_view, out_mirror = none.copy(), none.copy()
        out_view[idx], out_mirror[idx] = view, mirror
        return out_view, out_mirror

    def segmentation(self, data: mujoco.MjData) -> np.ndarray:
        """(H, W, 2) int32: the (object id, object type) seen at each pixel, (-1, -1) where
        none (as ``mujoco.Renderer`` 's segmentation rendering; every geom drawn)."""
        con, scn = self._update(data)
        self._render_segments(con, scn)
        mujoco.mjr_readPixels(self._rgb, None, self._rect, con)
        im = self._rgb[::-1].astype(np.uint32)
        segimage = im[:, :, 0] + im[:, :, 1] * (2**8) + im[:, :, 2] * (2**16)
        lut = np.full((scn.ngeom + 1, 2), -1, dtype=np.int32)  # segid + 1 -> (objid, objtype)
        seen = [g for g in scn.geoms[: scn.ngeom] if g.segid != -1]
        ids = np.array([g.segid + 1 for g in seen], dtype=np.int32)
        lut[ids, 0] = np.array([g.objid for g in seen], dtype=np.int32)
        lut[ids, 1] = np.array([g.objtype for g in seen], dtype=np.int32)
        return lut[segimage]

    def close(self) -> None:
        """Free the MuJoCo and OpenGL contexts (idempotent)."""
        if self._con is not None:
            if self._gl is not None:
                with self._gl.as_current():
                    self._con.free()
            else:
                self._con.free()
            self._con = None
        if self._gl is not None:
            self._gl.free()
            self._gl = None

    def __del__(self) -> None:
        self.close()
