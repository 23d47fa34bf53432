"""Tests of mmpa.robot.kinematics: FK (hand checks + independent product of exponentials),
Jacobian (finite differences), analytic UR IK (round trips, all branches), perturbed-DH IK
refinement, nearest-solution selection and manipulability."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from mmpa.core.errors import InvalidInputError, UnreachableError
from mmpa.robot import kinematics as K  # noqa: N812  (K as in the papers' notation)
from mmpa.robot.description import ArmDescription, DHParameters

DH = DHParameters()  # nominal UR5e
D1, A2, A3, D4, D5, D6 = 0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996
Q_MIN, Q_MAX = ArmDescription().q_limits
T_FLANGE_TCP = np.array(
    [[1.0, 0.0, 0.0, 0.01], [0.0, 1.0, 0.0, -0.02], [0.0, 0.0, 1.0, 0.16], [0.0, 0.0, 0.0, 1.0]]
)


def _wrap(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


def _rot_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.linalg.norm(Rotation.from_matrix(Ra @ Rb.T).as_rotvec()))


def _perturbed_dh(seed: int) -> DHParameters:
    """DESIGN.md arm error model: N(0, 0.2 mm) on a, d; N(0, 0.02 deg) on alpha, offsets."""
    rng = np.random.default_rng(seed)
    s_ang = np.deg2rad(0.02)
    return DHParameters(
        a=tuple(np.array(DH.a) + rng.normal(0, 2e-4, 6)),
        d=tuple(np.array(DH.d) + rng.normal(0, 2e-4, 6)),
        alpha=tuple(np.array(DH.alpha) + rng.normal(0, s_ang, 6)),
        theta_offset=tuple(rng.normal(0, s_ang, 6)),
    )


def _well_conditioned_q(rng: np.random.Generator, n: int) -> np.ndarray:
    """Random q away from the wrist (q5), elbow (q3) and shoulder singularities."""
    out = []
    while len(out) < n:
        q = rng.uniform(-np.pi, np.pi, 6)
        if abs(np.sin(q[4])) < 0.1 or abs(np.sin(q[2])) < 0.1:
            continue
        p5 = K.fk(DH, q)[:3, 3] - D6 * K.fk(DH, q)[:3, 2]
        if np.hypot(p5[0], p5[1]) < D4 + 0.05:
            continue
        out.append(q)
    return np.array(out)


# --- independent FK: product of exponentials from the UR5e geometry ---------------------------
# Screw axes at q = 0, read off the arm's zero pose (all links stretched along -x, see
# test_fk_zero_configuration): joint axis direction w and a point r on it, in arm_base.
_POE_AXES = [
    ((0, 0, 1), (0, 0, 0)),  # base: vertical through the origin
    ((0, -1, 0), (0, 0, D1)),  # shoulder
    ((0, -1, 0), (A2, 0, D1)),  # elbow
    ((0, -1, 0), (A2 + A3, 0, D1)),  # wrist 1
    ((0, 0, -1), (A2 + A3, -D4, D1)),  # wrist 2: points down
    ((0, -1, 0), (A2 + A3, -D4, D1 - D5)),  # wrist 3
]
# Flange at q = 0: x_flange = x_base, y_flange = z_base, z_flange = -y_base.
_POE_M = np.array(
    [
        [1.0, 0.0, 0.0, A2 + A3],
        [0.0, 0.0, -1.0, -(D4 + D6)],
        [0.0, 1.0, 0.0, D1 - D5],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def _fk_poe(q: np.ndarray) -> np.ndarray:
    """T(q) = exp([S1] q1) ... exp([S6] q6) M (Lynch & Park, space form), via scipy expm."""
    T = np.eye(4)
    for (w, r), qi in zip(_POE_AXES, q, strict=True):
        w, r = np.array(w, float), np.array(r, float)
        v = -np.cross(w, r)
        S = np.zeros((4, 4))
        S[:3, :3] = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        S[:3, 3] = v
        T = T @ expm(S * qi)
    return T @ _POE_M


# --- FK -------------------------------------------------------------------------------------


def test_fk_zero_configuration() -> None:
    # By hand, q = 0: A1 lifts by d1 and turns z_1 to -y_base; a2, a3 run along x; d4 runs
    # along z_3 = -y; alpha4 = pi/2 turns z_4 to -z_base, so d5 goes down; alpha5 = -pi/2
    # turns z_5 back to -y, so d6 goes along -y.
    #   x = a2 + a3 = -0.8172, y = -(d4 + d6) = -0.2329, z = d1 - d5 = 0.0628
    T = K.fk(DH, np.zeros(6))
    np.testing.assert_allclose(T[:3, 3], [-0.8172, -0.2329, 0.0628], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


def test_fk_hand_checks() -> None:
    # q1 = pi/2 turns the whole zero pose about z: (x, y) -> (-y, x)
    T = K.fk(DH, [np.pi / 2, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(T[:3, 3], [0.2329, -0.8172, 0.0628], atol=1e-12)
    # q2 = -pi/2 turns everything behind the shoulder by +pi/2 about +y_base (joint 2 axis is
    # -y_base, through (0, 0, d1)); the zero-pose flange offset from the shoulder
    # (a2 + a3, -(d4 + d6), -d5) becomes (-d5, -(d4 + d6), -(a2 + a3)): arm straight up.
    T = K.fk(DH, [0, -np.pi / 2, 0, 0, 0, 0])
    np.testing.assert_allclose(T[:3, 3], [-D5, -(D4 + D6), D1 - A2 - A3], atol=1e-12)
    # q3 = pi/2 turns the forearm by -pi/2 about +y_base around the elbow (a2, 0, d1):
    # offset (a3, -(d4 + d6), -d5) becomes (d5, -(d4 + d6), a3): forearm hangs down.
    T = K.fk(DH, [0, 0, np.pi / 2, 0, 0, 0])
    np.testing.assert_allclose(T[:3, 3], [A2 + D5, -(D4 + D6), D1 + A3], atol=1e-12)


def test_fk_matches_independent_poe() -> None:
    rng = np.random.default_rng(0)
    for q in rng.uniform(-2 * np.pi, 2 * np.pi, (100, 6)):
        np.testing.assert_allclose(K.fk(DH, q), _fk_poe(q), atol=1e-12)


def test_fk_batched_and_tool_point() -> None:
    rng = np.random.default_rng(1)
    Q = rng.uniform(-np.pi, np.pi, (7, 6))
    Tb = K.fk(DH, Q)
    assert Tb.shape == (7, 4, 4)
    for q, T in zip(Q, Tb, strict=True):
        np.testing.assert_allclose(T, K.fk(DH, q), atol=1e-15)
        np.testing.assert_allclose(K.fk(DH, q, T_FLANGE_TCP), T @ T_FLANGE_TCP, atol=1e-15)
    F = K.link_transforms(DH, Q)
    assert F.shape == (7, 7, 4, 4)
    np.testing.assert_allclose(F[:, 0], np.broadcast_to(np.eye(4), (7, 4, 4)))
    np.testing.assert_allclose(F[:, 6], Tb, atol=1e-15)
    # each link in its parent's frame: the step between consecutive link frames
    A = K.link_steps(DH, Q)
    assert A.shape == (7, 6, 4, 4)
    for i in range(6):
        np.testing.assert_allclose(A[:, i], np.linalg.inv(F[:, i]) @ F[:, i + 1], atol=1e-12)


def test_fk_theta_offset_shifts_joint() -> None:
    off = (0.1, -0.2, 0.3, 0.0, 0.5, -0.6)
    dh = DHParameters(theta_offset=off)
    q = np.random.default_rng(2).uniform(-np.pi, np.pi, 6)
    np.testing.assert_allclose(K.fk(dh, q), K.fk(DH, q + np.array(off)), atol=1e-14)


def test_fk_rejects_bad_input() -> None:
    with pytest.raises(InvalidInputError):
        K.fk(DH, np.zeros(5))
    with pytest.raises(InvalidInputError):
        K.fk(DH, [0, 0, np.nan, 0, 0, 0])
    with pytest.raises(InvalidInputError):
        K.ik(DH, np.eye(3))


# --- Jacobian -------------------------------------------------------------------------------


@pytest.mark.parametrize("tool", [None, T_FLANGE_TCP])
def test_jacobian_matches_finite_differences(tool) -> None:
    rng = np.random.default_rng(3)
    h = 1e-6
    for q in rng.uniform(-np.pi, np.pi, (20, 6)):
        J = K.jacobian(DH, q, tool)
        assert J.shape == (6, 6)
        J_fd = np.zeros((6, 6))
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = h
            Tp, Tm = K.fk(DH, q + dq, tool), K.fk(DH, q - dq, tool)
            J_fd[:3, i] = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
            # angular velocity in arm_base: log(R(q + dq) R(q - dq)^T) / (2 h)
            J_fd[3:, i] = Rotation.from_matrix(Tp[:3, :3] @ Tm[:3, :3].T).as_rotvec() / (2 * h)
        np.testing.assert_allclose(J, J_fd, atol=1e-8)


def test_jacobian_tcp_is_shifted_flange_jacobian() -> None:
    # v_tcp = v_flange + w x (p_tcp - p_flange)
    q = np.array([0.3, -1.2, 1.4, -0.8, 1.1, 0.4])
    J, Jt = K.jacobian(DH, q), K.jacobian(DH, q, T_FLANGE_TCP)
    r = K.fk(DH, q, T_FLANGE_TCP)[:3, 3] - K.fk(DH, q)[:3, 3]
    np.testing.assert_allclose(Jt[3:], J[3:])
    np.testing.assert_allclose(Jt[:3], J[:3] + np.cross(J[3:].T, r).T, atol=1e-14)
    Qb = np.stack([q, -q])
    np.testing.assert_allclose(K.jacobian(DH, Qb)[1], K.jacobian(DH, -q), atol=1e-15)


# --- IK, nominal DH (exact closed form) -------------------------------------------------------


def test_ik_round_trip_200_random_poses() -> None:
    rng = np.random.default_rng(4)
    n_sol = []
    for q in rng.uniform(-np.pi, np.pi, (200, 6)):
        T = K.fk(DH, q)
        Q = K.ik(DH, T)
        assert 1 <= len(Q) <= 8
        assert np.all(np.isfinite(Q))
        assert np.all(Q >= -np.pi) and np.all(Q < np.pi)
        n_sol.append(len(Q))
        for s in Q:
            Ts = K.fk(DH, s)
            assert np.linalg.norm(Ts[:3, 3] - T[:3, 3]) < 1e-9
            assert _rot_angle(Ts[:3, :3], T[:3, :3]) < 1e-9
        # the configuration that generated the pose is one of the solutions (mod 2 pi)
        assert np.min(np.max(np.abs(_wrap(Q - q)), axis=1)) < 1e-7
    assert max(n_sol) == 8  # all 8 branches show up for generic poses


def test_ik_solutions_are_distinct_branches() -> None:
    q = np.array([0.4, -1.1, 1.3, -1.5, 1.2, 0.3])
    Q = K.ik(DH, K.fk(DH, q))
    assert len(Q) == 8
    d = np.abs(_wrap(Q[:, None, :] - Q[None, :, :])).max(axis=2) + np.eye(8)
    assert d.min() > 1e-3
    # shoulder left/right x wrist flip x elbow up/down
    assert len(np.unique(np.round(Q[:, 0], 6))) == 2
    assert np.sum(Q[:, 4] > 0) == 4
    assert np.sum(Q[:, 2] > 0) == 4


def test_ik_with_theta_offsets_and_tool() -> None:
    off = (0.1, -0.2, 0.3, -0.05, 0.5, -0.6)
    dh = DHParameters(theta_offset=off)
    assert K.is_ur_structure(dh)
    rng = np.random.default_rng(5)
    for q in rng.uniform(-np.pi, np.pi, (30, 6)):
        T_tcp = K.fk(dh, q, T_FLANGE_TCP)
        Q = K.ik(dh, T_tcp, T_flange_point=T_FLANGE_TCP)
        assert len(Q) >= 1
        for s in Q:
            np.testing.assert_allclose(K.fk(dh, s, T_FLANGE_TCP), T_tcp, atol=1e-10)
        assert np.min(np.max(np.abs(_wrap(Q - q)), axis=1)) < 1e-7


@pytest.mark.parametrize(
    "q",
    [
        [0.3, -1.0, 1.2, 0.5, 0.0, 0.7],  # wrist singular: q5 = 0
        [0.3, -1.0, 1.2, 0.5, 1e-13, 0.7],
        [0.3, -1.0, 1.2, 0.5, 1e-9, 0.7],  # nearly singular: still exact
        [0.3, -1.0, 1.2, 0.5, np.pi, 0.7],
        [0.3, -1.0, 0.0, 0.5, 0.8, 0.7],  # elbow straight
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],  # elbow straight and wrist singular
    ],
)
def test_ik_singular_configurations_no_nan(q) -> None:
    q = np.array(q)
    T = K.fk(DH, q)
    Q = K.ik(DH, T, q6_singular=0.25)
    assert len(Q) >= 1
    assert np.all(np.isfinite(Q))
    for s in Q:
        Ts = K.fk(DH, s)
        assert np.linalg.norm(Ts[:3, 3] - T[:3, 3]) < 1e-9
        assert _rot_angle(Ts[:3, :3], T[:3, :3]) < 1e-9
    if abs(np.sin(q[4])) < 1e-12:  # q6 is free on the singular branch: requested value used
        singular = np.abs(np.sin(Q[:, 4])) < 1e-12
        assert singular.sum() >= 1
        np.testing.assert_allclose(Q[singular, 5], 0.25)


def test_ik_unreachable_is_empty() -> None:
    T = K.fk(DH, np.zeros(6))
    T[:3, 3] = [2.0, 0.5, 0.3]
    Q = K.ik(DH, T)
    assert Q.shape == (0, 6)
    # inside the shoulder-offset cylinder around the base axis
    T[:3, 3] = [0.0, 0.0, 0.4]
    T[:3, :3] = np.eye(3)
    assert K.ik(DH, T).shape == (0, 6)


def test_ik_expand_limits() -> None:
    q = np.array([0.4, -1.1, 1.3, -1.5, 1.2, 0.3])
    T = K.fk(DH, q)
    Q = K.ik(DH, T)
    Qx = K.ik(DH, T, expand_limits=(Q_MIN, Q_MAX))
    # UR5e: +-2 pi on joints 1, 2, 4, 5, 6 -> 2 variants each, +-pi on joint 3 -> 1 variant
    assert len(Qx) == 32 * len(Q)
    assert np.all(Qx >= Q_MIN) and np.all(Qx <= Q_MAX)
    for s in Qx[::7]:
        np.testing.assert_allclose(K.fk(DH, s), T, atol=1e-12)
    # tight limits around q keep exactly one variant of one solution
    Qt = K.ik(DH, T, expand_limits=(q - 0.1, q + 0.1))
    assert len(Qt) == 1
    np.testing.assert_allclose(Qt[0], q, atol=1e-9)


# --- IK, perturbed DH (refinement) ------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1])
def test_ik_perturbed_dh_refines_to_1e9(seed) -> None:
    dh_true = _perturbed_dh(seed)
    assert not K.is_ur_structure(dh_true)
    rng = np.random.default_rng(100 + seed)
    for q in _well_conditioned_q(rng, 25):
        T = K.fk(dh_true, q)
        # the closed form alone (structure assumed) is off by ~0.1 mm, not 1e-9
        Q0 = K.ik(dh_true, T, refine=False)
        err0 = min(np.linalg.norm(K.fk(dh_true, s)[:3, 3] - T[:3, 3]) for s in Q0)
        assert err0 > 1e-7
        Q = K.ik(dh_true, T)  # auto: refines on the full DH model
        assert len(Q) >= 1
        for s in Q:
            Ts = K.fk(dh_true, s)
            assert np.linalg.norm(Ts[:3, 3] - T[:3, 3]) < 1e-9
            assert _rot_angle(Ts[:3, :3], T[:3, :3]) < 1e-9
        assert np.min(np.max(np.abs(_wrap(Q - q)), axis=1)) < 1e-7


def test_ik_refine_from_nominal_seed() -> None:
    # the twin's software solves with nominal DH; ik_refine polishes it for the true arm
    dh_true = _perturbed_dh(7)
    rng = np.random.default_rng(8)
    for q in _well_conditioned_q(rng, 20):
        T = K.fk(dh_true, q)
        Q_nom = K.ik(DH, T)
        seed = Q_nom[np.argmin(np.max(np.abs(_wrap(Q_nom - q)), axis=1))]
        assert np.max(np.abs(_wrap(seed - q))) > 1e-6  # nominal answer is not exact
        q_ref = K.ik_refine(dh_true, T, seed)
        Ts = K.fk(dh_true, q_ref)
        assert np.linalg.norm(Ts[:3, 3] - T[:3, 3]) < 1e-9
        assert _rot_angle(Ts[:3, :3], T[:3, :3]) < 1e-9
        np.testing.assert_allclose(_wrap(q_ref - q), 0.0, atol=1e-7)


def test_ik_refine_raises_when_unreachable() -> None:
    T = K.fk(DH, np.zeros(6))
    T[:3, 3] = [2.0, 0.0, 0.0]
    with pytest.raises(UnreachableError, match="did not converge"):
        K.ik_refine(DH, T, np.zeros(6), max_iter=20)


# --- ik_nearest -------------------------------------------------------------------------------


def test_ik_nearest_returns_reference_when_it_is_a_solution() -> None:
    rng = np.random.default_rng(9)
    for q in rng.uniform(Q_MIN, Q_MAX, (30, 6)):
        q_sol = K.ik_nearest(DH, K.fk(DH, q), q, Q_MIN, Q_MAX)
        np.testing.assert_allclose(q_sol, q, atol=1e-7)  # not wrapped: q itself


def test_ik_nearest_wrist_singular_keeps_q6() -> None:
    q = np.array([0.2, -1.3, 1.5, -1.0, 0.0, 4.0])  # q5 = 0, q6 beyond pi
    q_sol = K.ik_nearest(DH, K.fk(DH, q), q, Q_MIN, Q_MAX)
    np.testing.assert_allclose(q_sol, q, atol=1e-9)


def test_ik_nearest_respects_joint_limits() -> None:
    q = np.array([0.4, -1.1, 1.3, -1.5, 1.2, 0.3])
    T = K.fk(DH, q)
    # exclude the generating elbow-up solution by limiting q3 to negative values
    lo, hi = Q_MIN.copy(), Q_MAX.copy()
    hi[2] = -0.1
    q_sol = K.ik_nearest(DH, T, q, lo, hi)
    assert np.all(q_sol >= lo) and np.all(q_sol <= hi)
    assert q_sol[2] < 0
    np.testing.assert_allclose(K.fk(DH, q_sol), T, atol=1e-12)
    # it is the nearest of the allowed solutions (all +-2 pi variants considered)
    Qx = K.ik(DH, T, expand_limits=(lo, hi))
    assert np.linalg.norm(q_sol - q) == pytest.approx(np.min(np.linalg.norm(Qx - q, axis=1)))


def test_ik_nearest_picks_2pi_variant_near_reference() -> None:
    q = np.array([0.4, -1.1, 1.3, -1.5, 1.2, 0.3])
    q_ref = q + np.array([-2 * np.pi, 2 * np.pi, 0, 2 * np.pi, 0, -2 * np.pi]) + 0.05
    q_sol = K.ik_nearest(DH, K.fk(DH, q), q_ref, Q_MIN, Q_MAX)
    np.testing.assert_allclose(q_sol, q_ref - 0.05, atol=1e-9)


def test_ik_nearest_weights_change_the_choice() -> None:
    q = np.array([0.4, -1.1, 1.3, -1.5, 1.2, 0.3])
    T = K.fk(DH, q)
    Q = K.ik(DH, T)
    other_q1 = Q[np.argmax(np.abs(_wrap(Q[:, 0] - q[0]))), 0]  # the other shoulder branch
    assert abs(_wrap(other_q1 - q[0])) > 0.1
    q_ref = np.r_[other_q1, q[1:]]
    # only joint 1 counts: a solution on the other shoulder branch
    q_sol = K.ik_nearest(DH, T, q_ref, Q_MIN, Q_MAX, weights=[1, 0, 0, 0, 0, 0])
    assert abs(_wrap(q_sol[0] - other_q1)) < 1e-9
    # joint 1 ignored: q itself (same q2..q6 as the reference)
    q_sol = K.ik_nearest(DH, T, q_ref, Q_MIN, Q_MAX, weights=[0, 1, 1, 1, 1, 1])
    np.testing.assert_allclose(q_sol, q, atol=1e-9)


def test_ik_nearest_unreachable_messages() -> None:
    T = K.fk(DH, np.zeros(6))
    T[:3, 3] = [2.0, 0.0, 0.3]  # 2 m away
    with pytest.raises(UnreachableError, match=r"from the shoulder, beyond the arm's reach"):
        K.ik_nearest(DH, T, np.zeros(6), Q_MIN, Q_MAX)
    q = np.array([0.4, -1.1, 1.3, -1.5, 1.2, 0.3])
    lo, hi = Q_MIN.copy(), Q_MAX.copy()
    lo[4], hi[4] = -0.1, 0.1  # wrist 2 may not move: every solution has |q5| = 1.2
    with pytest.raises(UnreachableError, match="all 8 IK solutions violate the joint limits"):
        K.ik_nearest(DH, K.fk(DH, q), q, lo, hi)


def test_ik_nearest_perturbed_dh() -> None:
    dh_true = _perturbed_dh(3)
    rng = np.random.default_rng(10)
    for q in _well_conditioned_q(rng, 10):
        T = K.fk(dh_true, q)
        q_sol = K.ik_nearest(dh_true, T, q + 0.01, Q_MIN, Q_MAX)
        np.testing.assert_allclose(q_sol, q, atol=1e-8)


# --- manipulability ---------------------------------------------------------------------------


def test_manipulability_is_product_of_singular_values() -> None:
    rng = np.random.default_rng(11)
    for q in rng.uniform(-np.pi, np.pi, (20, 6)):
        J = K.jacobian(DH, q)
        w = K.manipulability(J)
        assert w == pytest.approx(np.prod(np.linalg.svd(J, compute_uv=False)), rel=1e-9)
        assert w == pytest.approx(np.sqrt(np.linalg.det(J @ J.T)), rel=1e-6)
        assert w == pytest.approx(abs(np.linalg.det(J)), rel=1e-9)
        assert K.manipulability_q(DH, q) == pytest.approx(w)
    # non-square (e.g. position rows only): sqrt(det(J J^T)) = product of singular values
    J3 = K.jacobian(DH, rng.uniform(-np.pi, np.pi, 6))[:3]
    assert K.manipulability(J3) == pytest.approx(np.sqrt(np.linalg.det(J3 @ J3.T)), rel=1e-9)


def test_manipulability_vanishes_at_singularities() -> None:
    q = np.array([0.4, -1.1, 1.3, -1.5, 1.2, 0.3])
    w_regular = K.manipulability_q(DH, q)
    assert w_regular > 1e-3
    for i, v in ((2, 0.0), (4, 0.0)):  # elbow straight, wrist singular
        qs = q.copy()
        qs[i] = v
        assert K.manipulability_q(DH, qs) < 1e-12
    Qb = np.stack([q, q * 0.5])
    wb = K.manipulability(K.jacobian(DH, Qb))
    np.testing.assert_allclose(wb, [w_regular, K.manipulability_q(DH, q * 0.5)])
