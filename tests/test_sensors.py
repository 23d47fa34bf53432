"""Simulated sensors and noise functions against known scenes (MJCF written here, so these
tests do not depend on the world generator)."""

from __future__ import annotations

import math
import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import mujoco
import numpy as np
import pytest

from mmpa.backends.twin.error_model import CameraNoise, ErrorModelConfig, LidarNoise, OdometryNoise
from mmpa.backends.twin.noise import (
    axial_depth_sigma,
    bernoulli_indices,
    color_noise,
    depth_edges,
    depth_noise,
    edge_neighbours,
    odometry_increment_noise,
    range_noise,
    standard_normal_f32,
)
from mmpa.backends.twin.sensors import (
    SimCamera,
    SimLidar,
    SimOdometry,
    SimPhotoSensor,
    T_world_camera_optical,
)
from mmpa.core.errors import InvalidInputError, SimulationError, UnknownNameError
from mmpa.core.geometry import se2_compose, se2_inv
from mmpa.robot.description import (
    BaseDescription,
    CameraDescription,
    LidarDescription,
    PhotoSensorDescription,
)
from mmpa.robot.interfaces import Camera, Lidar, PhotoSensor, deproject

# --------------------------------------------------------------------------------------------
# the test scene

ROOM_X, ROOM_Y = 5.0, 4.0  # inner faces of the walls at x = +-5, y = +-4
REFLECTORS = {0: (3.0, 1.0), 1: (-2.0, -2.5)}
REFLECTOR_R = 0.04
BOX_POS, BOX_HALF, BOX_YAW = np.array([4.55, -0.15, 1.0]), np.array([0.1, 0.12, 0.15]), 0.5
LASER_POS = np.array([0.0, 0.0, 0.3])
TUBE_POS = np.array([-3.0, 2.0])  # on the floor
TUBE_ID, TUBE_H, WALL_T, N_WALLS = 0.0127, 0.0667, 0.001, 24
DISC_R = 0.0063


def _walls() -> str:
    t, h = 0.025, 1.0
    return "\n".join(
        f'<geom name="wall_{i}" type="box" size="{sx} {sy} {h}" pos="{px} {py} {h}" '
        f'rgba="0.8 0.8 0.75 1"/>'
        for i, (sx, sy, px, py) in enumerate(
            [
                (t, ROOM_Y + 2 * t, ROOM_X + t, 0),
                (t, ROOM_Y + 2 * t, -ROOM_X - t, 0),
                (ROOM_X, t, 0, ROOM_Y + t),
                (ROOM_X, t, 0, -ROOM_Y - t),
            ]
        )
    )


def _tube() -> str:
    r = TUBE_ID / 2
    half_len = (r + WALL_T) * math.tan(math.pi / N_WALLS) * 1.05
    out = [
        f'<geom name="fiducial_0_reflector" type="cylinder" size="{DISC_R} 0.0005" '
        f'pos="{TUBE_POS[0]} {TUBE_POS[1]} 0.0005" group="2" rgba="0.9 0.9 0.9 1"/>'
    ]
    for k in range(N_WALLS):
        a = 2 * math.pi * k / N_WALLS
        c = r + WALL_T / 2
        x, y = TUBE_POS[0] + c * math.cos(a), TUBE_POS[1] + c * math.sin(a)
        out.append(
            f'<geom name="fiducial_0_wall_{k}" type="box" '
            f'size="{WALL_T / 2} {half_len} {TUBE_H / 2}" pos="{x} {y} {TUBE_H / 2}" '
            f'euler="0 0 {a}" group="2" rgba="0.2 0.2 0.2 1"/>'
        )
    return "\n".join(out)


def scene_xml(offwidth: int = 640, offheight: int = 480, fovy_deg: float | None = None) -> str:
    fovy = math.degrees(CameraDescription().color.fovy) if fovy_deg is None else fovy_deg
    rx = "\n".join(
        f'<geom name="reflector_{i}" type="cylinder" size="{REFLECTOR_R} 0.5" '
        f'pos="{x} {y} 0.5" group="2" rgba="1 1 1 1"/>'
        for i, (x, y) in REFLECTORS.items()
    )
    return f"""
<mujoco model="sensor_test">
  <compiler angle="radian"/>
  <visual><global offwidth="{offwidth}" offheight="{offheight}"/><map znear="0.005"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" width="64" height="64"
             rgb1="0.2 0.3 0.4" rgb2="0.8 0.7 0.5"/>
    <material name="grid" texture="grid" texrepeat="8 8"/>
  </asset>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1" diffuse="0.8 0.8 0.8"/>
    <geom name="floor" type="plane" size="6 5 0.1" material="grid"/>
    {_walls()}
    {rx}
    {_tube()}
    <body name="target" pos="{BOX_POS[0]} {BOX_POS[1]} {BOX_POS[2]}" euler="0 0 {BOX_YAW}">
      <geom name="target_box" type="box" size="{BOX_HALF[0]} {BOX_HALF[1]} {BOX_HALF[2]}"
            group="1" rgba="0.1 0.5 0.9 1"/>
    </body>
    <body name="base" mocap="true" pos="{LASER_POS[0]} {LASER_POS[1]} 0">
      <geom name="base_collision" type="box" size="0.2 0.2 0.35" pos="0 0 0.3" group="3"/>
      <geom name="base_visual" type="cylinder" size="0.25 0.4" pos="0 0 0.3" group="4"
            contype="0" conaffinity="0"/>
      <site name="laser" pos="0 0 {LASER_POS[2]}"/>
    </body>
    <body name="cam" mocap="true" pos="4 0 1">
      <camera name="wrist_camera" xyaxes="0 -1 0 0 0 1" fovy="{fovy}"/>
    </body>
    <body name="sensor" mocap="true" pos="0 0 2">
      <site name="photosensor"/>
      <geom name="tool" type="box" size="0.03 0.03 0.03" group="3" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
</mujoco>"""


@pytest.fixture(scope="module")
def scene() -> tuple[mujoco.MjModel, mujoco.MjData]:
    m = mujoco.MjModel.from_xml_string(scene_xml())
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return m, d


def _set_mocap(m, d, body: str, pos, R=None) -> None:
    mid = m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, body)]
    d.mocap_pos[mid] = pos
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.asarray(np.eye(3) if R is None else R, dtype=float).reshape(-1))
    d.mocap_quat[mid] = q
    mujoco.mj_forward(m, d)


def _rot(axis: str, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def _clock() -> float:
    return 12.5


# --------------------------------------------------------------------------------------------
# pure noise functions


def test_standard_normal_f32_is_standard_normal() -> None:
    from scipy import stats

    x = standard_normal_f32(np.random.default_rng(0), (301, 333))  # odd count: one pair cut
    assert x.dtype == np.float32 and x.shape == (301, 333)
    f = x.astype(float).ravel()
    assert abs(f.mean()) < 4 / math.sqrt(f.size)
    assert f.std() == pytest.approx(1.0, abs=0.01)
    assert np.mean(f**4) == pytest.approx(3.0, abs=0.06)  # Gaussian kurtosis
    assert stats.kstest(f, "norm").pvalue > 1e-3
    # the two draws of a Box-Muller pair (first / second half) are independent
    n = f.size // 2
    assert abs(np.corrcoef(f[:n], f[n : 2 * n])[0, 1]) < 0.02
    assert abs(np.corrcoef(f[:n] ** 2, f[n : 2 * n] ** 2)[0, 1]) < 0.02
    np.testing.assert_array_equal(x, standard_normal_f32(np.random.default_rng(0), (301, 333)))


@pytest.mark.parametrize("p", [0.0, 0.02, 0.3, 1.0])
def test_bernoulli_indices_is_a_bernoulli_process(p: float) -> None:
    n, reps = 5000, 300
    rng = np.random.default_rng(1)
    draws = [bernoulli_indices(rng, n, p) for _ in range(reps)]
    for idx in draws[:20]:
        assert np.all(np.diff(idx) > 0) and (idx.size == 0 or (idx[0] >= 0 and idx[-1] < n))
    counts = np.array([d.size for d in draws])
    # Binomial(n, p) counts
    assert counts.mean() == pytest.approx(n * p, abs=4 * math.sqrt(n * p * (1 - p) / reps) + 1e-9)
    if 0 < p < 1:
        assert counts.var() == pytest.approx(n * p * (1 - p), rel=0.25)
        # every position equally likely (first and second half, even and odd indices)
        allidx = np.concatenate(draws)
        for sel in (allidx < n // 2, allidx % 2 == 0):
            assert sel.mean() == pytest.approx(0.5, abs=4 * 0.5 / math.sqrt(allidx.size))


def _depth_edges_reference(z: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel loop: the largest jump to a valid 4-neighbour (right, left, down, up first)."""
    h, w = z.shape
    ok = np.isfinite(z) & (z > 0)
    edge = np.zeros((h, w), bool)
    other = np.where(ok, z, 0.0)
    for i in range(h):
        for j in range(w):
            if not ok[i, j]:
                continue
            best = 0.0
            for di, dj in ((0, 1), (0, -1), (1, 0), (-1, 0)):
                a, b = i + di, j + dj
                if 0 <= a < h and 0 <= b < w and ok[a, b] and abs(z[a, b] - z[i, j]) > best:
                    best = abs(z[a, b] - z[i, j])
                    other[i, j] = z[a, b]
            edge[i, j] = best > threshold
    return edge, other


def test_depth_edges_against_a_pixel_loop() -> None:
    rng = np.random.default_rng(4)
    levels = np.array([0.5, 0.6, 1.0, 1.02, 2.0, 0.0, np.nan, np.inf, -1.0])
    for _ in range(5):
        z = rng.choice(levels, size=(17, 23)) + rng.integers(0, 2, (17, 23)) * 0.03
        edge, other = depth_edges(z, 0.05)
        e_ref, o_ref = _depth_edges_reference(z, 0.05)
        np.testing.assert_array_equal(edge, e_ref)
        ok = np.isfinite(z) & (z > 0)
        np.testing.assert_array_equal(other[ok], o_ref[ok])
        _, o32 = depth_edges(z.astype(np.float32), 0.05)  # float32 stays float32
        assert o32.dtype == np.float32


def test_edge_neighbours_is_depth_edges_at_its_edges() -> None:
    """The edge-only search gives depth_edges' edges (ascending flat indices) and, bit for
    bit, its neighbour depths there, ties included (levels repeat), in float32 and float64."""
    rng = np.random.default_rng(7)
    levels = np.array([0.0, 0.5, 0.6, 1.0, 1.02, 2.0])
    for dtype in (np.float32, np.float64):
        for _ in range(20):
            z = (rng.choice(levels, size=(19, 31)) + rng.integers(0, 3, (19, 31)) * 0.03).astype(
                dtype
            )
            z[rng.random(z.shape) < 0.1] = 0.0  # invalid pixels are 0, as depth_noise leaves them
            edge, other = depth_edges(z, 0.05)
            idx, nb = edge_neighbours(z, 0.05)
            np.testing.assert_array_equal(idx, np.flatnonzero(edge))
            assert nb.dtype == z.dtype
            np.testing.assert_array_equal(nb, other.reshape(-1)[idx])


def test_depth_noise_sigma_scale_and_holes() -> None:
    cfg = CameraNoise(correlated_fraction=0.0)  # all of the per-pixel noise per frame
    f, b = 385.0, 0.05
    z = np.full((480, 640), 1.5)
    out = depth_noise(z, np.random.default_rng(1), cfg, f, b, 0.2, 4.0)
    assert out.dtype == np.float32 and out.shape == z.shape
    valid = out > 0
    assert abs((~valid).mean() - cfg.invalid_fraction) < 0.002
    sigma = axial_depth_sigma(1.5, cfg, f, b)
    assert sigma == pytest.approx(1.5**2 * 0.08 / (385 * 0.05))
    assert np.std(out[valid]) == pytest.approx(sigma, rel=0.03)
    # the per-capture scale error: one offset per frame, spread depth_scale_sigma * z
    quiet = cfg.model_copy(update={"subpixel": 0.0, "invalid_fraction": 0.0})
    means = [
        float(depth_noise(z[:4, :4], np.random.default_rng(s), quiet, f, b, 0.2, 4.0).mean())
        for s in range(400)
    ]
    assert np.std(means) == pytest.approx(1.5 * cfg.depth_scale_sigma, rel=0.15)


def test_depth_noise_splits_the_variance_into_frame_and_session_parts() -> None:
    """With ``correlated_fraction`` c, a frame carries sqrt(1 - c) of the disparity noise and
    the fixed field the rest: the total per-pixel SD is the reference formula again, and the
    frame-to-frame difference has SD sqrt(2 (1 - c)) sigma."""
    cfg = CameraNoise(correlated_fraction=0.75, invalid_fraction=0.0, depth_scale_sigma=0.0)
    f, b, zz = 385.0, 0.05, 1.5
    z = np.full((480, 640), zz)
    fixed = np.random.default_rng(5).standard_normal(z.shape).astype(np.float32)
    fixed *= np.float32(np.sqrt(0.75) * cfg.subpixel)
    a = depth_noise(z, np.random.default_rng(1), cfg, f, b, 0.2, 4.0, fixed_disparity=fixed)
    c = depth_noise(z, np.random.default_rng(2), cfg, f, b, 0.2, 4.0, fixed_disparity=fixed)
    sigma = zz**2 * cfg.subpixel / (f * b)
    assert np.std(a) == pytest.approx(sigma, rel=0.03)
    assert np.std(a - c) == pytest.approx(np.sqrt(2 * 0.25) * sigma, rel=0.03)
    # the fixed part: a larger disparity is a nearer point, dz = -z^2 dd / (f b)
    expect = zz - zz**2 * fixed / (f * b)
    assert np.corrcoef((a + c).ravel() / 2, expect.ravel())[0, 1] > 0.9
    with pytest.raises(InvalidInputError):
        depth_noise(z, np.random.default_rng(1), cfg, f, b, 0.2, 4.0, fixed_disparity=fixed[1:])


def test_depth_noise_range_limits_and_invalid_input() -> None:
    cfg = CameraNoise(invalid_fraction=0.0, flying_pixel_fraction=0.0)
    z = np.array([[0.1, 0.5, 3.9, 4.5], [0.0, np.nan, np.inf, -1.0]])
    out = depth_noise(z, np.random.default_rng(0), cfg, 385.0, 0.05, 0.2, 4.0)
    assert out[0, 0] == 0 and out[0, 3] == 0
    assert out[0, 1] > 0 and out[0, 2] > 0
    assert np.all(out[1] == 0)


def test_flying_pixels_only_at_edges() -> None:
    cfg = CameraNoise(subpixel=0.0, invalid_fraction=0.0, depth_scale_sigma=0.0)
    z = np.full((100, 120), 1.0)
    z[:, 60:] = 2.0  # a vertical depth step between columns 59 and 60
    z[40:50, 20:30] = 1.02  # a small bump below the edge threshold
    edge, _ = depth_edges(z, cfg.edge_threshold)
    assert set(np.unique(np.nonzero(edge)[1])) == {59, 60}
    out = depth_noise(z, np.random.default_rng(3), cfg, 385.0, 0.05, 0.2, 4.0)
    moved = np.abs(out - z) > 1e-6
    assert set(np.unique(np.nonzero(moved)[1])) <= {59, 60}
    frac = moved[:, 59:61].mean()
    assert frac == pytest.approx(cfg.flying_pixel_fraction, abs=0.1)
    assert np.all((out[moved] > 1.0) & (out[moved] < 2.0))  # floating between fore and back
    none = depth_noise(
        z, np.random.default_rng(3), cfg.model_copy(update={"flying_pixel_fraction": 0.0}),
        385.0, 0.05, 0.2, 4.0,
    )  # fmt: skip
    np.testing.assert_allclose(none, z, atol=1e-6)


def test_color_noise() -> None:
    img = np.full((200, 300, 3), 128, dtype=np.uint8)
    cfg = CameraNoise()
    out = color_noise(img, np.random.default_rng(0), cfg)
    assert out.dtype == np.uint8 and out.shape == img.shape
    sd = np.std(out.astype(float))
    assert sd == pytest.approx(math.sqrt((255 * cfg.color_sigma) ** 2 + 1 / 12), rel=0.05)
    assert abs(out.mean() - 128) < 0.05
    dark = color_noise(img, np.random.default_rng(0), cfg.model_copy(update={"lighting_gain": 0.5}))
    assert abs(dark.mean() - 64) < 0.1
    white = color_noise(np.full_like(img, 255), np.random.default_rng(0), cfg)
    assert white.max() == 255 and white.mean() > 253
    same = color_noise(img, np.random.default_rng(0), cfg)
    np.testing.assert_array_equal(out, same)


def test_range_noise() -> None:
    r = np.full(20000, 5.0)
    r[:10] = np.inf
    r[10:20] = 25.0
    out = range_noise(r, np.random.default_rng(0), 0.015, 20.0)
    assert np.all(np.isinf(out[:20]))
    assert np.std(out[20:]) == pytest.approx(0.015, rel=0.05)
    assert abs(np.mean(out[20:]) - 5.0) < 0.001


def test_odometry_increment_noise() -> None:
    zero = OdometryNoise(alpha1=0, alpha2=0, alpha3=0, alpha4=0)
    rng = np.random.default_rng(0)
    assert odometry_increment_noise(0.3, 0.5, -0.2, rng, zero) == pytest.approx((0.3, 0.5, -0.2))
    cfg = OdometryNoise()
    s = np.array([odometry_increment_noise(0.0, 1.0, 0.0, rng, cfg) for _ in range(20000)])
    assert np.std(s[:, 0]) == pytest.approx(math.sqrt(cfg.alpha2), rel=0.05)
    assert np.std(s[:, 1]) == pytest.approx(math.sqrt(cfg.alpha3), rel=0.05)
    assert np.std(s[:, 2]) == pytest.approx(math.sqrt(cfg.alpha2), rel=0.05)
    # driving backwards (rot1 = pi) is as noisy as driving forward, not a half turn
    back = np.array(
        [odometry_increment_noise(math.pi, 0.2, -math.pi, rng, cfg) for _ in range(4000)]
    )
    assert np.std(np.cos(back[:, 0])) < 0.01


# --------------------------------------------------------------------------------------------
# camera


def _box_sdf(p: np.ndarray) -> np.ndarray:
    R = _rot("z", BOX_YAW)
    q = np.abs((p - BOX_POS) @ R) - BOX_HALF
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return outside + inside


def _surface_distance(p: np.ndarray) -> np.ndarray:
    """Distance of world points to the nearest true surface in the camera's view."""
    return np.minimum(np.abs(p[:, 0] - ROOM_X), np.abs(_box_sdf(p)))


@pytest.fixture
def camera(scene):
    m, d = scene
    _set_mocap(m, d, "cam", [4.0, 0.0, 1.0])
    # the per-pixel model with no session field: all of its variance drawn per frame
    noise = CameraNoise(correlated_fraction=0.0)
    cam = SimCamera(m, d, CameraDescription(), noise, np.random.default_rng(7), _clock)
    yield cam
    cam.close()


def test_camera_depth_is_axial_and_truth_exact(scene, camera) -> None:
    m, d = scene
    assert isinstance(camera, Camera)
    truth = camera.capture_truth()
    k = camera.intrinsics
    assert truth.intrinsics == CameraDescription().color and truth.stamp == 12.5
    assert truth.color.shape == (480, 640, 3) and truth.depth.dtype == np.float32
    # the left part of the image sees only the wall at 1 m straight ahead: constant depth
    np.testing.assert_allclose(truth.depth[:, :150], 1.0, atol=2e-4)
    T = T_world_camera_optical(m, d, "wrist_camera")
    np.testing.assert_allclose(T, camera.T_world_camera())
    np.testing.assert_allclose(T[:3, 2], [1, 0, 0], atol=1e-12)  # optical z looks along +x
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # optical y down
    pc = deproject(truth.depth, truth.color, k)
    assert len(pc) == 640 * 480
    p = pc.transformed(T, "world").points
    dist = _surface_distance(p)
    assert np.max(dist) < 1e-3
    on_box = np.abs(_box_sdf(p)) < 1e-3
    assert on_box.sum() > 5000  # the target box is in view and lands on its faces
    # the box is blue, the wall is not
    cols = truth.color.reshape(-1, 3).astype(float)
    blue = cols[:, 2] - cols[:, 0]
    assert np.mean(blue[on_box]) > np.mean(blue[~on_box]) + 30


def test_camera_noisy_points_on_true_surfaces(scene, camera) -> None:
    m, d = scene
    truth = camera.capture_truth()
    frame = camera.capture()
    assert frame.color.dtype == np.uint8 and frame.depth.dtype == np.float32
    T = T_world_camera_optical(m, d, "wrist_camera")
    edge, _ = depth_edges(truth.depth, CameraNoise().edge_threshold)
    near_edge = np.zeros_like(edge)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            near_edge |= np.roll(np.roll(edge, dy, 0), dx, 1)
    depth = np.where(near_edge, 0.0, frame.depth)
    pc = deproject(depth, frame.color, frame.intrinsics)
    p = pc.transformed(T, "world").points
    z = pc.points[:, 2]
    cfg, desc = CameraNoise(), CameraDescription()
    sig = axial_depth_sigma(z, cfg, desc.depth_focal_native, desc.baseline)
    # axial error (<= 4 sigma, 1.2 for oblique rays) plus up to 4 sigma of the scale error
    bound = 1.2 * 4 * sig + 4 * cfg.depth_scale_sigma * z
    dist = _surface_distance(p)
    assert np.mean(dist <= bound) > 0.999
    assert np.all(dist <= 1.5 * bound)
    # flying pixels exist, and only near depth edges
    moved = (frame.depth > 0) & (np.abs(frame.depth - truth.depth) > 10 * sig.max())
    assert moved.sum() > 20
    assert np.all(near_edge[moved])


def test_camera_flat_wall_noise_statistics(scene, camera) -> None:
    m, d = scene
    _set_mocap(m, d, "cam", [4.0, -1.5, 1.0])  # only the wall, 1 m ahead
    truth = camera.capture_truth()
    np.testing.assert_allclose(truth.depth, 1.0, atol=2e-4)
    frame = camera.capture()
    invalid = frame.depth == 0
    assert abs(invalid.mean() - 0.02) < 0.003
    res = frame.depth[~invalid].astype(float) - 1.0
    desc = CameraDescription()
    sigma_z = 1.0**2 * 0.08 / (desc.depth_focal_native * desc.baseline)
    assert np.std(res) == pytest.approx(sigma_z, rel=0.3)
    assert abs(np.mean(res)) < 4 * 0.001 + 1e-4  # only the per-capture scale error


def test_camera_set_resolution_same_rays(scene, camera) -> None:
    m, d = scene
    full = camera.capture_truth()
    camera.set_resolution(320, 240)
    assert camera.resolution == (320, 240)
    k = camera.intrinsics
    assert (k.width, k.height, k.fx, k.cx, k.cy) == (320, 240, 307.5, 159.5, 119.5)
    half = camera.capture_truth()
    assert half.color.shape == (240, 320, 3) and half.depth.shape == (240, 320)
    assert half.intrinsics == k
    # every pixel deprojects onto a true surface: the rays are those of the new intrinsics
    T = T_world_camera_optical(m, d, "wrist_camera")
    p = deproject(half.depth, half.color, k).transformed(T, "world").points
    assert np.max(_surface_distance(p)) < 1e-3
    # the same view: where a 2x2 block of the 640x480 depth is smooth, the 320x240 pixel at
    # the block's center sees a depth within the block's range
    blocks = full.depth.reshape(240, 2, 320, 2).astype(float)
    spread = np.ptp(blocks, axis=(1, 3))
    smooth = spread < 0.02
    assert smooth.mean() > 0.95
    dev = np.abs(half.depth - blocks.mean(axis=(1, 3)))
    assert np.all(dev[smooth] <= 0.5 * spread[smooth] + 2e-4)
    noisy = camera.capture()
    assert noisy.depth.shape == (240, 320) and noisy.intrinsics == k
    with pytest.raises(InvalidInputError):
        camera.set_resolution(320, 200)  # another aspect ratio
    camera.set_resolution(640, 480)
    np.testing.assert_array_equal(camera.capture_truth().depth, full.depth)


def test_camera_reproducible(scene) -> None:
    m, d = scene
    _set_mocap(m, d, "cam", [4.0, 0.0, 1.0])
    frames = []
    for seed in (3, 3, 4):
        with SimCamera(
            m, d, CameraDescription(), CameraNoise(), np.random.default_rng(seed), _clock
        ) as cam:
            frames.append(cam.capture())
    np.testing.assert_array_equal(frames[0].depth, frames[1].depth)
    np.testing.assert_array_equal(frames[0].color, frames[1].color)
    assert not np.array_equal(frames[0].depth, frames[2].depth)
    assert not np.array_equal(frames[0].color, frames[2].color)


def test_camera_model_checks() -> None:
    desc, noise, rng = CameraDescription(), CameraNoise(), np.random.default_rng(0)
    small = mujoco.MjModel.from_xml_string(scene_xml(offwidth=320, offheight=240))
    with pytest.raises(SimulationError, match="offwidth"):
        SimCamera(small, mujoco.MjData(small), desc, noise, rng, _clock)
    wrong = mujoco.MjModel.from_xml_string(scene_xml(fovy_deg=60.0))
    with pytest.raises(SimulationError, match="fovy"):
        SimCamera(wrong, mujoco.MjData(wrong), desc, noise, rng, _clock)
    m = mujoco.MjModel.from_xml_string(scene_xml())
    with pytest.raises(UnknownNameError, match="wrist_camera"):
        SimCamera(m, mujoco.MjData(m), desc, noise, rng, _clock, camera="nope")
    cam = SimCamera(m, mujoco.MjData(m), desc, noise, rng, _clock)
    cam.close()
    cam.close()
    with pytest.raises(SimulationError, match="closed"):
        cam.capture()


# --------------------------------------------------------------------------------------------
# lidar


# The single-ray lidar of the reference profile: these tests check its geometry (bearings,
# ranges, fields) exactly; under the realistic default a reflector's edge beams return partial
# intensity and a depth edge mixed ranges (beam width), which tests/test_error_model_lidar.py
# checks against their configured sizes.
REFERENCE_LIDAR = ErrorModelConfig(profile="reference").lidar


def _lidar(m, d, seed=0, **desc) -> SimLidar:
    return SimLidar(
        m, d, LidarDescription(**desc), REFERENCE_LIDAR, np.random.default_rng(seed), _clock
    )


def _clusters(mask: np.ndarray) -> list[np.ndarray]:
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return []
    return np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)


@pytest.mark.parametrize("yaw", [0.0, 0.5])
def test_lidar_reflectors_at_true_bearing_and_range(scene, yaw) -> None:
    m, d = scene
    _set_mocap(m, d, "base", [LASER_POS[0], LASER_POS[1], 0.0], _rot("z", yaw))
    lidar = _lidar(m, d, seed=1)
    assert isinstance(lidar, Lidar)
    scan = lidar.scan()
    bright = scan.intensities > 1000
    clusters = _clusters(bright)
    assert len(clusters) == len(REFLECTORS)
    sigma = LidarNoise().range_sigma
    for x, y in REFLECTORS.values():
        dx, dy = x - LASER_POS[0], y - LASER_POS[1]
        bearing = (math.atan2(dy, dx) - yaw + math.pi) % (2 * math.pi) - math.pi
        match = [c for c in clusters if abs(scan.angles[c].mean() - bearing) < math.radians(2)]
        assert len(match) == 1
        c = match[0]
        assert abs(scan.angles[c].mean() - bearing) < math.radians(0.5)
        assert 3 <= len(c) <= 8  # the cylinder subtends +-0.7 deg at ~3.2 m
        centre = c[np.argmin(np.abs(scan.angles[c] - bearing))]
        assert abs(scan.ranges[centre] - (math.hypot(dx, dy) - REFLECTOR_R)) < 3 * sigma
    # ordinary surfaces are dim
    assert np.all(scan.intensities[~bright] < 300)
    assert np.all(scan.intensities[~bright] > 0)


def test_lidar_walls_fields_and_robot_ignored(scene) -> None:
    m, d = scene
    _set_mocap(m, d, "base", [LASER_POS[0], LASER_POS[1], 0.0])
    lidar = _lidar(m, d, seed=2)
    desc = LidarDescription()
    scan = lidar.scan()
    assert scan.ranges.shape == (desc.num_beams,) == scan.intensities.shape
    assert scan.angle_min == desc.angle_min
    assert scan.angle_max == pytest.approx(math.pi - math.radians(0.25))
    assert scan.scan_time == pytest.approx(0.1)
    assert scan.time_increment == pytest.approx(0.1 / 1440)
    assert scan.stamp == 12.5 and scan.frame_id == "laser"
    # the laser sits inside the robot's collision box (group 3) and visual (group 4): unseen
    assert np.all(np.isfinite(scan.ranges)) and np.min(scan.ranges) > 2.0
    # east wall x = 5: r cos(a) = 5 for the beams that see it
    truth = lidar.scan_truth()
    a = scan.angles
    east = (np.abs(a) < math.radians(35)) & (scan.intensities < 1000)
    east &= np.abs(truth.ranges * np.cos(a) - ROOM_X) < 1e-9
    assert east.sum() > 200
    res = scan.ranges[east] * np.cos(a[east]) - ROOM_X
    sigma = LidarNoise().range_sigma
    assert np.std(res / np.cos(a[east])) == pytest.approx(sigma, rel=0.2)
    i0 = int(np.argmin(np.abs(a)))
    assert abs(scan.ranges[i0] - ROOM_X) < 3 * sigma
    i90 = int(np.argmin(np.abs(a - math.pi / 2)))
    assert abs(truth.ranges[i90] - ROOM_Y) < 1e-9
    # intensity falls with incidence on the same wall
    assert truth.intensities[i0] > truth.intensities[east][np.argmax(np.abs(a[east]))]


def test_lidar_max_range_and_reproducible(scene) -> None:
    m, d = scene
    _set_mocap(m, d, "base", [LASER_POS[0], LASER_POS[1], 0.0])
    scan = _lidar(m, d, range_max=4.5).scan()
    a = scan.angles
    assert np.all(np.isinf(scan.ranges[np.abs(a) < math.radians(5)]))  # wall at 5 m
    assert np.all(scan.intensities[np.isinf(scan.ranges)] == 0)
    north = np.abs(a - math.pi / 2) < math.radians(5)
    assert np.all(np.isfinite(scan.ranges[north]))
    s1, s2, s3 = (_lidar(m, d, seed=s).scan() for s in (5, 5, 6))
    np.testing.assert_array_equal(s1.ranges, s2.ranges)
    assert not np.array_equal(s1.ranges, s3.ranges)


# --------------------------------------------------------------------------------------------
# odometry


def _drive(odo: SimOdometry, poses: np.ndarray, dt: float = 0.05) -> list[np.ndarray]:
    out = []
    for i, p in enumerate(poses):
        odo.update(p, i * dt)
        out.append(odo.odometry().pose)
    return out


def test_odometry_without_noise_follows_true_path() -> None:
    zero = OdometryNoise(alpha1=0, alpha2=0, alpha3=0, alpha4=0)
    t = np.linspace(0, 1, 400)
    arc = np.stack([1.0 + np.sin(2 * t), 2.0 - np.cos(2 * t) + 1.0, 0.3 + 2 * t], 1)
    spin = np.stack([np.full(100, arc[-1, 0]), np.full(100, arc[-1, 1]),
                     arc[-1, 2] + np.linspace(0, -2.5, 100)], 1)  # fmt: skip
    back_dir = spin[-1, 2]
    s = np.linspace(0, -1.2, 100)
    back = np.stack([spin[-1, 0] + s * np.cos(back_dir), spin[-1, 1] + s * np.sin(back_dir),
                     np.full(100, back_dir)], 1)  # fmt: skip
    true = np.concatenate([arc, spin, back])
    odo = SimOdometry(BaseDescription(), zero, np.random.default_rng(0), initial_pose=(0.5, 0, 0))
    got = np.array(_drive(odo, true))
    want = se2_compose(np.array([0.5, 0, 0]), se2_compose(se2_inv(true[0]), true))
    np.testing.assert_allclose(got[:, :2], want[:, :2], atol=1e-9)
    dth = (got[:, 2] - want[:, 2] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(dth, 0, atol=1e-9)
    o = odo.odometry()
    assert o.frame_id == "odom" and o.child_frame_id == "base_link"
    assert o.twist[0] == pytest.approx(-1.2 / 99 / 0.05, rel=1e-6) and abs(o.twist[1]) < 1e-9
    assert o.extra["wheel_left"] == pytest.approx(o.extra["wheel_right"])


def test_odometry_noise_matches_motion_model_variance() -> None:
    cfg = OdometryNoise()
    seg, n_seg, step = 0.25, 6, 0.0125
    xs = np.arange(0, seg * n_seg + step / 2, step)
    true = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], 1)
    finals = []
    for seed in range(1500):
        odo = SimOdometry(BaseDescription(), cfg, np.random.default_rng(seed), segment_length=seg)
        for i, p in enumerate(true):
            odo.update(p, i * 0.02)
        finals.append(odo.odometry().pose)
    f = np.array(finals)
    var_rot = cfg.alpha2 * seg**2  # each of rot1, rot2 per segment
    var_x = n_seg * cfg.alpha3 * seg**2
    var_th = 2 * n_seg * var_rot
    # linearized: y = seg sum_k phi_k, phi_k = sum_{j<k} (e1_j + e2_j) + e1_k
    k = np.arange(1, n_seg + 1)
    var_y = seg**2 * var_rot * float(np.sum(k**2) + np.sum((k - 1) ** 2))
    assert np.var(f[:, 0]) == pytest.approx(var_x, rel=0.25)
    assert np.var(f[:, 2]) == pytest.approx(var_th, rel=0.25)
    assert np.var(f[:, 1]) == pytest.approx(var_y, rel=0.25)
    assert abs(np.mean(f[:, 0]) - seg * n_seg) < 0.03
    a = SimOdometry(BaseDescription(), cfg, np.random.default_rng(3))
    b = SimOdometry(BaseDescription(), cfg, np.random.default_rng(3))
    np.testing.assert_array_equal(_drive(a, true), _drive(b, true))


# --------------------------------------------------------------------------------------------
# photoelectric sensor


TUBE_TOP = np.array([TUBE_POS[0], TUBE_POS[1], TUBE_H])
TUBE_MID = np.array([TUBE_POS[0], TUBE_POS[1], TUBE_H / 2])
DOWN = _rot("x", math.pi)  # sensor +z pointing down


def _aim(m, d, pivot, tilt: float = 0.0, distance: float = 0.2) -> None:
    """Beam through ``pivot`` tilted by ``tilt`` from vertical (towards +x, a wall's face)."""
    R = _rot("y", tilt) @ DOWN
    beam = R[:, 2]
    _set_mocap(m, d, "sensor", np.asarray(pivot) - distance * beam, R)


@pytest.fixture
def photo(scene):
    m, d = scene
    return m, d, SimPhotoSensor(m, d, PhotoSensorDescription())


def test_photosensor_aligned_and_offset(photo) -> None:
    m, d, ps = photo
    assert isinstance(ps, PhotoSensor)
    _aim(m, d, TUBE_TOP)
    assert ps.triggered()
    name, dist = ps.hit()
    assert name == "fiducial_0_reflector"
    assert dist == pytest.approx(0.2 + TUBE_H - 0.001, abs=1e-9)
    _aim(m, d, TUBE_TOP + np.array([0.004, 0.0, 0.0]))
    assert ps.triggered()
    _aim(m, d, TUBE_TOP + np.array([0.0068, 0.0, 0.0]))  # onto the wall's rim
    assert not ps.triggered()
    assert ps.hit()[0].startswith("fiducial_0_wall_")
    _aim(m, d, TUBE_TOP + np.array([0.0, -0.009, 0.0]))  # beside the tube: the floor
    assert not ps.triggered()
    assert ps.hit()[0] == "floor"


def test_photosensor_tilt_acceptance(photo) -> None:
    m, d, ps = photo
    limit = math.atan(TUBE_ID / TUBE_H)
    assert math.degrees(limit) == pytest.approx(10.78, abs=0.01)
    _aim(m, d, TUBE_TOP, tilt=math.radians(3))
    assert ps.triggered()
    for tilt in (3.0, 8.0, 10.3):  # through the tube's centre at mid-height
        _aim(m, d, TUBE_MID, tilt=math.radians(tilt), distance=0.2)
        assert ps.triggered(), tilt
        _aim(m, d, TUBE_MID, tilt=-math.radians(tilt), distance=0.2)
        assert ps.triggered(), -tilt
    for tilt in (11.5, 20.0):
        _aim(m, d, TUBE_MID, tilt=math.radians(tilt), distance=0.2)
        assert not ps.triggered(), tilt
        assert ps.hit()[0].startswith("fiducial_0_wall_")


def test_photosensor_range_and_robot_ignored(photo) -> None:
    m, d, ps = photo
    _aim(m, d, TUBE_TOP, distance=0.4)
    assert ps.triggered()  # the sensor's own tool geom (group 3) is around the beam origin
    _aim(m, d, TUBE_TOP, distance=0.5)
    assert not ps.triggered()  # the reflector is 0.5 + 66 mm away, beyond max_range
    assert ps.hit() == (None, math.inf)
    _set_mocap(m, d, "sensor", [0.0, 0.0, 1.5])  # pointing up into nothing
    assert ps.hit() == (None, math.inf)


def test_mean_frame_averages_the_valid_depths_and_the_colors() -> None:
    """Against a per-pixel loop: depth the mean of the valid captures (> 0, finite), 0 where
    fewer than half are valid; color the rounded mean; the stamp the last capture's."""
    from mmpa.robot.description import CameraIntrinsics
    from mmpa.robot.interfaces import RGBDFrame, mean_frame

    k = CameraIntrinsics(width=4, height=3, fx=5.0, fy=5.0, cx=1.5, cy=1.0)
    rng = np.random.default_rng(2)
    frames = []
    for i in range(5):
        d = rng.uniform(0.3, 2.0, (3, 4)).astype(np.float32)
        d.flat[rng.choice(12, 4, replace=False)] = [0.0, np.nan, np.inf, -1.0]
        c = rng.integers(0, 256, (3, 4, 3), dtype=np.uint8)
        frames.append(RGBDFrame(c, d, k, float(i)))
    m = mean_frame(frames)
    for v in range(3):
        for u in range(4):
            good = [float(f.depth[v, u]) for f in frames if 0 < f.depth[v, u] < np.inf]
            want = sum(good) / len(good) if 2 * len(good) >= 5 else 0.0
            assert m.depth[v, u] == pytest.approx(want, rel=1e-6)
            for ch in range(3):
                mean_c = sum(int(f.color[v, u, ch]) for f in frames) / 5
                assert m.color[v, u, ch] == int(np.rint(mean_c))
    assert m.stamp == 4.0 and m.depth.dtype == np.float32 and m.color.dtype == np.uint8
