"""The online intercept planner (mmpa.servo.intercept): limits kept, target state met."""

import numpy as np
import pytest

from mmpa.core.errors import InvalidInputError
from mmpa.robot.limits import path_accelerations, path_velocities
from mmpa.servo.intercept import InterceptLimits, StreamState, intercept_step

QD = np.full(6, np.pi)
QDD = np.array([3.2, 3.2, 3.2, 4.8, 4.8, 4.8])
QDDD = np.array([40.0, 40.0, 40.0, 60.0, 60.0, 60.0])
LIM = InterceptLimits(np.full(6, -6.0), np.full(6, 6.0), QD, QDD, QDDD)


def _stream(q0, q_goal0, v_goal, h=0.01, steps=300, lim=LIM):
    """Replan every ``h`` s toward the target ``q_goal0 + v_goal t``; returns the times,
    the streamed positions (steps + 1, 6) and the plans' durations."""
    s = StreamState.at_rest(q0)
    t = np.arange(steps + 1) * h
    Q, T = [s.q], []
    for k in range(steps):
        s, dur = intercept_step(s, q_goal0 + v_goal * t[k], v_goal, h, lim)
        Q.append(s.q)
        T.append(dur)
    return t, np.array(Q), np.array(T)


def test_intercept_meets_a_target_moving_at_constant_velocity():
    rng = np.random.default_rng(7)
    q_goal0 = rng.uniform(-0.5, 0.5, 6)
    v_goal = rng.uniform(-0.4, 0.4, 6)
    t, Q, T = _stream(np.zeros(6), q_goal0, v_goal)
    # closed-form truth: once met, the stream is the target's line q_goal0 + v_goal t
    met = int(np.argmax(T < 1e-9))
    assert 0 < met < 150  # met within 1.5 s
    truth = q_goal0 + v_goal[None, :] * t[met + 1 :, None]
    assert np.allclose(Q[met + 1 :], truth, atol=1e-9)
    # each replan continues the previous plan: its remaining time falls by one period
    assert np.allclose(np.diff(T[: met - 1]), -0.01, atol=5e-4)
    # the streamed set-points keep qd_max and qdd_max (finite differences, module limits)
    v = path_velocities(t, Q)
    a = path_accelerations(t, Q)
    assert np.max(np.abs(v) / QD) <= 1.0 + 1e-6
    assert np.max(np.abs(a) / QDD) <= 1.0 + 1e-6
    assert np.max(np.abs(a) / QDD) > 0.9  # the catch-up uses the acceleration limit


def test_intercept_rest_to_rest_takes_the_closed_form_time():
    """A still target, one joint moving: with a very high jerk limit the plan is the
    bang-bang (triangular) profile of duration 2 sqrt(d / a), or the trapezoid
    d / v + v / a when the speed limit is reached."""
    jerk_free = InterceptLimits(LIM.q_min, LIM.q_max, QD, QDD, np.full(6, 1e6))
    for d in (0.2, 4.0):
        goal = np.zeros(6)
        goal[1] = d
        _, T = intercept_step(StreamState.at_rest(np.zeros(6)), goal, np.zeros(6), 0.01, jerk_free)
        a, v = QDD[1], QD[1]
        closed = 2 * np.sqrt(d / a) if np.sqrt(d * a) < v else d / v + v / a
        assert T == pytest.approx(closed, abs=1e-3)


def test_a_target_faster_than_qd_max_is_followed_within_it():
    v_goal = np.array([5.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # beyond qd_max = pi
    t, Q, _ = _stream(np.zeros(6), np.zeros(6), v_goal, steps=200)
    v = path_velocities(t, Q)
    assert np.max(np.abs(v) / QD) <= 1.0 + 1e-6
    assert v[-1, 0] >= 0.9 * np.pi - 1e-6  # chasing it at (near) the speed limit


def test_intercept_refuses_bad_input():
    s = StreamState.at_rest(np.zeros(6))
    with pytest.raises(InvalidInputError, match="q_goal"):
        intercept_step(s, np.full(6, np.nan), np.zeros(6), 0.01, LIM)
    with pytest.raises(InvalidInputError, match="period"):
        intercept_step(s, np.zeros(6), np.zeros(6), 0.0, LIM)
    with pytest.raises(InvalidInputError, match="qdd_max"):
        InterceptLimits(LIM.q_min, LIM.q_max, QD, np.zeros(6), QDDD)
