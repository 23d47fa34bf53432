"""``mmpa experiment NAME --record DIR``: one ROS 2 bag per trial (issue 20).

One IPE trial at Site 1 is run twice on the same seed, recorded and not (the second run
reuses the first one's taught task bundle through ``resume``, as a resumed run does, and
runs its trial afresh): the rows must be equal, and the trial's bag must hold what the
trial did, checked against the row (the IPE captures) and the taught truth (the parking
offset)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from mmpa.backends.bag import messages as rm
from mmpa.backends.bag.reader import BagCamera, BagPlayback, bag_topics, read_messages
from mmpa.core.errors import ConfigError
from mmpa.core.geometry import inv

SETS = ["sites=[1]", "paper_method=false"]


@pytest.fixture(scope="module")
def ipe_runs(tmp_path_factory):
    from mmpa.harness.runner import run_experiment

    d = tmp_path_factory.mktemp("exp_record")
    bags = d / "bags"
    rec = run_experiment("ipe", d / "rec", trials=1, overrides=SETS, record=bags)
    shutil.copytree(d / "rec" / "taught", d / "plain" / "taught")  # teach once
    plain = run_experiment("ipe", d / "plain", trials=1, overrides=SETS, resume=True)
    return {"dir": d, "bags": bags, "rec": rec, "plain": plain}


def test_every_trial_records_its_own_bag_and_the_rows_are_unchanged(ipe_runs) -> None:
    from mmpa.harness.recording import trial_bag_name
    from mmpa.harness.twin_trials import TIMING_COLUMNS

    rec, plain = ipe_runs["rec"], ipe_runs["plain"]
    assert [p.name for p in ipe_runs["bags"].iterdir()] == ["method-mmpa-site-1-trial-0.mcap"]
    assert trial_bag_name({"method": "mmpa"}, "1", 0) == "method-mmpa-site-1-trial-0.mcap"
    assert trial_bag_name({}, "2'", 3) == "site-2'-trial-3.mcap"
    assert trial_bag_name({"scene": "a b/c"}, "2", 0) == "scene-a_b_c-site-2-trial-0.mcap"
    assert rec.summary["bags"] == str(ipe_runs["bags"].resolve()) and "bags" not in plain.summary
    assert len(rec.rows) == len(plain.rows) == 1

    def strip(r: dict) -> dict:
        return {k: v for k, v in r.items() if k not in TIMING_COLUMNS}

    assert [strip(r) for r in rec.rows] == [strip(r) for r in plain.rows]
    assert rec.rows[0]["ipe_ok"]


def test_the_trial_bag_holds_the_trial(ipe_runs) -> None:
    from mmpa.harness.ipe_eval import pose_errors
    from mmpa.harness.twin_site import MMPAExperimentConfig
    from mmpa.robot.description import default_robot
    from mmpa.tasks import read_bundle

    bag = ipe_runs["bags"] / "method-mmpa-site-1-trial-0.mcap"
    row = ipe_runs["rec"].rows[0]
    counts = {k: v[1] for k, v in bag_topics(bag).items()}
    cfg = MMPAExperimentConfig()
    # the parking localization: the map once, one estimate per standing scan
    assert counts["/map"] == 1 and counts["/initialpose"] == 1
    assert counts["/amcl_pose"] == counts["/scan"] == cfg.park_scans
    # IPE's views: `frames` captures averaged per iteration, each in the bag
    frames = cfg.automation.ipe.frames
    assert counts["/camera/color/image_raw"] == row["iterations"] * frames
    assert counts["/camera/aligned_depth_to_color/image_raw"] == row["iterations"] * frames
    f = BagCamera(bag).capture()  # the backend reads the frames back
    assert f.color.shape[2] == 3 and (f.depth > 0).mean() > 0.5
    # the arm at >= 50 Hz through IPE's moves
    js = read_messages(bag, ["/joint_states"])["/joint_states"]
    t = np.array([rm.from_joint_state(m)[0] for m in js])
    assert len(t) > 100 and 0 < np.diff(t).min() and np.diff(t).max() <= 0.02 + 1e-9
    # the recorded true base, through the NOMINAL arm mount, gives the row's parking offset
    # against the arm base taught (the task bundle's truth; 1e-15 m apart measured)
    pb = BagPlayback.open(bag)
    assert pb.truth_base is not None
    (taught,) = list((ipe_runs["dir"] / "rec" / "taught").iterdir())
    T_map_Bo = np.array(json.loads(str(read_bundle(taught).meta["twin_T_map_arm_base"])))
    raw = read_messages(bag, ["/truth/base_pose"])["/truth/base_pose"]
    T_map_base = rm.from_pose(raw[-1].pose)
    T_map_Bk = T_map_base @ default_robot().T_base_link_arm_base
    e_r, e_t = pose_errors(np.eye(4), inv(T_map_Bk) @ T_map_Bo)
    assert row["park_E_t"] > 0.01  # a real parking offset, not zero
    assert e_t == pytest.approx(row["park_E_t"], abs=1e-4)
    assert e_r == pytest.approx(row["park_E_R"], abs=1e-3)


def test_an_experiment_that_cannot_record_says_so(tmp_path) -> None:
    from mmpa.harness.runner import run_experiment

    with pytest.raises(ConfigError, match="'planning-convergence' cannot record"):
        run_experiment("planning-convergence", tmp_path / "out", trials=1, record=tmp_path / "bags")
    assert not (tmp_path / "bags").exists() and not (tmp_path / "out").exists()
    (tmp_path / "file").write_text("")
    with pytest.raises(ConfigError, match="is a file"):
        run_experiment("parking", tmp_path / "p", trials=1, record=tmp_path / "file")


def test_experiment_command_has_a_record_option() -> None:
    from typer.testing import CliRunner

    from mmpa.cli.main import app

    out = CliRunner().invoke(app, ["experiment", "--help"], env={"COLUMNS": "200"})
    assert out.exit_code == 0 and "--record" in out.output
