"""The simulated camera's renderer (:mod:`mmpa.backends.twin.sensors.render`) gives the pixels
of ``mujoco.Renderer`` bit for bit: every IPE figure rides on the camera's frames.

The reference is the rendering path the camera had before (one ``mujoco.Renderer``: a colour
render, then a depth render), kept here as :func:`_reference_render`; frames are compared
with ``np.array_equal`` over views of the twin (where the culling skips most of the map's
geoms) and over a scene built to catch a wrong cull: a reflecting floor (a plane, or a box)
showing a box that is outside the view itself, a geom behind the camera, a transparent geom,
a mesh.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from mmpa.backends.twin.error_model import CameraNoise, ErrorModelConfig
from mmpa.backends.twin.noise import (
    color_noise,
    color_session_gain,
    depth_noise,
    session_disparity,
)
from mmpa.backends.twin.sensors import SimCamera
from mmpa.backends.twin.sensors.render import CameraRenderer, cull_mask
from mmpa.backends.twin.world import SimWorld


def _reference_render(r: mujoco.Renderer, data: mujoco.MjData, cam_id: int):
    """The camera's rendering before the CameraRenderer (commit 9b9baa7): colour, depth (m)
    and the (object id, type) segmentation of one ``mujoco.Renderer``."""
    r.update_scene(data, camera=cam_id)
    color = r.render()
    r.enable_depth_rendering()
    depth = r.render()
    r.disable_depth_rendering()
    r.enable_segmentation_rendering()
    seg = r.render()
    r.disable_segmentation_rendering()
    return color, depth, seg


def _assert_same(new: CameraRenderer, old: mujoco.Renderer, data, cam_id: int) -> None:
    color, depth = new.render(data)
    seg = new.segmentation(data)
    ref = _reference_render(old, data, cam_id)
    names = ("color", "depth", "segmentation")
    for name, a, b in zip(names, (color, depth, seg), ref, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape, name
        assert np.array_equal(a, b), f"{name}: {int(np.sum(a != b))} values differ"


def test_cull_mask_closed_form() -> None:
    # eye at the origin looking along +x, up +z: s = f x up = -y; 90 deg field of view
    # both ways (edges at +-0.1 at near 0.1), far 10
    frustum = (-0.1, 0.1, -0.1, 0.1, 0.1, 10.0)
    eye, f, up = np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 0, 1.0])
    # the point (1, 1.2, 0) is (1.2 - 1) / sqrt(2) = 0.1414 m beyond the side plane y = x
    centers = np.array(
        [[1, 0, 0], [-1, 0, 0], [-1, 0, 0], [1, 1.2, 0], [1, 1.2, 0], [1, 0, 1.2], [20, 0, 0]],
        float,
    )
    radii = np.array([0.01, 0.5, 1.2, 0.14, 0.15, 0.14, 10.5])
    got = cull_mask(centers, radii, eye, f, up, frustum)
    # behind: z = -1 < near - r for r = 0.5, not for r = 1.2; far: 20 - 10.5 < 10
    assert got.tolist() == [False, True, False, True, False, True, False]


@pytest.fixture(scope="module")
def twin():
    with SimWorld(errors=ErrorModelConfig(seed=0), site="0") as w:
        yield w


def _views(w: SimWorld):
    arm = w.true_robot.arm
    p0 = np.asarray(w.scene.site("0").pose2d, float)
    qs = [np.array(arm.home), np.array(arm.view_bench)]
    qs.append(qs[1] + [0.3, 0.1, -0.1, 0.2, 0.1, 0.5])  # looking past the desk
    qs.append(qs[1] + [-0.4, 0.3, -0.6, 0.5, 0.3, 0.0])  # at the floor, at a slant
    offsets = ([0, 0, 0], [0.6, -0.3, 0.8], [-1.0, 0.4, 2.5], [0.2, 1.0, -1.6])
    for i, (q, off) in enumerate(zip(qs, offsets, strict=True)):
        w.set_kinematic_state(p0 + off, q)
        yield i


def test_twin_frames_identical_to_mujoco_renderer(twin) -> None:
    w = twin
    cam_id = mujoco.mj_name2id(w.model, mujoco.mjtObj.mjOBJ_CAMERA, "wrist_camera")
    k = w.true_robot.camera.color
    culled = []
    for width, height in ((k.width, k.height), (k.width // 2, k.height // 2)):
        new = CameraRenderer(w.model, width, height, cam_id)
        old = mujoco.Renderer(w.model, height=height, width=width)
        try:
            for i in _views(w):
                w.set_lighting(("normal", "dark", "high", "normal")[i])
                _assert_same(new, old, w.data, cam_id)
                culled.append(new.culled)
        finally:
            w.set_lighting("normal")
            new.close()
            old.close()
    # the comparison covered culling: most of the map is out of view in every frame
    assert min(c for c, _ in culled) > 100 and all(d >= c for c, d in culled)


def test_capture_identical_to_reference_noise(twin) -> None:
    """capture() = the reference render, its far plane masked, then the error model's depth
    and colour noise with the session's fields, from the same generator state."""
    w = twin
    desc, cfg = w.true_robot.camera, CameraNoise()
    shape = (desc.color.height, desc.color.width)
    s_rng = np.random.default_rng(11)
    disparity, gain = session_disparity(shape, s_rng, cfg), color_session_gain(shape, s_rng, cfg)
    cam = SimCamera(w.model, w.data, desc, cfg, np.random.default_rng(5), lambda: 0.0)
    old = mujoco.Renderer(w.model, height=shape[0], width=shape[1])
    rng = np.random.default_rng(5)
    far = np.float32(w.model.vis.map.zfar * w.model.stat.extent * (1.0 - 1e-4))
    try:
        cam.set_session(disparity, gain)
        for i in _views(w):
            frame = cam.capture()
            color, depth, _ = _reference_render(old, w.data, cam._cam_id)
            depth[depth >= far] = 0.0
            d = depth_noise(
                depth,
                rng,
                cfg,
                desc.depth_focal_native,
                desc.baseline,
                desc.min_range,
                desc.max_range,
                fixed_disparity=disparity,
            )
            c = color_noise(color, rng, cfg, gain=gain)
            assert np.array_equal(frame.depth, d) and np.array_equal(frame.color, c), i
    finally:
        cam.close()
        old.close()


def _mirror_scene(floor: str, shadow: bool) -> str:
    """A camera 0.5 m up looking 50 deg down along +x (fovy 45: 27.5-72.5 deg down); a box
    at (2, 0, 2) is 37 deg UP (out of view) but its image in the reflecting floor, at
    (2, 0, -2), is 51 deg down (in view); a sphere behind the camera; a transparent sphere
    beside it; a mesh and a capsule in view. The light casts shadows iff ``shadow``."""
    floor_geom = (
        '<geom name="floor" type="plane" size="5 5 0.1" material="shiny"/>'
        if floor == "plane"
        else '<geom name="floor" type="box" size="5 5 0.05" pos="0 0 -0.05" material="shiny"/>'
    )
    return f"""
<mujoco>
  <visual><global offwidth="160" offheight="120"/><map znear="0.01"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" width="32" height="32"
             rgb1="0.2 0.3 0.4" rgb2="0.8 0.7 0.5"/>
    <material name="shiny" texture="grid" texrepeat="4 4" reflectance="0.5"/>
    <mesh name="tetra" vertex="0 0 0  0.3 0 0  0 0.3 0  0 0 0.3"/>
  </asset>
  <worldbody>
    <light pos="0 0 4" dir="0 0 -1" castshadow="{str(shadow).lower()}"/>
    {floor_geom}
    <geom name="tall" type="box" size="0.2 0.2 0.5" pos="2 0 2" rgba="0.9 0.1 0.1 1"/>
    <geom name="behind" type="sphere" size="0.3" pos="-2 0 0.5" rgba="0.1 0.9 0.1 1"/>
    <geom name="ghost" type="sphere" size="0.2" pos="-1 0 0.5" rgba="0.5 0.5 0.9 0.5"/>
    <geom name="tetra" type="mesh" mesh="tetra" pos="1.2 0.1 0.05" rgba="0.9 0.9 0.1 1"/>
    <geom name="pill" type="capsule" size="0.05 0.4" pos="1.0 -0.5 0.1" euler="0 1.2 0.4"/>
    <camera name="cam" pos="0 0 0.5" xyaxes="0 -1 0 0.766 0 0.643" fovy="45"/>
  </worldbody>
</mujoco>"""


@pytest.mark.parametrize(("floor", "shadow"), [("plane", False), ("box", False), ("plane", True)])
def test_reflected_geom_kept_and_frames_identical(floor: str, shadow: bool) -> None:
    m = mujoco.MjModel.from_xml_string(_mirror_scene(floor, shadow))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    new = CameraRenderer(m, 160, 120, 0)
    old = mujoco.Renderer(m, height=120, width=160)
    try:
        _assert_same(new, old, d, 0)
        # colour: only the sphere behind the camera skipped; depth: the tall box too; with
        # shadows nothing (a geom out of view may cast a shadow into it)
        assert new.culled == ((0, 0) if shadow else (1, 2))
        color, _ = new.render(d)
        scene = _reference_render(old, d, 0)[2]
        tall = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "tall")
        assert not np.any(scene[..., 0] == tall)  # not in view itself...
        red = (color[..., 0] > color[..., 1] + 20) & (color[..., 0] > color[..., 2] + 20)
        assert red.sum() > 20  # ...but its reflection is
    finally:
        new.close()
        old.close()
