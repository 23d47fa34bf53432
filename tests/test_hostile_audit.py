"""Regression tests for the defects found by the hostile re-audit of issue 22
(``benchmarks/audit_hostile.py``) and by ``tests/test_store_fuzz.py``: one test per fixed
defect, each input the one the audit used."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest

from mmpa.core.errors import ConfigError, CorruptTaskError, InvalidInputError
from mmpa.tasks import TaskStore
from test_tasks import assert_same_task, make_task


def test_deeply_nested_yaml_is_a_config_error_not_a_recursion_error(tmp_path: Path) -> None:
    """Audit: ``[`` * 5000 + ``]`` * 5000 raised RecursionError from PyYAML in every reader."""
    from mmpa.core.yamlio import load_yaml, load_yaml_text
    from mmpa.maps.map_server import load_map

    text = "[" * 5000 + "]" * 5000
    with pytest.raises(ConfigError, match=r"deep: YAML nested too deeply"):
        load_yaml_text(text, "deep")
    p = tmp_path / "map.yaml"
    p.write_text(text)
    for reader in (load_yaml, load_map):
        with pytest.raises(ConfigError, match=r"map\.yaml: YAML nested too deeply"):
            reader(p)
    assert load_yaml_text("[" * 3 + "]" * 3) == [[[]]]  # shallow nesting: fine


def _store(tmp_path: Path) -> Path:
    p = tmp_path / "t.db"
    with TaskStore(p) as s:
        s.save(make_task("valve"))
        s.save(make_task("cup", 1))
    return p


def test_a_null_or_blob_task_name_is_corrupt_not_returned(tmp_path: Path) -> None:
    """Fuzz: ``UPDATE tasks SET name = NULL`` made ``names()`` return ``[None, 'cup']``."""
    for value, kind in ((None, "NULL"), (b"\x01", "blob")):
        p = _store(tmp_path)
        con = sqlite3.connect(p)
        con.execute("UPDATE tasks SET name = ? WHERE name = 'valve'", (value,))
        con.commit()
        con.close()
        with TaskStore(p) as s:
            with pytest.raises(CorruptTaskError, match=rf"tasks\.name holds .*\({kind}\)"):
                s.names()
            with pytest.raises(CorruptTaskError):  # a lookup lists the names: same error
                s.load("nope")
            assert_same_task(make_task("cup", 1), s.load("cup"))  # the good row still loads
        p.unlink()


@pytest.mark.parametrize("version", [-1, 0])
def test_a_schema_version_below_1_is_corrupt(tmp_path: Path, version: int) -> None:
    """Fuzz: ``UPDATE schema_version SET version = -1`` raised KeyError (MIGRATIONS[0])."""
    p = _store(tmp_path)
    con = sqlite3.connect(p)
    con.execute("UPDATE schema_version SET version = ?", (version,))
    con.commit()
    con.close()
    with pytest.raises(CorruptTaskError, match=rf"schema_version\.version holds {version}"):
        TaskStore(p)


def _room(reflectors: bool = False):
    from mmpa.maps.occupancy import Box2D, rasterize

    walls = [Box2D((0.0, 3.0), (8.0, 0.1)), Box2D((0.0, -3.0), (8.0, 0.1))]
    L = np.array([[3.5, 2.5], [-3.5, 2.5], [3.5, -2.5], [-3.5, -2.5]]) if reflectors else None
    return rasterize(walls, (-4.5, -3.5, 4.5, 3.5), 0.05, L, 0.04)


def test_odometry_of_strings_is_refused() -> None:
    """Audit: ``update(np.array(['a', 'b', 'c']), ...)`` raised ValueError in finite_pose."""
    from mmpa.localization.amcl import finite_pose

    with pytest.raises(InvalidInputError, match=r"odometry pose must be 3 numbers"):
        finite_pose(np.array(["a", "b", "c"]), "odometry pose")
    with pytest.raises(InvalidInputError, match=r"initial pose must be 3 numbers"):
        finite_pose([1.0, None, object()], "initial pose")
    np.testing.assert_array_equal(finite_pose([1, 2, 3], "x"), [1.0, 2.0, 3.0])


@pytest.mark.parametrize(
    ("cov", "match"),
    [
        (np.full((3, 3), np.nan), "must be finite"),  # was LinAlgError (SVD)
        (
            -np.eye(3),
            "must be positive semi-definite, its smallest eigenvalue is -1",
        ),  # was accepted
        (np.eye(2), r"must be 3 x 3 .* got shape \(2, 2\)"),  # was numpy ValueError
        (np.array([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]]), "must be symmetric"),
    ],
)
def test_bad_initial_covariance_is_refused(cov: np.ndarray, match: str) -> None:
    from mmpa.localization.amcl import AMCL

    amcl = AMCL(_room(), np.zeros(3), rng=np.random.default_rng(0))
    with pytest.raises(InvalidInputError, match=f"initial covariance {match}"):
        amcl.initialize(np.zeros(3), cov)
    amcl.initialize(np.zeros(3), np.diag([0.01, 0.01, 0.0]))  # semi-definite: fine
    assert np.all(amcl.particles[:, 2] == 0.0)


def test_pose_at_refuses_nan_odometry() -> None:
    """Audit: AMCL.pose_at(NaN odometry) returned a pose (composed from the NaN)."""
    from mmpa.localization.amcl import AMCL

    amcl = AMCL(_room(), np.zeros(3), rng=np.random.default_rng(0))
    amcl.initialize(np.array([0.5, 0.0, 0.0]))
    with pytest.raises(InvalidInputError, match="odometry pose must be finite"):
        amcl.pose_at(np.array([np.nan, 0.0, 0.0]))


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"angle_increment": 0.0}, "angle_increment must not be 0"),  # was ZeroDivisionError
        (
            {"angle_increment": float("nan")},
            "angle_increment must be a number, got nan",
        ),  # ValueError
        ({"range_max": float("nan")}, "range_max must be a number, got nan"),  # was accepted
        ({"ranges": [1.0, 1.0, 1.0]}, "ranges must be a numpy array"),  # AttributeError
        ({"angle_min": float("-inf")}, "angle_min must be finite"),  # was OverflowError
        (
            {"angle_max": -1.0},
            r"angles \[0.0, -1.0\] step 0.5 hold no beam",
        ),  # a 0-beam scan was accepted
    ],
)
def test_malformed_laser_scan_is_refused(fields: dict, match: str) -> None:
    from mmpa.robot.interfaces import LaserScan

    kw = dict(
        angle_min=0.0,
        angle_max=1.0,
        angle_increment=0.5,
        time_increment=0.0,
        scan_time=0.1,
        range_min=0.05,
        range_max=10.0,
        ranges=np.ones(3),
        intensities=np.zeros(3),
    )
    assert LaserScan(**kw).ranges.shape == (3,)
    if fields.get("angle_max") == -1.0:
        kw.update(ranges=np.zeros(0), intensities=np.zeros(0))
    kw.update(fields)
    with pytest.raises(InvalidInputError, match=f"scan {match}"):
        LaserScan(**kw)


def test_point_cloud_of_text_is_refused() -> None:
    """Audit: register(PointCloud(text)) raised ValueError deep in the pipeline."""
    from mmpa.robot.interfaces import PointCloud

    with pytest.raises(InvalidInputError, match=r"points must be numbers, got dtype <U1"):
        PointCloud(np.full((10, 3), "x"), None)
    with pytest.raises(InvalidInputError, match=r"colors must be numbers"):
        PointCloud(np.zeros((2, 3)), np.full((2, 3), None))
    assert len(PointCloud(np.zeros((2, 3), np.float32), np.zeros((2, 3), np.uint8))) == 2


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ("timeout=.inf", r"timeout: Input should be a finite number"),  # drove forever
        ("controller.k_v=-.inf", r"controller\.k_v: Input should be a finite number"),
        ("controller.max_v=-0.4", r"controller\.max_v: Input should be greater than 0"),
        ("controller.max_v=0", r"controller\.max_v: Input should be greater than 0"),
        ("controller.pos_tol=-0.01", r"controller\.pos_tol: .*greater than or equal to 0"),
        ("navigate.planner.inflation_radius=.inf", r"inflation_radius: .*finite number"),
        ("navigate.follower.final.max_w=.nan", r"final\.max_w: .*finite number"),
        ("localization=bogus", r"localization: .*unknown localization 'bogus'; valid: truth"),
        ("arm_view=[.nan, 0, 0, 0, 0, 0]", r"arm_view\.0: Input should be a finite number"),
    ],
)
def test_demo_config_refuses_non_finite_and_out_of_range_values(override: str, match: str) -> None:
    """Audit: each of these ``--set`` overrides was accepted by ``load_config``."""
    from mmpa.apps.demo import DemoConfig
    from mmpa.core.config import load_config

    with pytest.raises(ConfigError, match=match):
        load_config(DemoConfig, None, [override])
    ok = load_config(DemoConfig, None, ["localization=truth", "navigate.follower.final.pos_tol=0"])
    assert ok.localization == "truth" and ok.navigate.follower.final.pos_tol == 0.0


@pytest.mark.parametrize("method", ["trilateration", "hector"])
def test_localizers_without_a_particle_cloud_check_cov_and_odometry_too(method: str) -> None:
    """Audit: trilateration and Hector accepted a NaN / negative / 2 x 2 initial covariance
    (they do not use it) and returned a pose from ``pose_at(NaN odometry)``."""
    from mmpa.localization.localizer import make_localizer

    loc = make_localizer(method, _room(reflectors=True), np.zeros(3))
    for cov in (np.full((3, 3), np.nan), -np.eye(3), np.eye(2)):
        with pytest.raises(InvalidInputError, match="initial covariance"):
            loc.initialize(np.zeros(3), cov)
    loc.initialize(np.array([0.5, 0.0, 0.1]), np.eye(3) * 0.01)
    np.testing.assert_array_equal(loc.pose_at(np.zeros(3)), [0.5, 0.0, 0.1])
    with pytest.raises(InvalidInputError, match="odometry pose must be finite"):
        loc.pose_at(np.array([np.nan, 0.0, 0.0]))


def test_make_localizer_refuses_a_nan_laser_pose() -> None:
    """Audit: ``make_localizer('amcl', grid, [nan, 0, 0])`` built a filter on a NaN mount."""
    from mmpa.localization.localizer import METHODS, make_localizer

    for method in METHODS:
        with pytest.raises(InvalidInputError, match="laser pose must be finite"):
            make_localizer(method, _room(reflectors=True), np.array([np.nan, 0.0, 0.0]))


@pytest.mark.parametrize("method", ["amcl", "enhanced", "trilateration", "tamcl", "hector"])
def test_update_without_a_scan_is_refused(method: str) -> None:
    """Audit: ``update(odom, None)`` raised AttributeError inside every localizer."""
    from mmpa.localization.localizer import make_localizer

    loc = make_localizer(method, _room(reflectors=True), np.zeros(3), np.random.default_rng(0))
    loc.initialize(np.zeros(3))
    for bad in (None, np.ones(360)):
        with pytest.raises(InvalidInputError, match="scan must be a LaserScan, got"):
            loc.update(np.zeros(3), bad, force=True)


def test_schema_text_that_is_not_utf8_is_corrupt(tmp_path: Path) -> None:
    """Fuzz (tests/test_store_fuzz.py): byte 0x80 written at 3/32 of the file, inside the
    schema's text, made sqlite3 raise UnicodeDecodeError (not an sqlite3.Error) out of
    TaskStore's constructor; it is now a CorruptTaskError naming the file."""
    from test_store_fuzz import SAVED

    p = tmp_path / "t.db"
    with TaskStore(p) as s:
        for task in SAVED.values():
            s.save(task)
    raw = bytearray(p.read_bytes())
    raw[int(0.09375 * len(raw))] = 0x80
    p.write_bytes(bytes(raw))
    with pytest.raises(CorruptTaskError, match=r"t\.db: .*text that is not UTF-8"):
        with TaskStore(p) as s:
            s.list()


@pytest.mark.parametrize(
    ("field", "override", "message"),
    [
        ("arm.reach", {"arm": {"reach": -0.85}}, "greater than 0"),
        ("arm.home", {"arm": {"home": [9, 0, 0, 0, 0, 0]}}, "outside the joint limits"),
        ("base.wheel_radius", {"base": {"wheel_radius": 0}}, "greater than 0"),
        ("base.mass", {"base": {"mass": float("nan")}}, "finite number"),
        ("camera.color.width", {"camera": {"color": {"width": 0}}}, "greater than 0"),
        ("camera.min_range", {"camera": {"min_range": 5}}, "must be below camera.max_range"),
        ("lidar.num_beams", {"lidar": {"num_beams": 0}}, "greater than 0"),
        ("lidar.range_max", {"lidar": {"range_max": 0.01}}, "must be below lidar.range_max"),
        ("gripper.stroke", {"gripper": {"stroke": -0.085}}, "greater than 0"),
        ("photosensor.max_range", {"photosensor": {"max_range": -0.5}}, "greater than 0"),
        ("arm.dh.a", {"arm": {"dh": {"a": [1e300, 0, 0, 0, 0, 0]}}}, "within 10 m"),
    ],
)
def test_robot_description_refuses_impossible_values(field, override, message) -> None:
    """The audit's 21 silent robot-file cases (a negative reach, a home outside the limits, a
    zero-width image, a lidar range_max under range_min, a 1e300 m link from a calibration
    file ...): refused naming the field; the defaults still load."""
    from pydantic import ValidationError

    from mmpa.robot.description import RobotDescription

    RobotDescription()
    with pytest.raises(ValidationError, match=message) as e:
        RobotDescription(**override)
    assert field.split(".")[0] in str(e.value)


@pytest.mark.parametrize("value", ["0:", "[realistic]", "{a: 1}"])
def test_a_profile_that_is_not_a_name_is_refused(value: str) -> None:
    """``--set errors.profile=0:`` (YAML: a mapping) raised ``TypeError: unhashable type``
    from the profile lookup (found by tests/test_fuzz.py under xdist); now a ConfigError
    naming the field."""
    from mmpa.apps.demo import DemoConfig
    from mmpa.core.config import load_config
    from mmpa.core.errors import ConfigError

    with pytest.raises(ConfigError, match=r"errors\.profile"):
        load_config(DemoConfig, None, [f"errors.profile={value}"])
