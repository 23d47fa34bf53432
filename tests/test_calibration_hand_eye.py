"""Hand-eye calibration: ChArUco detection and pose against the twin's truth, the AX = XB
solvers on exact synthetic data, pose selection, and ``mmpa calibrate hand-eye`` in the twin
recovering the TRUE hand-eye."""

from __future__ import annotations

import json
import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from mmpa.backends.twin.calibration_board import (
    BOARD_BODY,
    BoardPlacement,
    CharucoBoardSpec,
    T_map_board_truth,
    board_world,
)
from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.calibration.charuco import (
    BoardNotFoundError,
    CharucoDetection,
    board_pose,
    detect_charuco,
    estimate_board_pose,
)
from mmpa.calibration.hand_eye import (
    METHODS,
    board_consistency,
    calibrate_hand_eye,
    pair_motion_stats,
    plan_stations,
    pose_error,
    solve_hand_eye,
)
from mmpa.core.errors import InvalidInputError, UnreachableError
from mmpa.core.geometry import exp_se3, inv, make_T
from mmpa.core.yamlio import load_yaml
from mmpa.robot.description import CameraDescription
from mmpa.robot.kinematics import fk

SPEC = CharucoBoardSpec()


def _random_pose(rng: np.random.Generator, rot: float, trans: float) -> np.ndarray:
    return exp_se3(np.concatenate([rng.normal(0, trans, 3), rng.normal(0, rot, 3)]))


# --- synthetic AX = XB ---------------------------------------------------------------------


def _synthetic(rng: np.random.Generator, n: int = 10):
    X = _random_pose(rng, 0.5, 0.05)
    Y = _random_pose(rng, 1.0, 0.5)
    G = np.array([_random_pose(rng, 1.0, 0.4) for _ in range(n)])
    C = np.array([inv(X) @ inv(g) @ Y for g in G])
    return X, Y, G, C


@pytest.mark.parametrize("method", METHODS)
def test_every_method_recovers_exact_hand_eye(method: str) -> None:
    X, _, G, C = _synthetic(np.random.default_rng(3))
    X_est = solve_hand_eye(G, C, method)
    assert np.allclose(X_est, X, atol=1e-6)
    # the motion form: A = G_i^-1 G_j, B = X^-1 A X is what the camera sees between views
    A = inv(G[0]) @ G[4]
    B = C[0] @ inv(C[4])
    assert np.allclose(B, inv(X) @ A @ X, atol=1e-9)
    assert np.allclose(A @ X_est, X_est @ B, atol=1e-6)


def test_consistency_is_zero_for_the_truth_and_flags_an_offset() -> None:
    X, Y, G, C = _synthetic(np.random.default_rng(5), 12)
    exact = board_consistency(G, C, X, SPEC.corners())
    assert exact.point_rms_mm < 1e-6 and exact.rot_rms_deg < 1e-6
    assert np.allclose(exact.T_base_board, Y, atol=1e-9)
    wrong = X.copy()
    wrong[:3, 3] += np.array([1e-3, 0.0, 0.0])  # 1 mm off
    off = board_consistency(G, C, wrong, SPEC.corners())
    # the board predicted from station i moves by R_Gi (1 mm x): spread of a rotated vector
    spread = np.linalg.norm(G[:, :3, 0] - G[:, :3, 0].mean(axis=0), axis=1) * 1.0
    assert off.origin_rms_mm == pytest.approx(np.sqrt(np.mean(spread**2)), rel=1e-6)
    assert off.point_rms_mm > 0.3


def test_calibrate_picks_smallest_spread_under_noise() -> None:
    rng = np.random.default_rng(11)
    X, _, G, C = _synthetic(rng, 15)
    C = np.array([c @ _random_pose(rng, np.deg2rad(0.02), 0.2e-3) for c in C])
    res = calibrate_hand_eye(G, C, SPEC.corners())
    assert set(res.methods) == set(METHODS)
    spreads = {m: r.consistency.point_rms_mm for m, r in res.methods.items()}
    assert res.best == min(spreads, key=spreads.get)
    et, er = pose_error(res.T_flange_camera, X)
    assert et < 1.0 and er < 0.1  # 0.2 mm / 0.02 deg of noise per view
    with pytest.raises(InvalidInputError, match="at least 3"):
        solve_hand_eye(G[:2], C[:2])
    with pytest.raises(InvalidInputError, match="unknown hand-eye method"):
        solve_hand_eye(G, C, "magic")


# --- joint kinematic + hand-eye calibration (synthetic) -------------------------------------


def _joint_synthetic(seed: int, n: int, noise_px: float = 0.2):
    """Stations planned with the nominal UR5e around the default board, a TRUE arm with DH
    errors of the realistic profile's size, a TRUE hand-eye and corners projected through the
    truth with pixel noise."""
    from mmpa.calibration.kinematic import (
        DH_GROUPS,
        BoardObservations,
        apply_dh_deltas,
        fk_batch,
        project,
    )
    from mmpa.robot.description import default_robot

    rng = np.random.default_rng(seed)
    robot = default_robot()
    dh = robot.arm.dh
    K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
    P = SPEC.corners()
    X_nom = robot.camera.T_flange_camera
    Y = BoardPlacement().T_armbase_board(SPEC, robot)
    st = plan_stations(
        dh,
        robot.arm.q_limits,
        Y,
        X_nom,
        P,
        K,
        (640, 480),
        n,
        np.asarray(robot.arm.view_bench, float),
        distances=(0.3, 0.4, 0.5, 0.6),
        tilts_deg=(0.0, 15.0, 30.0, 45.0, 60.0),
        rolls_deg=(-90.0, -45.0, 0.0, 45.0, 90.0),
    )
    q = np.array([s.q for s in st])
    sig = {"delta_a": 5e-4, "delta_d": 5e-4}
    deltas = {k: rng.normal(0.0, sig.get(k, np.deg2rad(0.05)), 6) for k in DH_GROUPS}
    dh_true = apply_dh_deltas(dh, deltas)
    X_true = X_nom @ _random_pose(rng, np.deg2rad(0.5), 1e-3)
    Ph = np.c_[P, np.ones(len(P))]
    uv = []
    for g in fk_batch(*dh_true.as_arrays(), q):
        pc = (inv(g @ X_true) @ Y @ Ph.T).T[:, :3]
        uv.append(project(K, pc) + rng.normal(0.0, noise_px, (len(P), 2)))
    obs = BoardObservations.from_lists(list(q), [P] * len(q), uv)
    return dh, dh_true, X_nom, X_true, Y, K, obs


def test_joint_calibration_recovers_hand_eye_and_kinematics() -> None:
    """Synthetic truth (independent: the true DH, X and Y that made the corners): the joint
    MAP estimate finds the hand-eye up to the last link's unobservable DH error E6 (module
    docstring of mmpa.calibration.kinematic), and the calibrated kinematics put the camera
    closer to the truth than the nominal ones over random configurations."""
    from mmpa.apps.calibrate import last_link_error
    from mmpa.calibration.kinematic import (
        GAUGE_INDICES,
        JointCalibrationConfig,
        calibrate_kinematics_hand_eye,
        fk_point_error,
        random_configurations,
    )

    dh, dh_true, X_nom, X_true, Y, K, obs = _joint_synthetic(4, 30)
    Y0 = Y @ _random_pose(np.random.default_rng(1), 2e-3, 2e-3)
    res = calibrate_kinematics_hand_eye(
        dh, obs, K, X_nom, Y0, JointCalibrationConfig(pixel_sigma=0.2)
    )
    assert res.success and res.rms_px < 0.3 and res.rms_px_start > 2.0  # 2D RMS: 0.2 sqrt 2
    E6 = last_link_error(dh, dh_true)
    et, er = pose_error(res.T_flange_camera, E6 @ X_true)
    # within 3 posterior SDs (norm of the per-axis SDs: 0.18 mm, 0.010 deg). The optical
    # axis is weakly observed (SD 0.17 mm): where the solver stops along it depends on the
    # CPU's rounding (issue 32): 0.26 mm / 0.012 deg with AVX512, 0.31 mm / 0.005 deg with
    # numpy's AVX512 kernels off and one BLAS thread; the old bound (0.3 mm) sat in between
    sd_t, sd_r = (
        float(np.linalg.norm(res.hand_eye_sd_mm)),
        float(np.linalg.norm(res.hand_eye_sd_deg)),
    )
    assert 0.1 < sd_t < 0.3 and sd_r < 0.02  # the posterior itself is stable (0.177 / 0.0101)
    assert et < 3 * sd_t and er < 3 * sd_r, (et, er, sd_t, sd_r)
    nt, nr = pose_error(X_nom, E6 @ X_true)
    assert nt > 1.0 and nr > 0.3  # there was something to find
    # the 8 unobservable DH directions keep their prior SD, the rest are learnt
    ratio = np.concatenate([res.sd_ratio[k] for k in ("delta_theta", "delta_a", "delta_d")])
    ratio = np.concatenate([ratio, res.sd_ratio["delta_alpha"]])
    assert np.all(ratio[GAUGE_INDICES[:6]] > 0.99)
    assert res.n_identified == 16
    assert np.all(res.singular_values[16:] < 0.05)
    # the camera chain fk(q) X over random configurations, against the TRUE arm
    qs = random_configurations(300, 0)
    before = fk_point_error(dh, dh_true, qs, X_nom, X_true)
    after = fk_point_error(res.dh, dh_true, qs, res.T_flange_camera, X_true)
    assert after["rot_rms_deg"] < before["rot_rms_deg"] / 5
    assert after["rms_mm"] < before["rms_mm"] * 0.8, (before, after)


def test_last_link_error_is_indistinguishable_from_the_hand_eye() -> None:
    """Closed form: an arm whose last DH link is off by E6 carrying the camera at X puts the
    camera exactly where the same arm with a nominal last link puts it at E6 X, in every
    configuration (so no data from a flange-mounted sensor can split them); E6 does not
    depend on q6, and the identity fails for an error on link 5 (the test can tell)."""
    from mmpa.apps.calibrate import last_link_error
    from mmpa.calibration.kinematic import random_configurations
    from mmpa.robot.description import DHParameters

    rng = np.random.default_rng(3)
    nom = DHParameters()

    def perturbed(links: list[int]) -> DHParameters:
        vals = {k: np.array(getattr(nom, k)) for k in ("a", "d", "alpha", "theta_offset")}
        for i in links:
            vals["a"][i] += rng.normal(0, 5e-4)
            vals["d"][i] += rng.normal(0, 5e-4)
            vals["alpha"][i] += rng.normal(0, np.deg2rad(0.05))
            vals["theta_offset"][i] += rng.normal(0, np.deg2rad(0.05))
        return DHParameters(**{k: tuple(float(x) for x in v) for k, v in vals.items()})

    X = _random_pose(rng, 0.3, 0.05)
    qs = random_configurations(50, 0)
    true6 = perturbed([5])
    E6 = last_link_error(nom, true6)
    assert pose_error(E6, np.eye(4))[0] > 0.3  # mm: a real error
    for q in qs:
        et, er = pose_error(fk(true6, q) @ X, fk(nom, q) @ E6 @ X)
        assert et < 1e-9 and er < 1e-9
    true5 = perturbed([4])
    E5 = last_link_error(nom, true5)  # identity: link 6 is nominal
    assert pose_error(E5, np.eye(4))[0] < 1e-9
    worst = max(pose_error(fk(true5, q) @ X, fk(nom, q) @ X)[0] for q in qs)
    assert worst > 0.1  # link 5's error moves the camera with the configuration


def test_joint_calibration_bad_input() -> None:
    from mmpa.calibration.kinematic import BoardObservations, calibrate_kinematics_hand_eye

    dh, _, X_nom, _, Y, K, obs = _joint_synthetic(0, 4)
    with pytest.raises(InvalidInputError, match="must agree"):
        BoardObservations(obs.q, obs.station, obs.object_points, obs.image_points[:-1])
    with pytest.raises(InvalidInputError, match=r"\(N, 6\)"):
        BoardObservations(obs.q[:, :5], obs.station, obs.object_points, obs.image_points)
    with pytest.raises(InvalidInputError, match="station indices"):
        BoardObservations(obs.q[:2], obs.station, obs.object_points, obs.image_points)
    few = BoardObservations.from_lists(
        list(obs.q[:2]), [SPEC.corners()] * 2, [obs.image_points[:24]] * 2
    )
    with pytest.raises(InvalidInputError, match="at least 3 stations"):
        calibrate_kinematics_hand_eye(dh, few, K, X_nom, Y)
    with pytest.raises(InvalidInputError, match="3x3"):
        calibrate_kinematics_hand_eye(dh, obs, np.eye(4), X_nom, Y)
    with pytest.raises(InvalidInputError, match="X0"):
        calibrate_kinematics_hand_eye(dh, obs, K, np.full((4, 4), np.nan), Y)
    flipped = X_nom @ make_T(np.diag([1.0, -1.0, -1.0]), np.zeros(3))  # looking away
    with pytest.raises(InvalidInputError, match="behind the camera"):
        calibrate_kinematics_hand_eye(dh, obs, K, flipped, Y)


# --- the board in the twin -----------------------------------------------------------------


@pytest.fixture(scope="module")
def world():
    w = board_world("0", SPEC, BoardPlacement(), errors=ErrorModelConfig())
    yield w
    w.close()


def _stations(w, n: int, q_ref=None):
    nominal = w.nominal
    Y = BoardPlacement().T_armbase_board(SPEC, nominal)
    k = w.camera.intrinsics
    return plan_stations(
        nominal.arm.dh,
        nominal.arm.q_limits,
        Y,
        nominal.camera.T_flange_camera,
        SPEC.corners(),
        k.K,
        (k.width, k.height),
        n,
        np.asarray(nominal.arm.view_bench if q_ref is None else q_ref, float),
        max_joint_step=2 * np.pi,
    )


def test_board_is_where_the_placement_says(world) -> None:
    T = T_map_board_truth(world, SPEC)
    expected = BoardPlacement().T_map_board(world.scene.site("0").pose2d, SPEC)
    assert np.allclose(T, expected, atol=1e-9)
    # added last, so every other body keeps its id
    assert world.model.body(BOARD_BODY).id == world.model.nbody - 1


def test_placement_for_site_clears_the_desk() -> None:
    from mmpa.backends.twin.scene import load_scene

    scene = load_scene()
    assert BoardPlacement.for_site(scene, "0") == BoardPlacement()  # no desk at the start
    for site in ("1", "2"):
        p = BoardPlacement.for_site(scene, site)
        bench = scene.workbench(scene.site(site).workbench)
        # the desk's near edge is 0.45 m ahead (centre 0.75 m ahead, 0.6 m deep)
        assert p.position[0] == pytest.approx(0.45 - 0.06, abs=0.01)
        assert p.tilt_deg == 70.0
        T = p.T_park_geom(SPEC)
        w, h = SPEC.face_size
        lowest = min(
            (T @ np.array([sx * w / 2, sy * h / 2, 0.0, 1.0]))[2]
            for sx in (-1, 1)
            for sy in (-1, 1)
        )
        assert lowest > bench.size[2]


def test_charuco_pose_against_truth(world) -> None:
    board = SPEC.cv_board()
    for st in _stations(world, 3):
        world.set_arm_configuration(st.q)
        K = world.camera.intrinsics.K
        C_true = inv(world.truth.T_map_camera()) @ T_map_board_truth(world, SPEC)
        # the detected corners lie where the true pose projects them (checks the texture
        # mapping and the board frame independently of PnP)
        det = detect_charuco(world.camera.capture_truth().color, board)
        assert len(det) == SPEC.n_corners
        p = det.object_points @ C_true[:3, :3].T + C_true[:3, 3]
        uv = p[:, :2] / p[:, 2:] * np.diag(K)[:2] + K[:2, 2]
        assert np.sqrt(np.mean(np.sum((uv - det.image_points) ** 2, axis=1))) < 0.3
        pose = board_pose(world.camera.capture().color, board, K)  # realistic noise
        et, er = pose_error(pose.T_camera_board, C_true)
        assert pose.rms_px < 0.5
        assert et < 1.0 and er < 0.2, (et, er)  # measured: <= 0.5 mm, <= 0.11 deg


def test_charuco_errors() -> None:
    board = SPEC.cv_board()
    det = detect_charuco(np.full((120, 160, 3), 200, np.uint8), board)
    assert len(det) == 0
    with pytest.raises(BoardNotFoundError, match="found 0 ChArUco corners"):
        estimate_board_pose(det, np.eye(3))
    with pytest.raises(InvalidInputError, match="3x3"):
        estimate_board_pose(det, np.eye(4))
    with pytest.raises(InvalidInputError, match="image"):
        detect_charuco(np.zeros((4, 4, 4), np.uint8), board)
    assert isinstance(det, CharucoDetection)


def test_pose_selection_is_diverse_and_reachable(world) -> None:
    st = _stations(world, 12)
    dh = world.nominal.arm.dh
    X = world.nominal.camera.T_flange_camera
    lo, hi = world.nominal.arm.q_limits
    G = np.array([fk(dh, s.q) for s in st])
    for s, g in zip(st, G, strict=True):
        assert np.all(s.q >= lo) and np.all(s.q <= hi)
        Y = inv(world.nominal.T_base_link_arm_base) @ BoardPlacement().T_park_geom(SPEC)
        assert np.allclose(g @ X, Y @ SPEC.T_geom_board @ s.T_board_camera, atol=1e-6)
    stats = pair_motion_stats(G)
    assert stats["min_pair_rotation_deg"] >= 15.0
    assert stats["axis_conditioning"] > 0.2
    assert len({(s.tilt_deg, s.azimuth_deg, s.roll_deg) for s in st}) == 12
    far = inv(world.nominal.T_base_link_arm_base) @ BoardPlacement(
        position=(3.0, 0.0, 0.3)
    ).T_park_geom(SPEC)
    k = world.camera.intrinsics
    with pytest.raises(UnreachableError, match="reachable board views"):
        plan_stations(
            dh,
            (lo, hi),
            far @ SPEC.T_geom_board,
            X,
            SPEC.corners(),
            k.K,
            (k.width, k.height),
            5,
            np.asarray(world.nominal.arm.view_bench),
        )


# --- end to end ----------------------------------------------------------------------------


def test_twin_recovers_hand_eye_without_dh_error(tmp_path) -> None:
    """Realistic camera noise, hand-eye error and mount compliance, but exact arm DH: the
    target (0.5 mm, 0.1 deg) is met (measured 0.1-0.2 mm, < 0.03 deg)."""
    from mmpa.apps.calibrate import HandEyeConfig, run_hand_eye

    errors = ErrorModelConfig(
        profile="realistic", seed=1, kinematics={"dh_length_sigma": 0.0, "dh_angle_sigma_deg": 0.0}
    )
    cfg = HandEyeConfig(stations=8, method="opencv")
    s = run_hand_eye(cfg, None, log=lambda m: None, errors=errors)
    assert s["nominal_error_trans_mm"] > 1.0  # there was something to calibrate
    assert s["error_trans_mm"] < 0.5 and s["error_rot_deg"] < 0.1, s
    assert s["stations_used"] == 8


# slow (16.5 s: 40 rendered views and the joint fit); the default run keeps the same
# procedure writing a robot file (test_examples.py: test_hand_eye_on_your_robot), the joint
# fit against a synthetic truth, the twin run without DH error, and the CLI's refusals
@pytest.mark.slow
def test_cli_hand_eye_realistic(tmp_path) -> None:
    """``mmpa calibrate hand-eye`` at its defaults (joint method, 40 stations at 0.32-0.62 m,
    tilts to 45 deg), realistic seed 0, against the twin's truth. The last DH link's error E6
    (1.5 mm on this robot) cannot be told from the hand-eye by any flange-mounted sensor
    (test_last_link_error_is_indistinguishable_from_the_hand_eye), so the identifiable
    hand-eye E6 X_true is met within the issue's 0.5 mm / 0.1 deg (measured 0.08 mm,
    0.013 deg; seeds 0-9: 0.06-0.35 mm, <= 0.014 deg), and the true one within E6 + 0.5."""
    from mmpa.cli.calibrate import register

    app = typer.Typer()
    register(app)
    out = tmp_path / "he"
    r = CliRunner().invoke(app, ["calibrate", "hand-eye", "--out", str(out)])
    assert r.exit_code == 0, r.output
    s = json.loads((out / "summary.json").read_text())
    assert s["profile"] == "realistic" and s["stations_used"] >= 36
    assert set(s["methods"]) == set(METHODS)
    assert s["method"] == "joint" and set(s["by_method"]) == {"opencv", "joint"}
    joint = s["by_method"]["joint"]
    assert s["error_identifiable_trans_mm"] == joint["error_vs_effective_trans_mm"]
    assert s["error_identifiable_trans_mm"] < 0.5 and s["error_identifiable_rot_deg"] < 0.1
    assert s["within_target_identifiable"]
    e6 = s["diagnostic"]["last_link_dh_error_trans_mm"]
    assert e6 > 1.0  # this robot's last link is off by more than the target
    assert s["error_trans_mm"] < e6 + 0.5 and s["error_rot_deg"] < 0.1
    assert s["error_rot_deg"] < s["nominal_error_rot_deg"] / 5
    assert s["diagnostic"]["true_flange_poses"]["error_trans_mm"] < 0.5
    # the per-station base priors stand for a real motion of the arm base (0.3 mm, 0.03 deg)
    shift, rot = s["diagnostic"]["arm_base_motion_mm_deg_max"]
    assert 0.1 < shift < 1.5 and 0.005 < rot < 0.1
    fk_err = s["kinematics"]["fk_error"]["camera"]
    assert fk_err["calibrated_joint"]["rot_rms_deg"] < fk_err["nominal_opencv"]["rot_rms_deg"]
    X = np.array(s["T_flange_camera"])
    doc = load_yaml(out / "hand_eye.yaml")
    assert np.allclose(doc["hand_eye"]["T_flange_camera"], X)
    assert doc["hand_eye"]["parent_frame"] == "flange"
    cam = CameraDescription.model_validate(doc["camera"])  # a robot file's camera section
    assert np.allclose(cam.T_flange_camera, X, atol=1e-9)
    et, er = pose_error(X, np.array(s["T_flange_camera_true"]))
    assert et == pytest.approx(s["error_trans_mm"]) and er == pytest.approx(s["error_rot_deg"])
    # written into a robot file that the next run takes (mmpa --robot FILE)
    from mmpa.cli.main import app as main_app
    from mmpa.robot.description import default_robot, set_default_robot
    from mmpa.robot.robot_file import load_robot

    robot, _ = load_robot(out / "robot.yaml")
    assert np.allclose(robot.camera.T_flange_camera, X, atol=1e-9)
    # with the calibrated kinematics: nominal + the reported corrections, also as a UR
    # calibration.conf that a robot file takes (arm: {calibration: ...})
    from mmpa.calibration.kinematic import apply_dh_deltas
    from mmpa.robot.robot_file import read_ur_calibration

    d = s["kinematics"]["deltas"]
    deltas = {
        "delta_theta": np.deg2rad(d["delta_theta"]),
        "delta_a": np.array(d["delta_a"]) * 1e-3,
        "delta_d": np.array(d["delta_d"]) * 1e-3,
        "delta_alpha": np.deg2rad(d["delta_alpha"]),
    }
    dh_cal = apply_dh_deltas(default_robot().arm.dh, deltas)
    for k in ("a", "d", "alpha", "theta_offset"):
        np.testing.assert_allclose(getattr(robot.arm.dh, k), getattr(dh_cal, k), atol=1e-12)
    conf = read_ur_calibration(out / "calibration.conf")
    for k, v in deltas.items():
        np.testing.assert_allclose(conf[k], v, atol=1e-12)
    try:
        r = CliRunner().invoke(main_app, ["--robot", str(out / "robot.yaml"), "robot", "show"])
        assert r.exit_code == 0, r.output
        assert np.allclose(default_robot().camera.T_flange_camera, X, atol=1e-9)
    finally:
        set_default_robot(None)


def test_cli_hand_eye_bad_input(tmp_path) -> None:
    from mmpa.cli.calibrate import register

    app = typer.Typer()
    register(app)
    r = CliRunner().invoke(
        app, ["calibrate", "hand-eye", "--profile", "bogus", "--out", str(tmp_path)]
    )
    assert r.exit_code == 2 and "bogus" in r.output
    r = CliRunner().invoke(
        app, ["calibrate", "hand-eye", "--site", "nowhere", "--out", str(tmp_path)]
    )
    assert r.exit_code == 2 and "nowhere" in r.output
    r = CliRunner().invoke(
        app, ["calibrate", "hand-eye", "--method", "magic", "--out", str(tmp_path)]
    )
    assert r.exit_code == 2 and "magic" in r.output


def test_cli_lidar_mount_recovers_the_true_mount(tmp_path) -> None:
    """A turn on the spot at Site 0 under realistic: the calibrated mount is closer to the
    TRUE mount than the nominal one by an order (measured seed 0: 0.62 vs 4.09 mm), and the
    robot file it writes carries it for the next run."""
    from mmpa.cli.calibrate import register
    from mmpa.robot.robot_file import load_robot

    app = typer.Typer()
    register(app)
    out = tmp_path / "lm"
    r = CliRunner().invoke(app, ["calibrate", "lidar-mount", "--out", str(out)])
    assert r.exit_code == 0, r.output
    s = json.loads((out / "summary.json").read_text())
    assert s["error_mm"] < 1.5 and s["error_mm"] < s["nominal_error_mm"] / 3
    err = np.hypot(*(np.array(s["mount"][:2]) - np.array(s["mount_true"][:2])))
    assert 1e3 * err == pytest.approx(s["error_mm"])
    robot, _ = load_robot(out / "robot.yaml")
    np.testing.assert_allclose(robot.lidar.T_base_link_laser_vec[:2], s["mount"][:2])
    bad = CliRunner().invoke(app, ["calibrate", "lidar-mount", "--out", str(out), "--profile", "x"])
    assert bad.exit_code == 2
