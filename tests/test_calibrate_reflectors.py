"""``mmpa calibrate reflectors``: the reflector survey fit (closed-form synthetic truth), its
bad input, the robot file's ``reflector_map`` entry, and a short survey drive in the twin
against the twin's TRUE reflector positions."""

from __future__ import annotations

import json
import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np
import pytest
from typer.testing import CliRunner

from mmpa.calibration.reflector_survey import (
    SurveyConfig,
    SurveyError,
    SurveyObservations,
    anchor_to,
    cluster_points,
    fit_reflector,
    laser_origin_heading,
    match_reflectors,
    match_scan_to_map,
    signed_distance_map,
    survey_reflectors,
)
from mmpa.core.errors import ConfigError, InvalidInputError

REFL = np.array([[0.0, 3.0], [4.0, 2.5], [4.5, -2.0], [-1.0, -3.0], [2.0, 0.5]])
LASER = np.array([0.25, 0.02, 0.01])  # mount [x, y, yaw] in base_link


def _poses(rng: np.random.Generator, n: int = 8) -> np.ndarray:
    """Base poses on a loop inside the reflectors' field."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([1.5 + 1.2 * np.cos(a), 0.0 + 1.2 * np.sin(a), a + rng.normal(0, 1, n)])


def _detections(
    poses: np.ndarray,
    refl: np.ndarray,
    bias: np.ndarray,
    rng: np.random.Generator,
    scans: int = 5,
    noise: float = 0.0,
) -> SurveyObservations:
    """What the lidar at each TRUE pose sees: ``z = R^T (p - t) + beta z/|z|`` (the range
    off by the reflector's bias ``beta``), ``scans`` scans per pose, ``noise`` m per axis."""
    t, phi = laser_origin_heading(poses, LASER)
    pts, idx, scan = [], [], []
    k = 0
    for s in range(len(poses)):
        c, sn = np.cos(phi[s]), np.sin(phi[s])
        for _ in range(scans):
            for j, p in enumerate(refl):
                d = p - t[s]
                z = np.array([c * d[0] + sn * d[1], -sn * d[0] + c * d[1]])
                z = z + bias[j] * z / np.linalg.norm(z) + rng.normal(0, noise, 2) * (noise > 0)
                pts.append(z)
                idx.append(s)
                scan.append(k)
            k += 1
    return SurveyObservations(np.array(pts), np.array(idx), poses, LASER, np.array(scan))


def test_fit_recovers_positions_and_biases_exactly() -> None:
    """Noise-free views from the TRUE poses: the linear fit returns the closed-form truth
    (positions and each reflector's own range bias, the views spread around it)."""
    rng = np.random.default_rng(0)
    poses = _poses(rng)
    bias = np.array([-0.010, -0.004, -0.016, -0.008, -0.012])
    obs = _detections(poses, REFL, bias, rng)
    cfg = SurveyConfig(bias_sigma=1.0, refine_poses=False)  # (almost) no prior on the bias
    res = survey_reflectors(obs, cfg)
    assert res.ok and len(res) == 5
    m = match_reflectors(res.positions, REFL)
    assert len(m.pairs) == 5 and m.errors.max() < 1e-5
    est_bias = np.empty(5)
    est_bias[m.pairs[:, 1]] = res.biases[m.pairs[:, 0]]
    np.testing.assert_allclose(est_bias, bias, atol=1e-5)
    assert res.rms < 1e-5 and (res.views == 40).all() and (res.poses_seen == 8).all()
    # ignoring the bias instead (range_bias 0, fixed) moves every centre toward the views
    naive = survey_reflectors(obs, SurveyConfig(range_bias=0.0, bias_sigma=0.0, refine_poses=False))
    assert match_reflectors(naive.positions, REFL).errors.mean() > 2e-3


def test_fit_reflector_closed_form_single() -> None:
    """One reflector, views from four sides with a known bias: p and beta exactly; from one
    side only the prior holds the bias (the position stays within it)."""
    p = np.array([1.0, 2.0])
    u = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]], float)
    q = p + -0.01 * u
    f = fit_reflector(q, u, range_bias=0.0, bias_sigma=0.02, point_sigma=0.01)
    np.testing.assert_allclose(f.position, p, atol=1e-9)
    # sum u = 0: p decouples; delta = sum(u.(q - p)) / (4 + (s / s_b)^2), the prior's shrink
    assert f.bias == pytest.approx(-0.01 * 4 / (4 + 0.25), abs=1e-12)
    f1 = fit_reflector(q[:1], u[:1], range_bias=-0.01, bias_sigma=0.005)
    np.testing.assert_allclose(f1.position, p, atol=1e-9)


def test_noisy_survey_with_pose_errors_bundle_adjusted() -> None:
    """Range noise and pose estimates off by 2 cm / 0.3 deg: the survey stays within a few
    mm of the truth; the joint refinement pulls the poses toward the truth."""
    rng = np.random.default_rng(1)
    poses = _poses(rng, 12)
    bias = -0.008 + rng.normal(0, 0.003, len(REFL))
    obs = _detections(poses, REFL, bias, rng, scans=10, noise=0.01)
    pose_err = np.column_stack([rng.normal(0, 0.02, (12, 2)), rng.normal(0, 0.005, 12)])
    est = SurveyObservations(obs.points, obs.pose_index, poses + pose_err, LASER, obs.scan_index)
    plain = survey_reflectors(est, SurveyConfig(refine_poses=False))
    ba = survey_reflectors(est, SurveyConfig(refine_poses=True))
    e_plain = match_reflectors(plain.positions, REFL).errors
    e_ba = match_reflectors(ba.positions, REFL).errors
    assert ba.refined and len(e_ba) == 5
    assert e_ba.mean() < 0.012 and e_ba.max() < 0.02
    assert e_ba.mean() < e_plain.mean()
    before = np.hypot(*pose_err[:, :2].T).mean()
    after = np.hypot(*(ba.poses - poses)[:, :2].T).mean()
    assert after < before


def test_outliers_and_one_off_detections_are_dropped() -> None:
    rng = np.random.default_rng(2)
    poses = _poses(rng)
    obs = _detections(poses, REFL, np.full(5, -0.008), rng, noise=0.005)
    # a one-off glare (one scan, one pose) and a gross outlier next to reflector 0
    extra = np.array([[7.0, 7.0], obs.points[0] + [0.08, 0.0]])
    obs2 = SurveyObservations(
        np.vstack([obs.points, extra]),
        np.concatenate([obs.pose_index, [3, 0]]),
        poses,
        LASER,
        np.concatenate([obs.scan_index, [10_000, 0]]),
    )
    res = survey_reflectors(obs2, SurveyConfig(refine_poses=False, outlier_gate=0.05))
    assert len(res) == 5 and res.dropped_clusters == 1
    assert res.labels[-2] == -1 and res.labels[-1] == -1
    assert match_reflectors(res.positions, REFL).errors.max() < 0.005
    # seen from too few poses: nothing passes, the survey says why
    one = SurveyObservations(
        obs.points[obs.pose_index == 0], obs.pose_index[obs.pose_index == 0], poses, LASER
    )
    bad = survey_reflectors(one, SurveyConfig())
    assert not bad.ok and "poses" in bad.reason and len(bad) == 0


def test_bad_input_is_named() -> None:
    poses = np.zeros((2, 3))
    with pytest.raises(SurveyError, match="no reflector detections"):
        survey_reflectors(SurveyObservations(np.zeros((0, 2)), np.zeros(0, int), poses, LASER))
    pts = np.array([[1.0, 0.0], [np.nan, 1.0]])
    with pytest.raises(InvalidInputError, match="detection 1 is not finite"):
        SurveyObservations(pts, np.array([0, 1]), poses, LASER)
    with pytest.raises(InvalidInputError, match="pose 1 is not finite"):
        SurveyObservations(pts[:1], np.array([0]), np.array([[0, 0, 0], [np.nan, 0, 0]]), LASER)
    with pytest.raises(InvalidInputError, match="pose_index must lie in"):
        SurveyObservations(pts[:1], np.array([5]), poses, LASER)
    with pytest.raises(InvalidInputError, match="points must be"):
        SurveyObservations(np.zeros((3, 3)), np.zeros(3, int), poses, LASER)
    with pytest.raises(SurveyError, match="at least one view"):
        fit_reflector(np.zeros((0, 2)), np.zeros((0, 2)))


def test_cluster_and_match_helpers() -> None:
    xy = np.array([[0, 0], [0.05, 0], [0.1, 0.02], [3, 3], [3.02, 3.0], [10, 0]], float)
    lab = cluster_points(xy, 0.1)
    assert lab.tolist() == [0, 0, 0, 1, 1, 2]
    m = match_reflectors(np.array([[0.0, 0.01], [5.0, 5.0]]), np.array([[0, 0], [3, 3.0]]))
    assert m.pairs.tolist() == [[0, 0]] and m.missed.tolist() == [1]
    assert m.spurious.tolist() == [1] and m.errors[0] == pytest.approx(0.01)


def test_scan_to_map_match_recovers_the_pose() -> None:
    """A 4 m x 3 m room with a pillar, drawn as a 5 cm grid (cells whose centre lies inside
    a wall are occupied): a noise-free scan from a known laser pose, matched from a guess
    4 cm / 1 deg off, comes back within 1 mm / 0.01 deg (closed-form ray casting)."""
    res = 0.05
    xs = (np.arange(100) + 0.5) * res - 0.5  # map origin (-0.5, -0.5), 5 m x 5 m
    X, Y = np.meshgrid(xs, xs)
    room = (X < 0) | (X > 4) | (Y < 0) | (Y > 3)
    pillar = (np.abs(X - 2.5) < 0.2) & (np.abs(Y - 2.0) < 0.3)
    sdf = signed_distance_map(room | pillar, res)
    assert sdf[50, 50] > 0 and sdf[0, 0] < 0
    # rays from the true pose to the walls and the pillar's faces (closed form)
    true = np.array([1.2, 1.1, 0.3])
    a = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    d = np.stack([np.cos(a + true[2]), np.sin(a + true[2])], 1)
    ts = []
    for k, (lo, hi) in enumerate([(0.0, 4.0), (0.0, 3.0)]):
        dk = d[:, k]
        with np.errstate(divide="ignore"):
            ts.append(np.where(dk > 0, (hi - true[k]) / dk, (lo - true[k]) / dk))
    t = np.minimum(*ts)
    # the pillar: slab intersection of the box [2.3, 2.7] x [1.7, 2.3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (np.array([2.3, 1.7]) - true[:2]) / d
        t2 = (np.array([2.7, 2.3]) - true[:2]) / d
    tin = np.max(np.minimum(t1, t2), axis=1)
    tout = np.min(np.maximum(t1, t2), axis=1)
    hit = (tin <= tout) & (tin > 0)
    t = np.where(hit, np.minimum(t, tin), t)
    pts = t[:, None] * np.stack([np.cos(a), np.sin(a)], 1)  # laser frame
    guess = true + np.array([0.04, -0.03, np.deg2rad(1.0)])
    pose, rms, n = match_scan_to_map(sdf, res, (-0.5, -0.5), pts, guess)
    assert n > 600 and rms < 0.002
    assert np.hypot(*(pose[:2] - true[:2])) < 1e-3 and abs(pose[2] - true[2]) < np.deg2rad(0.01)
    with pytest.raises(InvalidInputError, match="finite"):
        match_scan_to_map(sdf, res, (-0.5, -0.5), pts, np.array([np.nan, 0, 0]))


def test_anchor_to_recovers_a_rigid_move() -> None:
    th = np.deg2rad(1.0)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    ref = REFL @ R.T + [0.05, -0.02]
    moved, tf, n = anchor_to(REFL, ref)
    assert n == 5 and np.abs(moved - ref).max() < 1e-12
    np.testing.assert_allclose(tf, [0.05, -0.02, th], atol=1e-12)
    with pytest.raises(SurveyError, match="at least 2"):
        anchor_to(REFL, REFL[:1] + 5.0)


def test_robot_file_reflector_map_entry(tmp_path) -> None:
    from mmpa.robot.description import RobotDescription
    from mmpa.robot.robot_file import load_robot, robot_reflector_map, save_robot

    path = save_robot(RobotDescription(), tmp_path / "r" / "robot.yaml", reflector_map="m.yaml")
    robot, _ = load_robot(path)  # the entry does not disturb the description
    assert robot == RobotDescription()
    assert robot_reflector_map(path) == tmp_path / "r" / "m.yaml"
    plain = save_robot(RobotDescription(), tmp_path / "plain.yaml")
    assert robot_reflector_map(plain) is None and load_robot(plain)[0] == RobotDescription()
    bad = tmp_path / "bad.yaml"
    bad.write_text("reflector_map: [1, 2]\n")
    with pytest.raises(ConfigError, match="reflector_map"):
        load_robot(bad)


def test_twin_survey_cli_short_drive(tmp_path) -> None:
    """``mmpa calibrate reflectors`` on a short drive (site 0 -> 1, a stop every 5 m, 3 scans
    per stop): the CLI writes a reflector map and a robot file that load, finds most of the
    twin's 9 reflectors (measured 7, 2 missed) and none spurious, within a loose bound
    (measured 4.6 mm mean, 5.6 max; the full survey's 3 mm target is
    test_twin_survey_cli_against_truth, slow)."""
    from mmpa.cli.main import app
    from mmpa.maps.reflector_map import load_reflector_map
    from mmpa.robot.robot_file import load_robot, robot_reflector_map

    out = tmp_path / "survey"
    args = ["calibrate", "reflectors", "--out", str(out), "--route", "1", "--scans", "3"]
    args += ["--spacing", "5"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    s = json.loads((out / "summary.json").read_text())
    assert s["found"] + s["missed"] == 9 and s["found"] >= 5 and s["spurious"] == 0
    assert s["error_mean_mm"] < 10.0 and s["error_max_mm"] < 20.0
    rm = load_reflector_map(out / "reflectors.yaml")
    true = np.array([r["true"] for r in s["reflectors"]])
    assert match_reflectors(rm.xy, true).errors.mean() * 1e3 == pytest.approx(s["error_mean_mm"])
    load_robot(out / "robot.yaml")
    assert robot_reflector_map(out / "robot.yaml") == out / "reflectors.yaml"


# slow (26 s: 7 stops of 30 scans); the default run keeps the CLI on a short drive
# (test_twin_survey_cli_short_drive) and the drive over the protocols
# (test_protocols_only.py: test_reflector_survey_drive_over_protocols_only)
@pytest.mark.slow
def test_twin_survey_cli_against_truth(tmp_path) -> None:
    """The survey drive (site 0 -> 1 -> 2 -> 0, 7 stops of 30 scans, intensity-centroid
    bearings) under `realistic`, seed 0: every true reflector found, none spurious, and the
    error against the TRUE positions within the issue's 3 mm mean. Measured: 2.10 mm mean
    (4.1 max; 3.52 / 7.9 with 10 scans and mean-angle bearings); the layout alone (after the
    best rigid move onto the truth) 2.1 mm; placed onto the twin's marked reflector map
    instead 6.1 mm; the marked map itself 14.3 mm. The files load, and ``mmpa --robot
    robot.yaml navigate`` picks the map up."""
    from mmpa.cli.main import app
    from mmpa.maps.reflector_map import load_reflector_map
    from mmpa.robot.robot_file import load_robot, robot_reflector_map

    out = tmp_path / "survey"
    runner = CliRunner()
    r = runner.invoke(app, ["calibrate", "reflectors", "--out", str(out)])
    assert r.exit_code == 0, r.output
    s = json.loads((out / "summary.json").read_text())
    d = s["diagnostic"]
    assert s["profile"] == "realistic" and s["seed"] == 0 and s["anchor"] == "poses"
    assert (s["found"], s["missed"], s["spurious"]) == (9, 0, 0)
    assert s["error_mean_mm"] < 3.0 and s["error_max_mm"] < 8
    assert s["error_mean_mm"] < d["marked_map"]["error_mean_mm"] / 2  # beats the marked map
    assert d["shape_error_mean_mm"] < 3.0  # the survey's own part
    assert d["anchor_reflector_map"]["error_mean_mm"] < 10
    # the scanner's published range walk was used (mean -10 mm + incidence over the face)
    assert s["survey_config"]["range_bias"] == pytest.approx(-0.01 + 0.01 * (1 - np.pi / 4))
    errs = [r["error_mm"] for r in s["reflectors"]]
    assert np.mean(errs) == pytest.approx(s["error_mean_mm"])
    rm = load_reflector_map(out / "reflectors.yaml")
    true = np.array([r["true"] for r in s["reflectors"]])
    assert len(rm) == 9 and np.abs(rm.radius - 0.04).max() == 0
    assert match_reflectors(rm.xy, true).errors.mean() * 1e3 == pytest.approx(s["error_mean_mm"])
    load_robot(out / "robot.yaml")
    assert robot_reflector_map(out / "robot.yaml") == out / "reflectors.yaml"
    # the next run takes it (a short drive: only the summary's entry is checked)
    nav = tmp_path / "nav"
    args = ["--robot", str(out / "robot.yaml"), "navigate", "--to", "1", "--timeout", "3"]
    r2 = runner.invoke(app, [*args, "--out", str(nav)])
    assert r2.exit_code in (0, 1), r2.output  # 1: not parked within 3 s
    assert json.loads((nav / "summary.json").read_text())["reflector_map"] == str(
        out / "reflectors.yaml"
    )
