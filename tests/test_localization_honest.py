"""The honest reflector fix (common range bias, survey error) and the lidar mount calibration,
against closed forms, Monte Carlo and the twin's ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.lidar_noise import rough_pose
from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import T_to_se2
from mmpa.localization.calibration import calibrated_mount, fit_turn_mount
from mmpa.localization.enhanced import (
    EnhancedConfig,
    ObserverConfig,
    ReflectorObserver,
    sensor_to_base,
    update_bias,
)
from mmpa.localization.reflectors import ReflectorDetections, detect_reflectors
from mmpa.localization.trilateration import trilaterate_bias
from mmpa.navigation.mount_calibration import calibrate_lidar_mount

AROUND = np.array([[3.0, 0.5], [-2.0, 2.5], [-1.5, -3.0], [2.5, -2.0], [0.5, 3.5], [-3.5, 0.0]])


def _measure(L: np.ndarray, pose: np.ndarray, bias: float) -> tuple[np.ndarray, np.ndarray]:
    d = L - pose[:2]
    return np.hypot(d[:, 0], d[:, 1]) + bias, np.arctan2(d[:, 1], d[:, 0]) - pose[2]


def test_trilaterate_bias_recovers_pose_and_bias_exactly() -> None:
    pose = np.array([0.3, -0.2, 0.7])
    r, b = _measure(AROUND, pose, -0.012)
    fit = trilaterate_bias(AROUND, r, b, 0.005, 0.002, bias_mean=0.0, bias_sigma=1.0)
    np.testing.assert_allclose(fit.pose, pose, atol=1e-9)
    assert fit.bias == pytest.approx(-0.012, abs=1e-6)  # the 1 m prior's pull: 5e-8
    # a tight prior at 0 keeps the bias at 0: the 12 mm then go into the residuals
    tight = trilaterate_bias(AROUND, r, b, 0.005, 0.002, bias_mean=0.0, bias_sigma=1e-6)
    assert abs(tight.bias) < 1e-6 and tight.rms > 0.005
    # from an initial pose, two reflectors suffice
    two = trilaterate_bias(AROUND[:2], r[:2], b[:2], 0.005, 0.002, -0.012, 1e-4, initial=pose)
    np.testing.assert_allclose(two.pose, pose, atol=1e-6)


def test_common_bias_is_observable_around_the_robot_not_from_one_side() -> None:
    """Reflectors all around pin a common bias (no pose shortens every range); reflectors on
    one side leave it to the prior, and a wrong prior moves the pose along their direction."""
    pose = np.array([0.0, 0.0, 0.0])
    side = np.array([[3.0, -0.4], [3.6, 0.1], [4.2, 0.5], [3.3, 0.6]])  # within 16 deg
    for L, observable in ((AROUND, True), (side, False)):
        r, b = _measure(L, pose, -0.010)
        fit = trilaterate_bias(L, r, b, 0.005, 0.002, bias_mean=0.0, bias_sigma=0.02)
        info_ratio = fit.bias_info_meas / (1 / 0.02**2)
        if observable:
            assert info_ratio > 5 and abs(fit.bias + 0.010) < 1e-3
        else:
            assert info_ratio < 0.5 and abs(fit.bias + 0.010) > 0.005
            assert fit.pose[0] > 0.005  # the unexplained shortening: the pose moves toward them


def test_trilaterate_bias_covariance_matches_monte_carlo() -> None:
    """The returned covariance is the honest one: per-reflector range noise, a survey error of
    ``survey_sigma`` per axis on every landmark and a common bias drawn from the prior, the
    empirical covariance of 2000 fits matches ``cov`` (pose and bias) within 15 %."""
    rng = np.random.default_rng(0)
    pose = np.array([0.4, 0.1, -0.3])
    sr, sb, ss, bs = 0.006, 0.0015, 0.010, 0.008
    r0, b0 = _measure(AROUND, pose, 0.0)
    est, covs = [], []
    for _ in range(2000):
        bias = rng.normal(0.0, bs)
        truth = np.array([*pose, bias])
        L_map = AROUND + rng.normal(0.0, ss, AROUND.shape)  # the map errs, the world does not
        r = r0 + bias + rng.normal(0.0, sr, len(r0))
        b = b0 + rng.normal(0.0, sb, len(b0))
        fit = trilaterate_bias(L_map, r, b, sr, sb, 0.0, bs, survey_sigma=ss)
        est.append(np.array([*fit.pose, fit.bias]) - truth)
        covs.append(fit.cov)
    E = np.array(est)
    emp = np.cov(E.T)
    pred = np.mean(covs, axis=0)
    np.testing.assert_allclose(np.sqrt(np.diag(emp)), np.sqrt(np.diag(pred)), rtol=0.15)
    assert np.abs(E.mean(axis=0)).max() < 0.1 * np.sqrt(np.diag(pred)).max()


def test_sensor_to_base_inverts_the_mount_and_its_jacobian() -> None:
    X = np.array([1.2, -0.4, 2.5])
    m = np.array([0.3, -0.02, 0.01])
    c, s = np.cos(X[2]), np.sin(X[2])
    S = np.array([X[0] + c * m[0] - s * m[1], X[1] + s * m[0] + c * m[1], X[2] + m[2]])
    cov = np.diag([1e-6, 4e-6, 9e-6])
    Xb, cb = sensor_to_base(S, cov, m)
    np.testing.assert_allclose(Xb, X, atol=1e-12)
    J = np.zeros((3, 3))
    for i in range(3):
        h = np.zeros(3)
        h[i] = 1e-6
        J[:, i] = (sensor_to_base(S + h, cov, m)[0] - sensor_to_base(S - h, cov, m)[0]) / 2e-6
    np.testing.assert_allclose(cb, J @ cov @ J.T, rtol=1e-6, atol=1e-15)


def test_update_bias_closed_form_gate_and_cap() -> None:
    # prior N(0, 10 mm), the fix alone says -12 mm with SD 5 mm: the Bayes posterior
    info0, info_m, b_m = 1 / 0.01**2, 1 / 0.005**2, -0.012
    post = (info0 * 0.0 + info_m * b_m) / (info0 + info_m)
    mean, info, ok = update_bias(0.0, info0, post, info_m, 1e-4, 3.0)
    assert ok and mean == pytest.approx(post) and info == pytest.approx(info0 + info_m)
    # the cap: information never beyond 1 / sigma_min^2
    mean, info, ok = update_bias(0.0, info0, post, info_m, 0.008, 3.0)
    assert ok and info == pytest.approx(1 / 0.008**2)
    # a fix 6 SDs off is not learned
    far = (info0 * 0.0 + info_m * 0.07) / (info0 + info_m)
    assert update_bias(0.0, info0, far, info_m, 1e-4, 3.0) == (0.0, info0, False)
    # no information: nothing learned
    assert update_bias(0.0, info0, 0.0, 0.0, 1e-4, 3.0)[2] is False


def test_range_corrected_moves_centers_along_their_rays() -> None:
    r, b = np.array([2.0, 3.0]), np.array([0.3, -2.0])
    det = ReflectorDetections(r, b, np.column_stack([r * np.cos(b), r * np.sin(b)]), np.ones(2))
    c = det.range_corrected(-0.01)
    np.testing.assert_allclose(c.ranges, r + 0.01)
    np.testing.assert_allclose(np.arctan2(c.points[:, 1], c.points[:, 0]), b)
    np.testing.assert_allclose(np.hypot(c.points[:, 0], c.points[:, 1]), r + 0.01)


def test_observer_learns_the_twins_common_range_bias() -> None:
    """Realistic twin, parked at site 1: the running bias of the observer matches the mean
    range error of the detected reflector centers measured against the simulator's truth
    (true laser site to the true reflectors; -10 mm range walk on average), within 3 mm; the
    paper's observer learns nothing."""
    with SimWorld(site="1", errors=ErrorModelConfig(seed=0)) as w:
        obs = ReflectorObserver(w.map_reflectors, laser_pose2d(w))
        paper = ReflectorObserver(
            w.map_reflectors, laser_pose2d(w), EnhancedConfig.paper().observer
        )
        T = w.truth.T_map_base_link() @ w.true_robot.lidar.T_base_link_laser
        S = T_to_se2(T)  # the true laser pose (evaluation only)
        R = w.truth.reflector_positions()
        errs = []
        for _ in range(10):
            w.step(0.2)
            scan = w.lidar.scan()
            assert obs.observe(scan) is not None and paper.observe(scan) is not None
            det = detect_reflectors(scan, obs.cfg.detection.model_copy(update={"radius": 0.04}))
            c, s = np.cos(S[2]), np.sin(S[2])
            pm = det.points @ np.array([[c, s], [-s, c]]) + S[:2]
            k = np.linalg.norm(pm[:, None] - R[None], axis=2).argmin(axis=1)
            errs.extend(det.ranges - np.linalg.norm(R[k] - S[:2], axis=1))
        true_bias = float(np.mean(errs))
        assert true_bias < -0.005  # the twin's range walk is there
        assert abs(obs.bias - true_bias) < 0.003, (obs.bias, true_bias)
        assert obs.bias_updates == 10 and paper.bias == 0.0
        # the honest fix's SD is at the survey level (10 mm / sqrt(n)), not the beam noise's
        fix = obs.observe(w.lidar.scan())
        assert fix is not None
        sd = np.sqrt(np.linalg.eigvalsh(fix.trilateration.cov[:2, :2]))
        assert 0.003 < sd.min() and sd.max() < 0.008, sd


def test_honest_observer_off_is_the_old_fix() -> None:
    """``survey_sigma = range_bias_scatter = 0`` and ``range_bias`` off give the fix of before
    (:func:`trilaterate` in ``base_link``) to numerical precision."""
    with SimWorld(site="1", errors=ErrorModelConfig(seed=1)) as w:
        lp = laser_pose2d(w)
        off = ObserverConfig(survey_sigma=0.0, range_bias_scatter=0.0, range_bias=False)
        assert not off.honest_fix
        fix = ReflectorObserver(w.map_reflectors, lp, off).observe(w.lidar.scan())
        assert fix is not None and fix.bias_fit is None
        sd = np.sqrt(np.linalg.eigvalsh(fix.trilateration.cov[:2, :2]))
        assert sd.max() < 0.003  # beam noise only: the overconfident fix of before


def test_fit_turn_mount_closed_form() -> None:
    """Scanner poses on a circle about the base with a constant map offset (the map's error at
    that place goes into the center) give the mount translation exactly; too small a turn is
    refused."""
    m = np.array([0.297, 0.004, 0.02])
    c0 = np.array([1.0, -2.0])
    th = np.linspace(0.0, 2 * np.pi, 40, endpoint=False)
    P = np.array(
        [
            [
                c0[0] + np.cos(t) * m[0] - np.sin(t) * m[1],
                c0[1] + np.sin(t) * m[0] + np.cos(t) * m[1],
                t + m[2],
            ]
            for t in th
        ]
    )
    P[:, :2] += np.array([0.006, -0.004])  # the map's local offset
    fit = fit_turn_mount(P)
    v = np.array(
        [np.cos(m[2]) * m[0] + np.sin(m[2]) * m[1], -np.sin(m[2]) * m[0] + np.cos(m[2]) * m[1]]
    )
    np.testing.assert_allclose(fit.v, v, atol=1e-12)
    np.testing.assert_allclose(fit.center, c0 + np.array([0.006, -0.004]), atol=1e-12)
    assert fit.rms < 1e-12
    # with the nominal yaw (0), the calibrated mount puts the base where the true one does
    cal = calibrated_mount(fit, np.array([0.3, 0.0, 0.0]))
    S = P[7]
    base_true = S[:2] - np.array(
        [
            np.cos(S[2] - m[2]) * m[0] - np.sin(S[2] - m[2]) * m[1],
            np.sin(S[2] - m[2]) * m[0] + np.cos(S[2] - m[2]) * m[1],
        ]
    )
    base_cal = S[:2] - np.array(
        [
            np.cos(S[2]) * cal[0] - np.sin(S[2]) * cal[1],
            np.sin(S[2]) * cal[0] + np.cos(S[2]) * cal[1],
        ]
    )
    np.testing.assert_allclose(base_cal, base_true, atol=1e-12)
    with pytest.raises(InvalidInputError, match="span"):
        fit_turn_mount(P[:3])


def test_mount_calibration_in_the_twin_against_the_true_mount() -> None:
    """Realistic twin, seed 0 (its mount is 3.8 / -1.6 mm off the nominal): one turn on the
    spot at site 1, matched against the warped map from the operator's rough pose, recovers
    the TRUE mount translation (in the scanner's frame) within 0.6 mm (measured 0.1-0.3 mm,
    seeds 0-4); the nominal is 4.3 mm off."""
    with SimWorld(site="1", errors=ErrorModelConfig(seed=0), episode=500) as w:
        nominal = laser_pose2d(w)
        true = T_to_se2(w.true_robot.lidar.T_base_link_laser)
        c, s = np.cos(true[2]), np.sin(true[2])
        v_true = np.array([c * true[0] + s * true[1], -s * true[0] + c * true[1]])
        guess = rough_pose(w.truth.base_pose2d(), np.random.default_rng(1), 0.2, 0.17)
        cal = calibrate_lidar_mount(w, twin_map(w), nominal, guess)
        assert cal.mount is not None and cal.fit.turned > 6.0
        assert np.hypot(*(nominal[:2] - v_true)) > 0.003
        assert np.hypot(*(cal.fit.v - v_true)) < 0.0006, (cal.fit.v, v_true)
        np.testing.assert_allclose(cal.mount[2], nominal[2])
