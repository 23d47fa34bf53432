"""Paper 002 algorithms against independent computations: spiral closed form (eq. 1), Kalman
filter (eq. 2-5) by hand and at its Riccati steady state, grid sampling (eq. 6, §2.1.3),
compensation (eq. 7) by finite differences, ruckig timing and Algorithm 2 convergence."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import solve_discrete_are
from scipy.special import erf

from mmpa.core.errors import InvalidInputError, UnreachableError
from mmpa.fiducial_search import (
    ArmLimits,
    ConstantVelocityKF,
    SpiralConfig,
    ToolPointIK,
    compensate,
    grid_samples,
    iterative_plan,
    sample_path,
    segment_durations,
    spiral_points,
    transition,
)
from mmpa.robot.description import default_robot


# --- eq. 1 ------------------------------------------------------------------------------------
def test_spiral_closed_form_per_turn() -> None:
    cfg = SpiralConfig()  # R = 4 cm per turn, phi = pi / 5
    p = spiral_points(20, cfg)
    k = np.arange(1, 21)
    r = np.hypot(p[:, 0], p[:, 1])
    np.testing.assert_allclose(r, 0.04 * k / 10, atol=1e-12)  # 10 samples per turn
    ang = np.arctan2(p[:, 1], p[:, 0])
    np.testing.assert_allclose(np.cos(ang - k * np.pi / 5), 1.0, atol=1e-12)
    np.testing.assert_allclose(p[9], [0.04, 0.0], atol=1e-12)  # one full turn: radius R on +x
    # the paper's "interpoint spacing of approximately 12 mm" over the first turn
    first = np.vstack([[0.0, 0.0], p[:10]])
    spacing = np.linalg.norm(np.diff(first, axis=0), axis=1).mean()
    assert 0.010 < spacing < 0.015


def test_spiral_literal_reading_and_bad_input() -> None:
    p = spiral_points(np.array([0, 5]), SpiralConfig(radius_per="radian"))
    np.testing.assert_allclose(p[0], [0.0, 0.0])
    np.testing.assert_allclose(p[1], [0.04 * np.pi * np.cos(np.pi), 0.0], atol=1e-12)
    with pytest.raises(InvalidInputError):
        spiral_points(-1)
    with pytest.raises(InvalidInputError):
        spiral_points(np.array([1.0, np.nan]))


# --- eq. 2-5 ----------------------------------------------------------------------------------
def test_kalman_one_step_by_hand() -> None:
    # per axis the filter is a 2-state system; compute one step with scalar algebra
    x0 = np.array([1.0, 0.5, -2.0, 0.1])
    p0, pv = 0.04, 0.01
    q_p, q_v, r = 3e-4, 2e-4, 1.8e-4
    kf = ConstantVelocityKF(
        x0, np.diag([p0, pv, p0, pv]), np.array([q_p, q_v, q_p, q_v]), np.array([r, r])
    )
    dt = 2.0
    z = np.array([2.3, -1.7])
    kf.predict(dt)
    kf.update(z)
    for ax, (pos, vel) in enumerate([(1.0, 0.5), (-2.0, 0.1)]):
        xp, vp = pos + dt * vel, vel
        P11 = p0 + dt * dt * pv + q_p
        P12 = dt * pv
        P22 = pv + q_v
        S = P11 + r
        k1, k2 = P11 / S, P12 / S
        e = z[ax] - xp
        np.testing.assert_allclose(kf.x[2 * ax], xp + k1 * e, rtol=1e-12)
        np.testing.assert_allclose(kf.x[2 * ax + 1], vp + k2 * e, rtol=1e-12)
        Pp = np.array([[P11, P12], [P12, P22]])
        Pu = Pp - np.outer([k1, k2], Pp[0])
        np.testing.assert_allclose(kf.P[2 * ax : 2 * ax + 2, 2 * ax : 2 * ax + 2], Pu, rtol=1e-9)
    assert kf.P[0, 2] == 0.0 and kf.P[1, 3] == 0.0  # axes stay decoupled


def test_kalman_steady_state_matches_riccati() -> None:
    q = np.array([3e-4, 2e-4, 3e-4, 2e-4])
    r = 1.8e-4
    kf = ConstantVelocityKF(np.zeros(4), np.eye(4), q, np.array([r, r]))
    rng = np.random.default_rng(0)
    for k in range(1, 200):
        kf.predict(float(k))
        kf.update(rng.normal(0, 0.01, 2))
    A = transition(1.0)[:2, :2]
    C = np.array([[1.0, 0.0]])
    P_pred = solve_discrete_are(A.T, C.T, np.diag(q[:2]), np.array([[r]]))
    K = P_pred @ C.T / (C @ P_pred @ C.T + r)
    P_post = (np.eye(2) - K @ C) @ P_pred
    np.testing.assert_allclose(kf.P[:2, :2], P_post, rtol=1e-6)
    _, P = kf.predicted(200.0)
    np.testing.assert_allclose(P[:2, :2], P_pred, rtol=1e-6)


def test_kalman_learns_a_constant_velocity() -> None:
    kf = ConstantVelocityKF(
        [0.0, 0.02, 0.0, 0.0], np.diag([1e-4, 1e-4, 1e-4, 1e-4]), [1e-8] * 4, [1e-6, 1e-6]
    )
    v = np.array([0.021, -0.0015])
    for t in np.arange(1.0, 60.0, 5.0):
        kf.predict(t)
        kf.update(v * t)
    np.testing.assert_allclose(kf.velocity(), v, atol=2e-5)


def test_kalman_bad_input() -> None:
    with pytest.raises(InvalidInputError, match="positive semi-definite"):
        ConstantVelocityKF(np.zeros(4), np.diag([1, 1, -1, 1.0]), [0] * 4, [1, 1])
    with pytest.raises(InvalidInputError, match="4 finite"):
        ConstantVelocityKF(np.zeros(3), np.eye(4), [0] * 4, [1, 1])
    kf = ConstantVelocityKF(np.zeros(4), np.zeros((4, 4)), [0] * 4, [0, 0])
    with pytest.raises(InvalidInputError, match="singular"):
        kf.update(np.zeros(2))
    with pytest.raises(InvalidInputError):
        ConstantVelocityKF(np.zeros(4), np.eye(4), [0] * 4, [1, 1]).update([np.nan, 0])


# --- eq. 6 + grid -----------------------------------------------------------------------------
def test_grid_samples_ordering_and_probabilities() -> None:
    mean = np.array([0.3, -0.1])
    sigma = 0.012
    gamma = 0.014
    g = grid_samples(mean, sigma**2 * np.eye(2), np.random.default_rng(3), gamma, 20000, 1.0)
    assert np.all(np.diff(g.counts) <= 0)  # most probable first
    np.testing.assert_allclose(g.points[0], mean)  # the grid is anchored at the mean
    idx = (g.points - mean) / gamma
    np.testing.assert_allclose(idx, np.round(idx), atol=1e-9)  # on the grid
    assert g.probability.sum() == pytest.approx(1.0)
    # the centre cell's probability against the Gaussian integral over the cell
    p1 = erf(gamma / 2 / (sigma * math.sqrt(2)))
    expected = p1 * p1
    se = math.sqrt(expected * (1 - expected) / 20000)
    assert abs(g.probability[0] - expected) < 4 * se
    # a mass cut keeps a prefix
    h = grid_samples(mean, sigma**2 * np.eye(2), np.random.default_rng(3), gamma, 20000, 0.9)
    assert 0.9 <= h.probability.sum() < 0.9 + h.probability[-1] + 1e-12
    np.testing.assert_allclose(h.points, g.points[: len(h.points)])


def test_grid_samples_singular_and_invalid_covariance() -> None:
    g = grid_samples([1.0, 2.0], np.zeros((2, 2)), np.random.default_rng(0))
    assert len(g.points) == 1 and g.probability[0] == 1.0
    # rank 1: every cell on the line through the mean along (1, 1)
    g = grid_samples([0.0, 0.0], 1e-4 * np.ones((2, 2)), np.random.default_rng(0))
    np.testing.assert_allclose(g.points[:, 0], g.points[:, 1])
    with pytest.raises(InvalidInputError, match="positive semi-definite"):
        grid_samples([0.0, 0.0], np.diag([1e-4, -1e-4]), np.random.default_rng(0))
    with pytest.raises(InvalidInputError, match="finite"):
        grid_samples([0.0, np.inf], np.eye(2), np.random.default_rng(0))
    with pytest.raises(InvalidInputError, match="gamma"):
        grid_samples([0.0, 0.0], np.eye(2), np.random.default_rng(0), gamma=0.0)


# --- eq. 7 ------------------------------------------------------------------------------------
def test_compensation_finite_differences_and_moving_frame() -> None:
    rng = np.random.default_rng(1)
    s = rng.normal(0, 0.02, (6, 2))
    v = np.array([0.03, -0.01])
    delta = rng.uniform(0.1, 0.5, 6)
    f0 = compensate(s, v, delta)
    h = 1e-6
    for j in range(6):
        d2 = delta.copy()
        d2[j] += h
        J = (compensate(s, v, d2) - f0) / h
        for k in range(6):
            np.testing.assert_allclose(J[k], v if j <= k else 0.0, atol=1e-6)
    # a point fixed in the world, seen from a base moving at v_b: where it is at arrival
    p_world = np.array([1.0, 0.4])
    vb = np.array([0.02, 0.0])
    T = np.cumsum(delta)
    seen = p_world - (vb * T[:, None])  # base at vb * t
    np.testing.assert_allclose(compensate(np.tile(p_world, (6, 1)), -vb, delta), seen)
    with pytest.raises(InvalidInputError):
        compensate(s, v, delta[:3])
    with pytest.raises(InvalidInputError):
        compensate(s, v, -delta)


# --- ruckig + Algorithm 2 ---------------------------------------------------------------------
ROBOT = default_robot()
LIM = ArmLimits.from_description(ROBOT)


def test_ruckig_segment_matches_jerk_limited_closed_form() -> None:
    # rest-to-rest with only the jerk limit active: D = j T^3 / 32
    q0 = np.array(ROBOT.arm.home)
    D = 0.01
    q1 = q0.copy()
    q1[0] += D
    (T,) = segment_durations(q0, q1[None], LIM)
    assert T == pytest.approx((32 * D / LIM.j_max[0]) ** (1 / 3), rel=1e-6)
    # a long move is velocity/acceleration limited: slower than the jerk-only bound
    q2 = q0.copy()
    q2[0] += 2.0
    (T2,) = segment_durations(q0, q2[None], LIM)
    assert T2 > 2.0 / LIM.v_max[0]


def _ik() -> ToolPointIK:
    return ToolPointIK(ROBOT, z_sensor=-0.15, z_pivot=-0.27)


def test_tool_point_ik_round_trip_and_tilt() -> None:
    ik = _ik()
    q_ref = np.array(ROBOT.arm.home)
    for p in ([0.2, 0.35], [-0.1, 0.5], [0.3, 0.3, 0.05, -0.04]):
        q = ik(np.array(p), q_ref)
        np.testing.assert_allclose(ik.beam_point(q, ik.z_pivot), p[:2], atol=1e-9)
        o, d = ik.beam(q)
        assert o[2] == pytest.approx(ik.z_sensor, abs=1e-9)
        tilt = math.acos(-d[2])
        expected = math.acos(math.cos(p[2]) * math.cos(p[3])) if len(p) == 4 else 0.0
        assert tilt == pytest.approx(expected, abs=1e-9)
    assert 0.8 < ik.reach_radius() < 1.0
    with pytest.raises(UnreachableError):
        ik(np.array([1.5, 0.0]), q_ref)


@pytest.mark.parametrize("speed", [0.01, 0.03])
def test_iterative_planning_converges_to_the_fixed_point(speed: float) -> None:
    ik = _ik()
    q0 = ik(np.array([0.1, 0.4]), np.array(ROBOT.arm.home))
    s = np.array([0.1, 0.4]) + spiral_points(15)
    v = np.array([-speed, 0.0])
    plan = iterative_plan(s, v, q0, ik, LIM, n_iter=8)
    assert plan.reachable.all()
    assert np.all(np.diff(plan.rmse) < 0)  # monotone convergence (Fig. 3c)
    assert plan.rmse[-1] < 1e-4 * plan.rmse[0]
    # fixed point of eq. 7: the points are compensated with their own planned times
    np.testing.assert_allclose(compensate(s, v, plan.delta), plan.points, atol=1e-5)
    # and the joint targets put the beam on them
    for q, p in zip(plan.q, plan.points, strict=True):
        np.testing.assert_allclose(ik.beam_point(q, ik.z_pivot), p, atol=1e-9)
    # the sampled path respects the joint limits and the velocity limit
    t, qs, _ = sample_path(q0, plan.q, LIM, 0.002)
    assert np.all(np.diff(t) > 0) and t[-1] == pytest.approx(plan.duration)
    qd = np.abs(np.diff(qs, axis=0)) / np.diff(t)[:, None]
    assert np.all(qd <= LIM.v_max * 1.001)
    assert np.all(qs >= LIM.q_min) and np.all(qs <= LIM.q_max)


def test_planning_standing_base_and_unreachable_points() -> None:
    ik = _ik()
    q0 = ik(np.array([0.1, 0.4]), np.array(ROBOT.arm.home))
    s = np.array([[0.12, 0.4], [2.0, 0.0], [0.1, 0.42]])
    plan = iterative_plan(s, np.zeros(2), q0, ik, LIM, n_iter=3)
    np.testing.assert_allclose(plan.rmse, 0.0, atol=1e-15)
    assert plan.reachable.tolist() == [True, False, True]
    assert len(plan.q) == 2
    with pytest.raises(InvalidInputError):
        iterative_plan(np.zeros((0, 2)), np.zeros(2), q0, ik, LIM)


def test_stochastic_config_rejects_singular_observation_noise() -> None:
    from pydantic import ValidationError

    from mmpa.fiducial_search import StochasticConfig

    with pytest.raises(ValidationError, match="Sigma_vv"):
        StochasticConfig(sigma_vv=(0.0, 1e-4))
    with pytest.raises(ValidationError, match="Sigma_ww"):
        StochasticConfig(sigma_ww=(1e-4, -1.0, 0.0, 0.0))
    # a zero process noise is allowed: the search then collapses onto few cells
    kf = ConstantVelocityKF.from_config(
        [0.0, 0.0], [0.02, 0.0], StochasticConfig(sigma_ww=(0, 0, 0, 0), initial_position_sigma=0)
    )
    mean, cov = kf.position(10.0)
    g = grid_samples(mean, cov, np.random.default_rng(0))
    np.testing.assert_allclose(g.points[0], [0.2, 0.0])
