"""Smoke runs of the paper 001 localization experiments (small, through the runner)."""

from __future__ import annotations

import json

import pytest

from mmpa.harness.runner import run_experiment


def test_localization_experiment_small(tmp_path) -> None:
    """One navigation trial and one kidnapping, the trial recorded (``--record``): its bag
    holds an estimate per scan, the last one off the recorded truth by the row's error."""
    import numpy as np

    from mmpa.backends.bag import messages as rm
    from mmpa.backends.bag.reader import BagPlayback, bag_topics, read_messages

    out = run_experiment(
        "localization",
        tmp_path,
        trials=1,
        overrides=["methods=[enhanced]", "kidnap_trials=1", "kidnap_duration=5"],
        record=tmp_path / "bags",
    )
    s = json.loads((tmp_path / "summary.json").read_text())["methods"]["enhanced"]
    assert s["err_pos_cm"] < 1.2 and s["success"] == 1.0
    assert s["kidnap_recovered"] == 1.0
    assert "paper position" in out.report and (tmp_path / "fig9_error_vs_time.png").exists()
    bag = tmp_path / "bags" / "method-enhanced-site-0-trial-0.mcap"
    counts = {k: v[1] for k, v in bag_topics(bag).items()}
    assert counts["/map"] == 1 and counts["/amcl_pose"] == counts["/scan"] > 100
    t, pose, _ = rm.from_pose_cov(read_messages(bag, ["/amcl_pose"])["/amcl_pose"][-1])
    truth = BagPlayback.open(bag).truth_at(t)
    err = float(np.hypot(*(pose[:2] - truth[:2])))
    assert err == pytest.approx(out.rows[0]["err_pos_m"], abs=1e-6)


# slow (14 s: a dropout run of two methods, recorded); the default run keeps a dropout
# trial of the methods (test_dropout_trial_does_not_depend_on_the_other_methods) and a
# recorded trial checked against its row (test_localization_experiment_small)
@pytest.mark.slow
def test_reflector_dropout_small(tmp_path) -> None:
    """A dropout run on a short route, recorded (``--record``): trilateration loses the robot
    while people hide the reflectors, the enhanced AMCL does not; the bag's estimates of the
    enhanced AMCL against its recorded truth give the row's peak errors during and after
    the dropout."""
    import numpy as np

    from mmpa.backends.bag import messages as rm
    from mmpa.backends.bag.reader import BagPlayback, bag_topics, read_messages

    out = run_experiment(
        "reflector-dropout",
        tmp_path,
        trials=1,
        overrides=[
            "methods=[trilateration,enhanced]",
            "waypoints=[[-0.35,0.94],[2.4,0.2],[2.0,-1.2]]",
            "dropout_start=5",
            "dropout_end=9",
            "visible_counts=[4,9]",
            "subsets_per_count=1",
            "settle_scans=5",
        ],
        record=tmp_path / "bags",
    )
    bag = tmp_path / "bags" / "method-enhanced-site-0-trial-0.mcap"
    counts = {k: v[1] for k, v in bag_topics(bag).items()}
    assert counts["/map"] == 1 and counts["/amcl_pose"] == counts["/scan"] > 50
    from mmpa.experiments.paper001.reflector_dropout import Config

    est = [rm.from_pose_cov(m) for m in read_messages(bag, ["/amcl_pose"])["/amcl_pose"]]
    pb = BagPlayback.open(bag)
    err = 1000 * np.array([np.hypot(*(p[:2] - pb.truth_at(t)[:2])) for t, p, _ in est])
    t = (np.arange(len(est)) + 1) / Config().scan_rate  # one estimate per scan step
    row = next(r for r in out.rows if r.get("method") == "enhanced")
    assert err[(t >= 5) & (t < 9)].max() == pytest.approx(row["err_peak_during_mm"], rel=1e-9)
    assert err[t >= 9].max() == pytest.approx(row["err_peak_after_mm"], rel=1e-9)
    s = json.loads((tmp_path / "summary.json").read_text())
    tri, enh = s["methods"]["trilateration"], s["methods"]["enhanced"]
    # trilateration alone loses the robot while the reflectors are hidden; ours does not
    assert tri["err_peak_during_mm"] > 300 and enh["err_mean_during_mm"] < 100
    # no spike: 2 reflectors left (one sometimes cut by a person), the error stays mm-level
    assert enh["err_p95_during_mm"] < 15 and enh["err_peak_during_mm"] < 30, enh
    # realistic profile (the default): with all reflectors in view the fix carries their range
    # walk and the 10 mm survey error; the honest fix (common bias estimated, survey error in
    # its covariance), the sharp laser beside it and the calibrated mount: 2.3 mm measured
    # before the dropout, 2.8 / 5.3 / 5.9 mm mean / p95 / peak during it (the overconfident
    # fix of before: 16.6 mm before, 10.0 / 15.5 mm p95 / peak during). In view, the
    # reflectors must not make it worse than without them
    assert enh["err_before_mm"] < 8
    assert enh["err_before_mm"] < 1.5 * enh["err_mean_during_mm"], enh
    assert s["visible"]["9"]["enhanced_err_mm"] < 6


def test_kidnap_trial_does_not_depend_on_what_ran_before(monkeypatch) -> None:
    """Each trial builds its own world, map, localizer and seeded generator: the same kidnap
    trial gives the same estimates run first or after other methods' and trials' runs."""
    import numpy as np

    from mmpa.experiments.paper001 import localization as loc_exp
    from mmpa.harness import twin_localization

    estimates: list[np.ndarray] = []
    make = twin_localization.make_localizer  # what twin_localizer() builds with

    def recording(*args, **kwargs):
        loc = make(*args, **kwargs)
        update = loc.update

        def update_and_record(odom, scan, force=False):
            est = update(odom, scan, force)
            estimates.append(np.asarray(loc.pose_at(odom), float).copy())
            return est

        loc.update = update_and_record
        return loc

    monkeypatch.setattr(twin_localization, "make_localizer", recording)
    cfg = loc_exp.Config(kidnap_duration=2.0)

    def kidnap(k: int, method: str) -> tuple[float, np.ndarray]:
        estimates.clear()
        r = loc_exp._kidnap(cfg, k, method)
        return r["recovery_s"], np.array(estimates)

    first = kidnap(1, "enhanced")
    kidnap(0, "amcl")
    kidnap(0, "enhanced-paper")
    again = kidnap(1, "enhanced")
    assert len(first[1]) > 5
    np.testing.assert_array_equal(first[1], again[1])
    assert first[0] == again[0] or (np.isnan(first[0]) and np.isnan(again[0]))


def test_dropout_trial_does_not_depend_on_the_other_methods() -> None:
    """A reflector-dropout trial (initial guess, reflectors left visible, each method's
    generator) is the same whichever methods run beside it: the enhanced AMCL's error trace
    with trilateration and T-AMCL in front of it equals its trace alone."""
    import numpy as np

    from mmpa.experiments.paper001 import reflector_dropout as rd

    short = {
        "waypoints": [[-0.35, 0.94], [2.4, 0.2]],
        "dropout_start": 4.0,
        "dropout_end": 7.0,
    }
    alone = rd._dropout_run(rd.Config(methods=["enhanced"], **short), 0)[1]
    mixed = rd._dropout_run(rd.Config(methods=["trilateration", "tamcl", "enhanced"], **short), 0)[
        1
    ]
    assert len(alone["enhanced"]) > 20
    np.testing.assert_array_equal(alone["enhanced"], mixed["enhanced"])
    np.testing.assert_array_equal(alone["visible"], mixed["visible"])


def test_only_our_method_gets_the_calibrated_mount(monkeypatch) -> None:
    """``calibrate_mount``: the mount from the turn on the spot goes to the methods in
    ``calibrated_methods`` (ours); the paper's methods keep the nominal one (None); one
    calibration per experiment; off: every method nominal."""
    import numpy as np

    from mmpa.experiments.paper001 import localization as loc_exp

    calls: list[str] = []

    def fake(errors, site, seed, resolution=0.05, cfg=None):
        calls.append(site)
        return np.array([0.301, -0.002, 0.0]), 0.001

    monkeypatch.setattr(loc_exp, "twin_mount_calibration", fake)
    methods = ["amcl", "enhanced", "enhanced-paper"]
    mounts = loc_exp.method_mounts(loc_exp.Config(), methods, "1")
    assert calls == ["1"]
    assert mounts["amcl"] is None and mounts["enhanced-paper"] is None
    np.testing.assert_array_equal(mounts["enhanced"], [0.301, -0.002, 0.0])
    off = loc_exp.method_mounts(loc_exp.Config(calibrate_mount=False), methods, "1")
    assert calls == ["1"] and all(v is None for v in off.values())


def test_the_twin_mount_calibration_is_remembered_by_its_arguments(monkeypatch) -> None:
    """One calibration per robot instance and settings in a process: the same arguments
    give the first result (a copy: the caller's changes stay its own), another seed, site
    or error model calibrates again."""
    import numpy as np

    from mmpa.backends.twin.error_model import ErrorModelConfig
    from mmpa.experiments.paper001 import localization as loc_exp

    calls: list[tuple] = []

    def fake(errors, site, seed, resolution, cfg):
        calls.append((errors.profile, site, seed))
        return np.array([0.3, 0.0, float(seed)]), 0.001

    monkeypatch.setattr(loc_exp, "_calibrate_mount", fake)
    monkeypatch.setattr(loc_exp, "_MOUNTS", {})
    real = ErrorModelConfig(profile="realistic")
    a, _ = loc_exp.twin_mount_calibration(real, "1", 7)
    a[0] = 99.0
    b, rms = loc_exp.twin_mount_calibration(ErrorModelConfig(profile="realistic"), "1", 7)
    np.testing.assert_array_equal(b, [0.3, 0.0, 7.0])
    assert rms == 0.001 and calls == [("realistic", "1", 7)]
    loc_exp.twin_mount_calibration(real, "1", 8)
    loc_exp.twin_mount_calibration(real, "2", 7)
    loc_exp.twin_mount_calibration(ErrorModelConfig(profile="ideal"), "1", 7)
    assert len(calls) == 4
