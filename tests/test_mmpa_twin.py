"""MMPA end to end in the twin: teach once, park elsewhere, IPE, adapted path; truth decides."""

from __future__ import annotations

import dataclasses
import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np
import pytest
from typer.testing import CliRunner

from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.cli.main import app
from mmpa.harness.ipe_eval import ipe_rows
from mmpa.harness.twin_site import MMPAExperimentConfig, TwinSite
from mmpa.robot.interfaces import PointCloud, RobotDevices


@pytest.fixture(scope="module")
def site1():
    """Site 1 in the reference twin: the mission's mechanics (IPE loop, refusals, re-park,
    execution) against the algorithms' accuracy without session-to-session errors."""
    ts = TwinSite(MMPAExperimentConfig(errors=ErrorModelConfig(profile="reference")), "1")
    yield ts
    ts.close()


# slow (8 s: a site taught anew; the suite budget): the default run keeps realistic teaching,
# rough parking, IPE and the needle within 1 mm (tests/test_examples.py:
# test_teach_and_repeat_in_the_twin, the demo's test in test_cli.py) and replay missing by
# tens of mm in the reference twin (test_ipe_recovers_the_parking_offset_and_the_tool_hits_the_dot)
@pytest.mark.slow
def test_ipe_and_tool_under_realistic_errors():
    """The realistic twin (a new camera session and maybe nudged objects at every park, an
    uncalibrated arm, hand-eye off by 1 mm / 0.5 deg): IPE still converges and MMPA still beats
    plain replay by an order of magnitude. Measured at Site 1, seed 0: IPE 2.7 mm mean over 3
    parks; the bounds leave room for the draw, not for a regression to replay."""
    with TwinSite(MMPAExperimentConfig(), "1") as ts:
        assert ts.cfg.errors.profile == "realistic"
        ts.park(session=1)
        res = ts.run_ipe(execute=False)
        truth = ts.parking_truth()
        row, _ = ipe_rows(res.ipe, truth)
        assert res.ok and row["ipe_ok"], res.reason
        assert row["E_t"] < 8e-3 and row["E_R"] < 0.02
        tool = ts.execute(res)
        assert tool < 8e-3
        ts.world.reset(site="1", pose2d=ts.parked_pose2d)
        assert ts.run_tmma() > 10 * tool


def test_teaching_records_what_the_robot_sees(site1):
    task, taught = site1.taught.task, site1.taught
    assert len(task.cloud) > 100_000
    assert task.path.rate_hz == 50.0 and len(task.path.t) > 200
    # the recorded tool path (nominal FK of encoders) matches the TRUE tip within the
    # kinematic error budget (DH N(0, 0.2 mm)): a few mm in the arm base, not cm
    tip_B = task.path.T_arm_base_tool[taught.key_index, :3, 3]
    tip_true_B = (np.linalg.inv(taught.T_map_Bo) @ np.r_[taught.key_tcp_map, 1])[:3]
    assert np.linalg.norm(tip_B - tip_true_B) < 0.005
    # the operator put the needle 30 mm above the red dot (truth from the scene)
    dot = next(i for i in site1.scene.workbench("site1_bench").items if i.kind == "dot")
    from mmpa.backends.twin.operator import T_map_desk

    T = T_map_desk(site1.world, "site1_bench")
    dot_map = T[:3, :3] @ np.array([*dot.xy, 0.03]) + T[:3, 3]
    assert np.linalg.norm(taught.key_tcp_map - dot_map) < 0.5e-3


def test_ipe_recovers_the_parking_offset_and_the_tool_hits_the_dot(site1):
    site1.park()
    before = site1.parking_truth()
    assert np.linalg.norm(before[:3, 3]) > 0.03  # a real parking error (Table 2: ~10 cm)
    # the IPE loop from the taught joints (paper Fig. 4): the park estimate now comes from the
    # localizer, ~1 mm in the reference twin, and as a prior it would aim the first view so
    # well that the camera never has to move back
    res = site1.run_ipe(
        site1.automation_config().model_copy(update={"localization_prior": False}),
        execute=False,
    )
    truth = site1.parking_truth()
    row, its = ipe_rows(res.ipe, truth)
    assert res.ok and row["ipe_ok"], res.reason
    assert row["E_t"] < 3e-3 and row["E_R"] < 0.008
    assert len(its) >= 2  # the camera moved back at least once (Fig. 4)
    # the full-resolution projective refinement ran and estimated a depth scale near 1
    pr = res.ipe.projective
    assert pr is not None and pr.ok, pr
    assert abs(pr.scale - 1.0) < 0.005
    tool = site1.execute(res)
    assert tool < 0.5e-3
    # TMMA from the same parked pose misses by tens of mm (paper Table 4: 68-85 mm)
    site1.world.reset(site="1", pose2d=site1.parked_pose2d)
    assert site1.run_tmma() > 0.03


def test_a_witness_view_confirms_the_estimate_or_refuses_a_slid_one(site1, monkeypatch):
    """``IPEConfig.witness`` (issue 19: a consistency check between equivalent views): a
    second view 3 cm sideways from the taught viewpoint agrees with the estimate within its
    tolerance; a final refinement that slid 6 mm at the converged view (injected: the
    witness's own refinement is left alone) is refused, and no estimate comes out."""
    import mmpa.ipe.loop as loop
    from mmpa.core.geometry import make_T

    def witnessed():
        a = site1.automation_config()
        return a.model_copy(
            update={"ipe": a.ipe.model_copy(update={"witness": 0.03}), "localization_prior": False}
        )

    site1.park()
    res = site1.run_ipe(witnessed(), execute=False)
    assert res.ok, res.reason
    assert res.ipe.witness_dT_B is not None
    d, ang = res.ipe.witness_disagreement
    tol = loop.IPEConfig().witness_tolerance
    assert d < tol[0] and ang < tol[1], (d, ang)
    truth = site1.parking_truth()
    row, _ = ipe_rows(res.ipe, truth)
    assert row["E_t"] < 3e-3  # the estimate itself as good as without the witness

    photometric, calls = loop._photometric, []

    def slid_once(*args, **kwargs):  # the converged view's refinement slides 6 mm
        out = photometric(*args, **kwargs)
        calls.append(out)
        if out is not None and len(calls) == 1:
            out = dataclasses.replace(out, T=out.T @ make_T(np.eye(3), [0.006, 0.0, 0.0]))
        return out

    monkeypatch.setattr(loop, "_photometric", slid_once)
    site1.park()
    res = site1.run_ipe(witnessed(), execute=False)
    assert len(calls) == 2 and calls[0] is not None  # the converged view, the witness
    assert not res.ok and res.ipe.dT_B is None and "witness view disagrees" in res.ipe.reason
    assert res.ipe.witness_disagreement[0] > 0.004


def test_failed_registration_stops_ipe_and_the_arm_stays(site1):
    site1.park()
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.3, 0.3, (5000, 3)) + np.array([0.0, 0.0, 0.6])
    junk = PointCloud(pts, rng.uniform(0, 1, (5000, 3)))
    task = dataclasses.replace(site1.taught.task, cloud=junk)
    from mmpa.missions.teach_repeat import automate

    w = site1.world
    res = automate(task, w)
    assert not res.ok and not res.executed and res.joint_path is None
    assert "registration failed" in res.reason
    # the arm took its views (the first one, then one step back for a wider view) and did not
    # move after the last failed registration
    assert 1 <= res.ipe.n_iterations <= 2
    np.testing.assert_allclose(w.arm.joint_positions(), res.ipe.iterations[-1].q, atol=1e-6)


def test_unreachable_sampling_pose_is_refused_before_motion(site1):
    w = site1.world
    site1.park()
    q0 = w.arm.joint_positions()
    q = site1.taught.task.q_sample.copy()
    q[1] = 10.0  # beyond the joint limit
    task = dataclasses.replace(site1.taught.task, q_sample=q)
    from mmpa.missions.teach_repeat import automate

    res = automate(task, w)
    assert not res.ok and "joint limits" in res.reason
    np.testing.assert_allclose(w.arm.joint_positions(), q0, atol=1e-6)


def test_path_out_of_reach_reparks_then_hits_the_dot(site1):
    """A base parked 30 cm behind its taught pose leaves the taught path out of the arm's
    reach: without a re-park MMPA refuses before any motion; with one (default) the base
    navigates by the IPE estimate, IPE runs again and the needle still hits the dot."""
    from mmpa.core.geometry import se2_compose, se2_to_T
    from mmpa.missions.teach_repeat import AutomationConfig

    w = site1.world
    pose = se2_compose(w.scene.site("1").pose2d, np.array([-0.30, 0.0, 0.0]))

    def park_far():
        w.reset(site="1", pose2d=pose)
        site1.parked_pose2d = pose
        site1.T_map_base_estimate = se2_to_T(*(pose + np.array([0.006, -0.004, 0.003])))

    park_far()
    res = site1.run_ipe(AutomationConfig(max_reparks=0), execute=False)
    assert not res.ok and "unreachable" in res.reason and not res.reparks
    park_far()
    res = site1.run_ipe(execute=False)
    assert res.ok, res.reason
    assert len(res.reparks) == 1 and len(res.ipe_before_repark) == 1
    # the requested motion is the parking offset (truth: 0.30 m forward, no turn) to ~1 cm
    np.testing.assert_allclose(res.reparks[0], [0.30, 0.0, 0.0], atol=0.015)
    truth = site1.parking_truth()
    assert np.linalg.norm(truth[:3, 3]) < 0.05  # the navigation brought it back within cm
    row, _ = ipe_rows(res.ipe, truth)
    assert row["E_t"] < 3e-3 and row["E_R"] < 0.008
    assert site1.execute(res) < 0.5e-3


def test_cli_teach_run_and_missing_task(tmp_path):
    cli = CliRunner()
    db = str(tmp_path / "t.db")
    r = cli.invoke(app, ["teach", "2", "needle_site2", "--db", db])
    assert r.exit_code == 0, r.output
    r = cli.invoke(app, ["tasks", "list", "--db", db])
    assert "needle_site2" in r.output
    r = cli.invoke(app, ["run", "needle_site2", "--db", db])
    assert r.exit_code == 0, r.output
    assert "tool_error_mm" in r.output and "estimate_E_t_mm" in r.output
    r = cli.invoke(app, ["run", "nope", "--db", db])
    assert r.exit_code == 2 and "needle_site2" in r.output  # lists the stored tasks
    r = cli.invoke(app, ["teach", "1", "needle_site2", "--db", db])
    assert r.exit_code == 2 and "site" in r.output


# slow (20 s: the scenes experiment); the default run keeps the refusal of a pure colour
# plane and the acceptance of a textured one (test_registration.py:
# test_pure_color_plane_is_refused_textured_plane_is_not)
@pytest.mark.slow
def test_scenes_ablation_refuses_the_pure_color_plane(tmp_path):
    """Table A.7's pattern: no pose from a plain plane, a good one from textured geometry."""
    from mmpa.harness.runner import run_experiment

    out = run_experiment("scenes", tmp_path, trials=1, overrides=["scenes=[A.1, B.3]"])
    rows = {r["scene"]: r for r in out.rows}
    assert not rows["A.1"]["ipe_ok"] and "registration failed" in rows["A.1"]["reason"]
    assert rows["B.3"]["ipe_ok"] and rows["B.3"]["E_t"] < 3e-3
    assert (tmp_path / "report.md").read_text().count("| A.1 |") == 1


@pytest.mark.slow
def test_ipe_and_path_targets_at_every_site(tmp_path):
    """Issue 18 goals under realistic on a small sample: IPE success 1.0, mean E_t <= 1 mm,
    E_R <= 0.003; needle tip mean <= 0.5 mm and max <= 1.5 mm, TMMA tens of mm (measured:
    E_t 0.55/0.44/0.51 mm, E_R 0.0009/0.0007/0.0007, tip max 0.39 mm)."""
    from mmpa.harness.runner import run_experiment

    out = run_experiment("path-accuracy", tmp_path, trials=5, overrides=["paper_method=false"])
    for site in ("1", "2", "2'"):
        r = [x for x in out.rows if x["site"] == site and x["method"] == "mmpa"]
        assert all(x["ipe_ok"] for x in r), [x["reason"] for x in r]
        assert np.mean([x["E_t"] for x in r]) <= 1e-3
        assert np.mean([x["E_R"] for x in r]) <= 0.003
        tips = [x["mmpa_mm"] for x in r if x["plan_ok"]]
        assert np.mean(tips) <= 0.5 and np.max(tips) <= 1.5
        assert np.mean([x["tmma_mm"] for x in r]) >= 20.0


def test_site2_prime_parking_tilts_like_table2(tmp_path):
    """Sampled parking at Site 2' gets z, roll and pitch from the bump; they must stay in the
    paper's range (Table 2: tz -4 +- 5 mm, pitch 0.8 +- 2.7 deg), not lift the drive wheels
    onto the bump (the old placement: tz -63 mm, pitch 5.7 deg)."""
    from mmpa.harness.runner import run_experiment

    out = run_experiment("parking", tmp_path, trials=12, overrides=['sites=["2\'"]'])
    tz = np.array([r["park_tz"] for r in out.rows])
    pitch = np.array([r["park_p_deg"] for r in out.rows])
    assert abs(tz.mean()) < 0.015 and tz.std() < 0.02
    assert abs(pitch.mean()) < 2.5 and np.abs(pitch).max() < 8.0
    assert np.abs(pitch).max() > 0.3  # the bump does tilt the base


class _ScaledDepthCamera:
    """A camera with a depth calibration fault: every depth times ``scale``."""

    def __init__(self, camera, scale: float) -> None:
        self._camera, self._scale = camera, scale

    def capture(self):
        f = self._camera.capture()
        return dataclasses.replace(f, depth=f.depth * self._scale)

    def __getattr__(self, name):
        return getattr(self._camera, name)


def test_depth_scale_fault_is_refused_and_the_arm_stays(site1, caplog):
    """A 3 % depth-scale fault (the audit's case: ok with a 14 mm wrong dT_B) is seen by the
    projective refinement's scale estimate and refused; the arm does not move after."""
    from mmpa.missions.teach_repeat import automate

    w = site1.world
    site1.park()
    cam = _ScaledDepthCamera(w.camera, 1.03)
    with caplog.at_level("WARNING", logger="mmpa"):
        res = automate(
            site1.taught.task,
            RobotDevices(w.nominal, arm=w.arm, camera=cam, gripper=w.gripper, clock=w),
        )
    assert any("the arm does not move" in r.getMessage() for r in caplog.records)
    assert not res.ok and not res.executed and res.joint_path is None
    assert "depth calibration fault" in res.reason, res.reason
    pr = res.ipe.iterations[-1].projective
    # the taught depth scaled onto the faulty one (scale and disparity offset together)
    assert pr.stages["effective_scale"] == pytest.approx(1.03, abs=0.01)
    np.testing.assert_allclose(w.arm.joint_positions(), res.ipe.iterations[-1].q, atol=1e-6)
