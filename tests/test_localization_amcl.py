"""AMCL and the enhanced AMCL against closed forms and the twin's ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.errors import InvalidInputError, UnknownNameError
from mmpa.localization.amcl import AMCL, AMCLConfig, odometry_delta, sample_motion
from mmpa.localization.enhanced import EnhancedAMCL, orientation_weight, position_weight
from mmpa.localization.localizer import Localizer, make_localizer
from mmpa.navigation.mission import laser_pose2d, twin_map
from mmpa.sim.world import SimWorld


@pytest.fixture(scope="module")
def world():
    with SimWorld(site="1") as w:
        yield w


@pytest.fixture(scope="module")
def grid(world):
    return twin_map(world)


def test_motion_model_moments() -> None:
    rng = np.random.default_rng(0)
    P = np.zeros((200_000, 3))
    delta = odometry_delta(np.zeros(3), np.array([1.0, 0.0, 0.0]))
    assert delta == pytest.approx((0.0, 1.0, 0.0))
    out = sample_motion(P, delta, (0.1, 0.2, 0.3, 0.4), rng)
    # rot1 ~ N(0, alpha2): E[x] = E[t] E[cos rot1] = exp(-alpha2 / 2); final heading
    # rot1 + rot2 has variance 2 alpha2; E[t] = 1 with sd sqrt(alpha3)
    assert out[:, 0].mean() == pytest.approx(np.exp(-0.1), abs=5e-3)
    assert out[:, 2].std() == pytest.approx(np.sqrt(0.4), rel=0.03)
    t = out[:, 0] / np.cos(out[:, 2] - (out[:, 2] - np.arctan2(out[:, 1], out[:, 0])))
    assert np.std(np.hypot(out[:, 0], out[:, 1]) * np.sign(t)) == pytest.approx(
        np.sqrt(0.3), rel=0.05
    )


def test_eq3_eq4_closed_form() -> None:
    mu = np.array([1.0, 2.0, 0.1])
    P = np.array([[1.0, 2.0, 0.1], [2.0, 2.0, 0.1], [1.5, 2.5, 0.1]])
    d = position_weight(P, mu)
    assert d[0] == pytest.approx((2 * np.pi) ** -1.5)
    assert d[1] == pytest.approx((2 * np.pi) ** -1.5 * np.exp(-0.5))
    L = np.array([[3.0, 2.0], [1.0, 5.0]])
    phi = np.array([-0.1, np.pi / 2 - 0.1])  # exact bearings from particle 0
    s = orientation_weight(P, L, phi, 0.01)
    assert s[0] == pytest.approx(1 / (0.01 * np.sqrt(2 * np.pi)))
    assert s[2] < 1e-3 * s[0]


def test_likelihood_field_peaks_at_truth(world, grid) -> None:
    amcl = AMCL(grid, laser_pose2d(world), rng=np.random.default_rng(1))
    truth = world.truth.base_pose2d()
    scan = world.lidar.scan()
    offs = np.array([[0, 0, 0], [0.3, 0, 0], [0, -0.3, 0], [0, 0, 0.2]], float)
    p = amcl.measurement_weights(truth + offs, scan)
    assert np.argmax(p) == 0 and p[0] > 1.5 * p[1:].max()
    beam = AMCL(grid, laser_pose2d(world), AMCLConfig(laser_model_type="beam", max_beams=30))
    pb = beam.measurement_weights(truth + offs, scan)
    assert np.argmax(pb) == 0


def test_kld_shrinks_a_converged_cloud(world, grid) -> None:
    amcl = AMCL(grid, laser_pose2d(world), rng=np.random.default_rng(2))
    amcl.set_initial_pose(world.truth.base_pose2d(), np.diag([0.04, 0.04, 0.01]))
    amcl.resample()  # a few KLD bins need far fewer than min_particles: clamped
    assert len(amcl.particles) == amcl.cfg.min_particles
    amcl.global_localization()
    amcl.resample()
    assert len(amcl.particles) == amcl.cfg.max_particles


def _drive(world, locs, v, w, seconds, rate=5.0):
    for _ in range(int(seconds * rate)):
        world.base.set_velocity(v, w)
        world.step(1.0 / rate)
        odom = world.odometry.odometry().pose
        scan = world.lidar.scan()
        for loc in locs:
            loc.update(odom, scan)
    world.base.stop()


def test_amcl_and_enhanced_track_the_truth(world, grid) -> None:
    world.reset("1")
    lp = laser_pose2d(world)
    t0 = world.truth.base_pose2d()
    guess = t0 + np.array([0.15, -0.1, 0.05])
    amcl = make_localizer("amcl", grid, lp, np.random.default_rng(3))
    enh = make_localizer("enhanced", grid, lp, np.random.default_rng(3))
    assert isinstance(amcl, Localizer) and isinstance(enh, EnhancedAMCL)
    for loc in (amcl, enh):
        loc.initialize(guess)
    _drive(world, [amcl, enh], 0.3, 0.2, 4.0)
    _drive(world, [amcl, enh], 0.0, 0.0, 2.0)
    truth = world.truth.base_pose2d()
    odom = world.odometry.odometry().pose
    e_amcl = np.hypot(*(amcl.pose_at(odom)[:2] - truth[:2]))
    e_enh = np.hypot(*(enh.pose_at(odom)[:2] - truth[:2]))
    assert e_amcl < 0.15  # Nav2 defaults: centimetres
    assert e_enh < 0.006  # reflectors: millimetres
    assert abs(enh.pose_at(odom)[2] - truth[2]) < 0.005
    assert enh.last_fix is not None and len(enh.last_fix.ids) >= 7


def test_enhanced_falls_back_without_reflectors(world, grid) -> None:
    world.reset("1")
    enh = make_localizer("enhanced", grid, laser_pose2d(world), np.random.default_rng(4))
    enh.initialize(world.truth.base_pose2d())
    # people in front of every reflector: no fix, plain AMCL, still close
    eye = world.truth.base_pose2d()[:2]
    u = (eye - world.map_reflectors) / np.linalg.norm(eye - world.map_reflectors, axis=1)[:, None]
    world.lidar.occluders = [
        (*(p + 0.3 * e), 0.15) for p, e in zip(world.map_reflectors, u, strict=False)
    ]
    try:
        est = enh.update(world.odometry.odometry().pose, world.lidar.scan(), force=True)
    finally:
        world.lidar.occluders = []
    assert enh.last_fix is None and est.source == "amcl"
    assert np.hypot(*(est.pose[:2] - world.truth.base_pose2d()[:2])) < 0.3


def test_enhanced_recovers_from_kidnapping(world, grid) -> None:
    world.reset("1")
    enh = make_localizer("enhanced", grid, laser_pose2d(world), np.random.default_rng(5))
    enh.initialize(world.scene.site("2").pose2d)  # told the wrong place
    for _ in range(5):
        enh.update(world.odometry.odometry().pose, world.lidar.scan())
    e = enh.pose_at(world.odometry.odometry().pose) - world.truth.base_pose2d()
    assert np.hypot(e[0], e[1]) < 0.01


def test_bad_input(world, grid) -> None:
    amcl = AMCL(grid, laser_pose2d(world))
    with pytest.raises(InvalidInputError, match="initial pose"):
        amcl.update(np.zeros(3), world.lidar.scan())
    with pytest.raises(InvalidInputError):
        amcl.set_initial_pose(np.array([np.nan, 0, 0]))
    with pytest.raises(UnknownNameError):
        make_localizer("gps", grid, laser_pose2d(world))
