"""The whole twin, end to end: sensors in the default world agree with its ground truth."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np
import pytest

from mmpa.backends.twin.world import SimWorld
from mmpa.core.geometry import apply, inv
from mmpa.robot.kinematics import fk


@pytest.fixture(scope="module")
def world():
    w = SimWorld(site="1")
    w.arm.move_joints(w.nominal.arm.view_bench)
    yield w
    w.close()


def test_bench_cloud_lands_on_the_desk_top(world):
    """Deproject the noisy depth with the TRUE camera pose: desk-top points sit at its height
    with the spread of the depth noise model (sigma_z = z^2 0.08 / (385 * 0.05))."""
    frame = world.camera.capture()
    cloud = frame.to_point_cloud(min_depth=0.2, max_depth=2.0)
    p_map = apply(world.truth.T_map_camera(), cloud.points)
    bench = world.scene.workbench("site1_bench")
    c, s = np.cos(np.deg2rad(bench.yaw_deg)), np.sin(np.deg2rad(bench.yaw_deg))
    d = p_map[:, :2] - np.array(bench.center)
    u, v = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    top = bench.size[2]
    on_desk = (np.abs(u) < bench.size[0] / 2 - 0.02) & (np.abs(v) < bench.size[1] / 2 - 0.02)
    near_top = on_desk & (np.abs(p_map[:, 2] - top) < 0.02)
    assert near_top.sum() > 20_000  # the camera does look at the bench
    dz = p_map[near_top, 2] - top
    # range to the desk top is ~0.6 m: sigma_z ~ 0.6^2 * 0.08 / 19.25 = 1.5 mm (+ 0.1 % scale)
    rng_m = np.linalg.norm(cloud.points[near_top], axis=1).mean()
    sigma = rng_m**2 * 0.08 / (385.0 * 0.05)
    assert abs(np.median(dz)) < 3 * sigma + 0.001 * rng_m
    assert np.std(dz) < 3 * sigma
    assert np.std(dz) > 0.3 * sigma  # noise is really there


def test_nominal_belief_of_the_camera_is_off_by_the_calibration_error(world):
    """Software's camera pose (nominal FK and hand-eye) vs the truth: millimetres, not zero."""
    q = world.arm.joint_positions()
    nom = world.nominal
    T_map_cam_belief = world.truth.T_map_arm_base() @ fk(nom.arm.dh, q) @ nom.camera.T_flange_camera
    err = np.linalg.norm(T_map_cam_belief[:3, 3] - world.truth.T_map_camera()[:3, 3])
    assert 0.1e-3 < err < 10e-3


def test_lidar_sees_each_visible_reflector_at_its_true_bearing_and_range(world):
    scan = world.lidar.scan()
    assert scan.ranges.shape == (1440,) and scan.angle_increment == pytest.approx(np.deg2rad(0.25))
    T_laser_map = inv(world.truth.T_map_base_link() @ world.nominal.lidar.T_base_link_laser)
    refl = world.truth.reflector_positions()
    radius = world.scene.reflectors.radius
    bright = scan.intensities > 1000.0
    angles = scan.angles
    seen = 0
    for x, y in refl:
        p = apply(T_laser_map, np.array([x, y, 0.22]))  # scan-plane height
        bearing, dist = np.arctan2(p[1], p[0]), np.hypot(p[0], p[1])
        beam = int(np.argmin(np.abs(np.angle(np.exp(1j * (angles - bearing))))))
        if not bright[beam]:
            continue  # occluded from here (a desk leg, the pillar)
        seen += 1
        # the cluster of bright beams around the beam toward the center
        lo, hi = beam, beam
        while bright[(lo - 1) % 1440]:
            lo -= 1
        while bright[(hi + 1) % 1440]:
            hi += 1
        idx = np.arange(lo, hi + 1) % 1440
        center_bearing = np.angle(np.exp(1j * angles[idx]).mean())
        assert abs(np.angle(np.exp(1j * (center_bearing - bearing)))) < np.deg2rad(0.5)
        assert np.min(scan.ranges[idx]) == pytest.approx(dist - radius, abs=4 * 0.015 + 0.005)
    assert seen >= 5  # the lobby's reflectors surround Site 1
