"""Property-based fuzzing of mmpa's loaders and public entry points: whatever the input,
the answer is a value or one of mmpa's errors (a clear message), never a traceback from
deeper down, never a hang. Bounded: ~a minute in all on 2 cores (``max_examples``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mmpa.core.errors import ConfigError, InvalidInputError, JointLimitError, MMPAError

FUZZ = settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    derandomize=True,  # the same cases on every run (determinism)
)

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**12), 10**12),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
yaml_docs = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=6), st.dictionaries(st.text(max_size=10), inner, max_size=6)
    ),
    max_leaves=25,
)


def _dump(doc: object) -> str:
    import yaml

    return yaml.safe_dump(doc, allow_unicode=True)


@FUZZ
@given(st.text(max_size=300))
def test_yaml_text_never_escapes(text: str) -> None:
    from mmpa.core.yamlio import load_yaml_text

    try:
        load_yaml_text(text, "fuzz")
    except ConfigError:
        pass


ROBOT_KEYS = ["name", "arm", "camera", "lidar", "gripper", "frames", "base"]
ARM_KEYS = ["model", "calibration", "dh", "qd_max", "q_min", "reach", "home"]


@FUZZ
@given(
    st.dictionaries(st.sampled_from(ROBOT_KEYS), yaml_docs, max_size=4),
    st.dictionaries(st.sampled_from(ARM_KEYS), yaml_docs, max_size=4),
)
def test_robot_file_never_escapes(tmp_path_factory, doc: dict, arm: dict) -> None:
    from mmpa.robot.robot_file import load_robot

    if arm:
        doc = {**doc, "arm": arm}
    p = tmp_path_factory.mktemp("robot") / "robot.yaml"
    p.write_text(_dump(doc))
    try:
        robot, _ = load_robot(p)
    except ConfigError:
        return
    assert robot.arm.q_limits[0].shape == (6,)


@FUZZ
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["errors.seed", "errors.profile", "automation.max_reparks", "x.y"]),
            st.text(max_size=15),
        ),
        max_size=3,
    )
)
def test_config_overrides_never_escape(sets: list[tuple[str, str]]) -> None:
    from mmpa.apps.demo import DemoConfig
    from mmpa.core.config import load_config

    try:
        load_config(DemoConfig, None, [f"{k}={v}" for k, v in sets])
    except ConfigError:
        pass


finite_or_not = st.floats(allow_nan=True, allow_infinity=True, width=64)


@FUZZ
@given(
    st.integers(0, 12),
    st.lists(finite_or_not, min_size=0, max_size=80),
    st.floats(min_value=1e-4, max_value=0.1),
)
def test_path_checks_and_retime_never_escape(n: int, values: list[float], dt: float) -> None:
    from mmpa.planning import retime
    from mmpa.robot.description import ArmDescription
    from mmpa.robot.limits import JointLimits, check_path

    arm = ArmDescription()
    lim = JointLimits.from_description(arm)
    q = np.resize(np.array(values or [0.0]), (n, 6)) if n else np.zeros((0, 6))
    t = np.arange(n) * dt
    try:
        check_path(t, q, lim)
    except (InvalidInputError, JointLimitError):
        pass
    try:
        path = retime(t, q, arm)
    except (InvalidInputError, JointLimitError):
        return
    check_path(path.t, path.q, lim)  # whatever retime returns is executable


@FUZZ
@given(
    st.lists(st.floats(-3, 3), min_size=6, max_size=6),
    st.lists(st.floats(-3, 3), min_size=6, max_size=6),
    st.integers(1, 400),
)
def test_streaming_limiter_stays_within_limits(target: list, v0: list, steps: int) -> None:
    from mmpa.robot.description import ArmDescription
    from mmpa.robot.limits import JointLimits, limit_setpoint

    lim = JointLimits.from_description(ArmDescription())
    dt = 0.002
    q, v = np.zeros(6), np.clip(np.array(v0), -lim.qd_max, lim.qd_max)
    for _ in range(steps):
        q_new, v_new = limit_setpoint(q, v, np.array(target), dt, lim)
        assert np.all(np.abs(q_new - q) <= lim.qd_max * dt * (1 + 1e-9))
        assert np.all(np.abs(v_new - v) <= lim.qdd_max * dt * (1 + 1e-6))
        q, v = q_new, v_new


@pytest.mark.parametrize("bad", [math.nan, -1.0, math.inf])
def test_error_model_fields_refuse_nan_and_negative(bad: float) -> None:
    from mmpa.backends.twin.error_model import ErrorModelConfig

    with pytest.raises((ValueError, MMPAError)):
        ErrorModelConfig.model_validate({"camera": {"depth_scale_sigma": bad}})


MAP_KEYS = [
    "image",
    "resolution",
    "origin",
    "occupied_thresh",
    "free_thresh",
    "negate",
    "mode",
    "reflectors",
]


@FUZZ
@given(
    st.dictionaries(st.sampled_from(MAP_KEYS), yaml_docs, max_size=8),
    st.binary(min_size=0, max_size=64),
    st.booleans(),
)
def test_map_loader_never_escapes(tmp_path_factory, doc: dict, pixels: bytes, good_image) -> None:
    from mmpa.maps.map_server import load_map

    d = tmp_path_factory.mktemp("map")
    if good_image:  # a valid 4 x 4 PGM so that the YAML fields get exercised
        (d / "m.pgm").write_bytes(b"P5\n4 4\n255\n" + (pixels * 16)[:16].ljust(16, b"\xfe"))
    else:  # whatever bytes: a corrupt image
        (d / "m.pgm").write_bytes(pixels)
    doc = {"image": "m.pgm", "resolution": 0.05, "origin": [0.0, 0.0, 0.0], **doc}
    (d / "map.yaml").write_text(_dump(doc))
    try:
        grid = load_map(d / "map.yaml")
    except ConfigError:
        return
    assert np.all(np.isin(grid.data, np.arange(-1, 101)))


@FUZZ
@given(st.lists(st.dictionaries(st.sampled_from(["id", "x", "y", "radius"]), scalars), max_size=5))
def test_reflector_map_never_escapes(tmp_path_factory, entries: list) -> None:
    from mmpa.maps.reflector_map import load_reflector_map

    p = tmp_path_factory.mktemp("rm") / "reflectors.yaml"
    p.write_text(_dump({"frame_id": "map", "reflectors": entries}))
    try:
        rm = load_reflector_map(p)
    except ConfigError:
        return
    assert np.all(np.isfinite(rm.xy)) and np.all(rm.radius > 0)


def _small_task():
    from mmpa.robot.description import ArmDescription
    from mmpa.robot.interfaces import PointCloud
    from mmpa.robot.kinematics import fk
    from mmpa.tasks import Task, ToolPath

    arm = ArmDescription()
    q = np.tile(np.array(arm.home), (5, 1))
    T = np.array([fk(arm.dh, qi) for qi in q])
    rng = np.random.default_rng(0)
    cloud = PointCloud(rng.normal(size=(20, 3)), rng.uniform(size=(20, 3)))
    path = ToolPath(np.arange(5) * 0.1, q, T, 10.0)
    return Task("fuzz", "1", np.eye(4), np.array(arm.home), np.eye(4), cloud, path)


@settings(FUZZ, max_examples=60)  # each case writes a bundle
@given(st.dictionaries(st.text(max_size=12), yaml_docs, max_size=3), st.booleans())
def test_bundle_reader_never_escapes(tmp_path_factory, changes: dict, drop: bool) -> None:
    import yaml

    from mmpa.tasks.bundle import read_bundle, write_bundle

    d = write_bundle(_small_task(), tmp_path_factory.mktemp("b") / "task")
    doc = yaml.safe_load((d / "task.yaml").read_text())
    if drop and doc:
        doc.pop(sorted(doc)[len(changes) % len(doc)])
    doc.update(changes)
    (d / "task.yaml").write_text(_dump(doc))
    try:
        read_bundle(d)
    except MMPAError:
        pass
