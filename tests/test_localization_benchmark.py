"""Issue 34 items 1-2: a CARMEN log as a ROS 2 bag, ``mmpa benchmark localization`` and its
statistics, the localization settings everywhere (robot file, ``--config``, ``--set``,
``--global``)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from mmpa.apps.benchmark import BenchmarkConfig, run_benchmark, run_pipeline
from mmpa.apps.benchmark_data import CarmenDataset, open_dataset
from mmpa.apps.convert import carmen_map, carmen_to_bag, increasing_stamps
from mmpa.apps.localization_settings import load_localization_config
from mmpa.apps.localize import LocalizeConfig
from mmpa.backends.bag.carmen import parse_carmen, relative_pose
from mmpa.backends.bag.reader import BagPlayback
from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.localization.config import AMCLConfig
from mmpa.localization.evaluation import error_statistics
from mmpa.localization.settings import LocalizationConfig, build_localizer, start_localizer
from mmpa.robot.robot_file import load_robot

REAL = Path("/work/shared/real-data/laser")
ROOT = Path(__file__).resolve().parents[1]

# ------------------------------------------------------------------ a synthetic CARMEN log

#: walls of a 8 m x 5 m room with a pillar (segments (x0, y0, x1, y1)), so no pose is alike
WALLS = [
    (-4, -2.5, 4, -2.5),
    (4, -2.5, 4, 2.5),
    (4, 2.5, -4, 2.5),
    (-4, 2.5, -4, -2.5),
    (1.0, 0.6, 1.6, 0.6),
    (1.6, 0.6, 1.6, 1.1),
    (1.6, 1.1, 1.0, 1.1),
    (1.0, 1.1, 1.0, 0.6),
    (-2.5, -2.5, -2.5, -1.2),
]


def _ranges(pose: np.ndarray, n: int = 180) -> np.ndarray:
    """Ray-cast ranges of ``n`` beams (CARMEN geometry: -pi/2 + i pi / n) at ``pose``."""
    a = pose[2] - np.pi / 2 + np.arange(n) * np.pi / n
    d = np.column_stack([np.cos(a), np.sin(a)])
    best = np.full(n, 81.9)
    for x0, y0, x1, y1 in WALLS:
        e = np.array([x1 - x0, y1 - y0])
        w = np.array([x0 - pose[0], y0 - pose[1]])
        den = d[:, 0] * (-e[1]) - d[:, 1] * (-e[0])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[0] * (-e[1]) - w[1] * (-e[0])) / den
            u = (d[:, 0] * w[1] - d[:, 1] * w[0]) / den
        hit = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
        best = np.where(hit & (t < best), t, best)
    return np.round(best, 3)


def _room_lines(n: int = 24, t0: float = 100.0, same_stamp: bool = False) -> list[str]:
    """A CARMEN log of ``n`` scans along an arc in the room, with wheel odometry that drifts
    (a 2 % scale and 0.01 rad per scan) and restarts at each corrected pose."""
    lines = ["PARAM robot_frontlaser_offset 0.0 nohost 0"]
    s = np.linspace(0, 1, n)
    poses = np.column_stack([-3 + 5.5 * s, -1.2 + 2.0 * s**2, 0.3 + 1.2 * s])
    for k, p in enumerate(poses):
        t = t0 if same_stamp else t0 + 2.0 * k
        if k:
            prev = poses[k - 1]
            inc = relative_pose(prev, p) * np.array([1.02, 1.02, 1.0]) + [0, 0, 0.01]
            c, sn = math.cos(prev[2]), math.sin(prev[2])
            step = np.array([c * inc[0] - sn * inc[1], sn * inc[0] + c * inc[1], inc[2]])
            mid, end = prev + 0.5 * step * [1, 1, 0], prev + step
            for q in (mid, end):
                lines.append(f"ODOM {q[0]:.6f} {q[1]:.6f} {q[2]:.6f} 0 0 0 {t} host {t}")
        r = " ".join(f"{v:g}" for v in _ranges(p))
        x, y, th = p
        lines.append(f"FLASER 180 {r} {x:.6f} {y:.6f} {th:.6f} {x} {y} {th} {t} host {t}")
        lines.append(f"ODOM {x:.6f} {y:.6f} {th:.6f} 0 0 0 {t} host {t}")  # restart
    return lines


@pytest.fixture(scope="module")
def room_log():
    return parse_carmen(_room_lines())


@pytest.fixture(scope="module")
def room_bag(room_log, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("room") / "room.mcap"
    carmen_to_bag(room_log, path, carmen_map(room_log))
    return path


# ------------------------------------------------------------------------- conversion


def test_a_carmen_log_round_trips_through_a_bag(room_log, room_bag) -> None:
    """The bag reader gives back the log's scans (float32 ranges, inf for no return, the
    same beam angles), its odometry increments and its corrected poses."""
    pb = BagPlayback.open(room_bag)
    n = len(room_log)
    assert len(pb.scans) == n and len(pb.odometry) == n
    for a, b in zip(room_log.scans, pb.scans, strict=True):
        np.testing.assert_allclose(b.angles, a.angles, atol=1e-6)
        fin = np.isfinite(a.ranges)
        assert np.array_equal(np.isfinite(b.ranges), fin) and (~fin).sum() == (~fin).sum()
        np.testing.assert_allclose(b.ranges[fin], a.ranges[fin], rtol=1e-7)
        assert b.frame_id == "laser"
    odo = np.array([pb.odometry_at(s.stamp).pose for s in pb.scans])
    for k in range(1, n):  # the log's increments, to double precision
        np.testing.assert_allclose(
            relative_pose(odo[k - 1], odo[k]), room_log.increments[k], atol=1e-9
        )
    truth = np.array([pb.truth_at(s.stamp) for s in pb.scans])
    np.testing.assert_allclose(truth, room_log.poses, atol=1e-9)
    # the drift is real: the odometry is not the truth
    assert np.hypot(*(odo[-1, :2] - room_log.poses[-1, :2])) > 0.05
    np.testing.assert_allclose(pb.static_transform("base_link", "laser"), np.eye(4), atol=1e-12)
    assert pb.initial_pose is not None
    np.testing.assert_allclose(pb.initial_pose[1], room_log.poses[0], atol=1e-9)


def test_stamps_that_do_not_increase_are_moved_and_counted() -> None:
    t, moved = increasing_stamps(np.array([5.0, 5.0, 4.9, 9.0, 9.2, 9.1]), 1.0)
    np.testing.assert_allclose(t, [5.0, 6.0, 7.0, 9.0, 9.2, 10.2])  # 9.2 increases: kept
    assert moved == 3


def test_convert_cli_writes_the_bag_and_the_map(tmp_path) -> None:
    from mmpa.cli.main import app

    log = tmp_path / "room.log"
    log.write_text("\n".join(_room_lines(6, same_stamp=True)) + "\n")
    bag, m = tmp_path / "room.mcap", tmp_path / "map" / "room.yaml"
    res = CliRunner().invoke(
        app, ["convert", "carmen", str(log), "--out", str(bag), "--map", str(m)]
    )
    assert res.exit_code == 0, res.output
    assert m.exists() and m.with_suffix(".pgm").exists()
    pb = BagPlayback.open(bag)
    assert np.all(np.diff([s.stamp for s in pb.scans]) >= 1.0 - 1e-9)  # all at t = 100 s
    again = CliRunner().invoke(app, ["convert", "carmen", str(log), "--out", str(bag)])
    assert again.exit_code == 2 and "exists" in again.output


# ------------------------------------------------------------------------ statistics


def test_the_statistics_match_an_independent_computation() -> None:
    """Errors set by construction on a synthetic trajectory; percentiles, shares and the
    divergence scan computed by hand."""
    rng = np.random.default_rng(3)
    n = 80
    s = np.linspace(0, 2 * np.pi, n)
    truth = np.column_stack([3 * np.cos(s), 3 * np.sin(s), s + np.pi / 2])
    err = rng.uniform(0.0, 0.2, n)
    err[10] = 2.0  # before scan 30: not a divergence
    err[47] = 0.7  # the first one after
    err[60] = 0.9
    ang = rng.uniform(-np.pi, np.pi, n)
    dyaw = rng.uniform(-0.2, 0.2, n)
    est = truth + np.column_stack([err * np.cos(ang), err * np.sin(ang), dyaw])
    est[5, 2] += 2 * np.pi  # a heading one turn off is no error
    t = 10.0 + 0.5 * np.arange(n)
    upd = rng.uniform(0.001, 0.01, n)
    st = error_statistics(est, truth, t, upd)

    def p95(v: np.ndarray) -> float:  # linear interpolation between order statistics
        v = np.sort(v)
        h = 0.95 * (len(v) - 1)
        lo = math.floor(h)
        return v[lo] + (h - lo) * (v[lo + 1] - v[lo])

    assert st["scans"] == n
    assert st["error_mean_mm"] == pytest.approx(1e3 * sum(err) / n, abs=1e-3)
    srt = sorted(err)
    assert st["error_median_mm"] == pytest.approx(1e3 * (srt[39] + srt[40]) / 2, abs=1e-3)
    assert st["error_p95_mm"] == pytest.approx(1e3 * p95(err), abs=1e-3)
    assert st["error_max_mm"] == pytest.approx(2000.0, abs=1e-3)
    yaw_deg = np.degrees(np.abs(dyaw))
    assert st["heading_error_max_deg"] == pytest.approx(yaw_deg.max(), abs=1e-3)
    assert st["heading_error_p95_deg"] == pytest.approx(p95(yaw_deg), abs=1e-3)
    assert st["within_5cm"] == pytest.approx(sum(e <= 0.05 for e in err) / n, abs=1e-4)
    assert st["within_10cm"] == pytest.approx(sum(e <= 0.10 for e in err) / n, abs=1e-4)
    assert st["diverged"] and st["diverged_at_scan"] == 47
    assert st["diverged_at_s"] == pytest.approx(0.5 * 47)
    assert st["update_max_ms"] == pytest.approx(1e3 * upd.max(), abs=1e-3)
    calm = error_statistics(truth, truth)
    assert not calm["diverged"] and calm["diverged_at_scan"] is None
    assert calm["within_5cm"] == 1.0 and calm["error_max_mm"] == 0.0


# --------------------------------------------------------------------- the benchmark


def test_benchmark_on_a_log_writes_the_folder(room_log, tmp_path) -> None:
    """AMCL (sparse-scan preset) tracks the synthetic room from the true pose; the folder
    holds the figures, the per-scan table, the plot and the settings that reproduce them."""
    log = tmp_path / "room.log"
    log.write_text("\n".join(_room_lines()) + "\n")
    ds = open_dataset(log)
    assert isinstance(ds, CarmenDataset) and len(ds) == len(room_log)
    cfg = BenchmarkConfig(amcl=AMCLConfig.sparse_scans(), divergence_after=5)
    res = run_benchmark(ds, cfg, tmp_path / "out")
    # measured: median 29-35 mm, max 47-74 mm (seeds 0-3)
    assert res["error_median_mm"] < 70 and not res["diverged"], res
    assert res["laser_pose_source"].startswith("carmen")
    for f in ("results.json", "estimate.csv", "trajectory.png", "config.yaml"):
        assert (tmp_path / "out" / f).exists()
    saved = load_localization_config(BenchmarkConfig, None, tmp_path / "out" / "config.yaml")
    assert saved == cfg
    table = np.loadtxt(tmp_path / "out" / "estimate.csv", delimiter=",", skiprows=1)
    assert table.shape == (len(room_log), 14)
    assert json.loads((tmp_path / "out" / "results.json").read_text())["scans"] == len(room_log)


def test_the_bag_loader_finds_the_mount_and_refuses_without_truth(room_bag, tmp_path) -> None:
    ds = open_dataset(room_bag)
    assert ds.format == "bag" and ds.laser_pose_source == "tf_static"
    run = run_pipeline(ds, BenchmarkConfig(max_scans=3, start=2))
    assert len(run.t) == 3 and run.refused is None  # AMCL has no refusals of its own
    hector = run_pipeline(ds, BenchmarkConfig(method="hector", max_scans=3))
    assert hector.refused is not None and len(hector.refused) == 3
    np.testing.assert_allclose(run.truth[0], ds[2].truth)
    with pytest.raises(InvalidInputError, match="start 99"):
        run_pipeline(ds, BenchmarkConfig(start=99))


def test_global_localization_only_for_particle_filters(room_log) -> None:
    grid = carmen_map(room_log)
    loc = build_localizer(LocalizationConfig(method="hector"), grid, np.zeros(3))
    with pytest.raises(InvalidInputError, match="--global"):
        start_localizer(loc, "hector", None, global_localization=True)
    amcl = build_localizer(LocalizationConfig(method="amcl"), grid, np.zeros(3))
    start_localizer(amcl, "amcl", None, global_localization=True)
    spread = np.ptp(amcl.particles[:, :2], axis=0)  # over the whole room
    assert spread[0] > 6 and spread[1] > 3.5


# ------------------------------------------------------------------------- settings


def test_set_reaches_the_localizer(room_bag, tmp_path) -> None:
    """``--set`` changes the result (the laser model and the method), and config.yaml says
    what ran."""
    from mmpa.cli.main import app

    base = ["localize", "--bag", str(room_bag), "--method", "amcl", "--max-scans", "8"]

    def run(name: str, *extra: str) -> tuple[np.ndarray, dict, dict]:
        out = tmp_path / name
        res = CliRunner().invoke(app, [*base, "--out", str(out), *extra])
        assert res.exit_code == 0, res.output
        est = np.loadtxt(out / "estimate.csv", delimiter=",", skiprows=1)[:, 1:4]
        cfg = yaml.safe_load((out / "config.yaml").read_text())
        return est, json.loads((out / "summary.json").read_text()), cfg

    a, sa, ca = run("a")
    b, _, cb = run("b", "--set", "amcl.laser_model_type=beam", "--set", "amcl.max_particles=600")
    a2, _, _ = run("a2")
    np.testing.assert_array_equal(a, a2)  # same settings, same seed: the same run
    assert np.abs(a - b).max() > 1e-6
    assert ca["amcl"]["laser_model_type"] == "likelihood_field_prob"  # the default
    assert cb["amcl"]["laser_model_type"] == "beam" and cb["amcl"]["max_particles"] == 600
    _, sh, ch = run("h", "--set", "method=hector")
    assert sh["method"] == "hector" and ch["method"] == "hector"
    assert sa["laser_pose_source"] == "tf_static" and sa["laser_pose"] == [0.0, 0.0, 0.0]
    bad = CliRunner().invoke(app, [*base, "--out", str(tmp_path / "x"), "--set", "amcl.alpa=1"])
    assert bad.exit_code == 2 and "amcl.alpa" in bad.output


def test_the_robot_file_section_is_layered_under_config_and_set(tmp_path) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text(
        "name: r\nlocalization:\n  method: amcl\n"
        "  amcl: {laser_model_type: beam, alpha1: 0.05, z_hit: 0.95}\n"
        "  initial_cov: [0.01, 0.01, 0.005]\n"
    )
    load_robot(robot)  # the description loader accepts the section
    cfg = load_localization_config(LocalizeConfig, robot)
    assert cfg.method == "amcl" and cfg.amcl.alpha1 == 0.05 and cfg.amcl.z_hit == 0.95
    assert cfg.amcl.alpha2 == 0.2 and cfg.initial_cov == (0.01, 0.01, 0.005)
    conf = tmp_path / "c.yaml"
    conf.write_text("amcl: {alpha1: 0.1}\n")
    cfg = load_localization_config(LocalizeConfig, robot, conf, {"seed": 4}, ["amcl.z_hit=0.9"])
    assert cfg.amcl.alpha1 == 0.1 and cfg.amcl.z_hit == 0.9 and cfg.seed == 4
    assert cfg.amcl.laser_model_type == "beam"  # the robot file's, kept
    cfg = load_localization_config(LocalizeConfig, robot, None, {"method": "hector"})
    assert cfg.method == "hector"


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ("localization: {amcl: {alpha1: -1}}", "robot.yaml: localization.amcl.alpha1"),
        ("localization: {amcl: {alpah1: 0.1}}", "localization.amcl.alpah1: Extra inputs"),
        ("localization: {method: nav2}", "localization.method: Value error, unknown method"),
        ("localization: {initial_cov: [0.1, 0, 0.1]}", "localization.initial_cov"),
        ("localization: {enhanced: {amcl: {alpha1: 0.1}}}", "set under amcl"),
        ("localization: 3", "localization: must be a mapping"),
    ],
)
def test_a_malformed_localization_section_is_refused_naming_the_key(
    tmp_path, section: str, message: str
) -> None:
    from mmpa.cli.main import app
    from mmpa.robot.description import set_default_robot

    robot = tmp_path / "robot.yaml"
    robot.write_text(f"name: r\n{section}\n")
    with pytest.raises(ConfigError, match=message):
        load_localization_config(LocalizeConfig, robot)
    try:  # refused when the robot file is loaded, before any command runs
        res = CliRunner().invoke(app, ["--robot", str(robot), "robot", "show"])
    finally:
        set_default_robot(None)
    assert res.exit_code == 2 and "robot.yaml" in res.output


def test_the_sparse_scans_yaml_is_the_preset() -> None:
    cfg = load_localization_config(
        LocalizationConfig, None, ROOT / "docs" / "amcl_sparse_scans.yaml"
    )
    assert cfg.method == "amcl" and cfg.amcl == AMCLConfig.sparse_scans()


# ------------------------------------------------------------------------- real logs


@pytest.mark.skipif(not (REAL / "intel-corrected.log.gz").exists(), reason=f"no {REAL}")
def test_benchmark_smoke_on_a_slice_of_the_intel_log(tmp_path) -> None:
    """AMCL with the sparse-scan preset over scans 0-39 of the Intel lab log, from the true
    pose, on the map built from the log: it tracks (measured: median 103 mm, max 281 mm over
    the first 100 scans, seed 0; the bound leaves a factor 2 on the median)."""
    ds = open_dataset(REAL / "intel-corrected.log.gz")
    cfg = BenchmarkConfig(amcl=AMCLConfig.sparse_scans(), max_scans=40)
    res = run_benchmark(ds, cfg, tmp_path)
    assert res["scans"] == 40 and res["scans_in_dataset"] == 910
    assert res["error_median_mm"] < 250 and not res["diverged"], res


def test_global_and_bad_settings_on_the_cli(room_bag, tmp_path) -> None:
    """``mmpa localize --global`` starts AMCL without a pose and says so; hector refuses it
    naming the option; ``mmpa navigate --set`` is checked before the twin is built."""
    from mmpa.cli.main import app

    base = ["localize", "--bag", str(room_bag), "--max-scans", "3"]
    res = CliRunner().invoke(app, [*base, "--method", "amcl", "--global", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["start"] == "global"
    assert yaml.safe_load((tmp_path / "config.yaml").read_text())["global_localization"] is True
    res = CliRunner().invoke(app, [*base, "--method", "hector", "--global", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "--global" in res.output
    res = CliRunner().invoke(app, ["navigate", "--to", "1", "--set", "hector.levels=0"])
    assert res.exit_code == 2 and "hector.levels" in res.output
