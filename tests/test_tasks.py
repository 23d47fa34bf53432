"""mmpa.tasks: the task record, its validation and the SQLite store (checksums, transactions,
schema versions). Bundles are in test_tasks_bundle.py, the CLI in test_tasks_cli.py."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import textwrap
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

from mmpa.core.errors import InvalidInputError, MMPAError, UnknownNameError
from mmpa.core.geometry import make_T, rpy_to_R
from mmpa.robot.interfaces import PointCloud
from mmpa.tasks import (
    FORMAT_VERSION,
    SCHEMA_VERSION,
    CorruptTaskError,
    Task,
    TaskExistsError,
    TaskNotFoundError,
    TaskStore,
    ToolPath,
    UnsupportedVersionError,
    default_store_path,
    formats,
)


def random_T(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    return make_T(rpy_to_R(*rng.uniform(-np.pi, np.pi, 3)), rng.normal(scale=scale, size=3))


def make_task(
    name: str = "valve",
    seed: int = 0,
    *,
    n_points: int = 500,
    n_waypoints: int = 40,
    colors: str = "8bit",
    gripper: bool = True,
    site: str = "1",
) -> Task:
    """A synthetic task with random (seeded) poses, joints, cloud and path."""
    rng = np.random.default_rng(seed)
    rate = 30.0
    T = np.stack([random_T(rng, 0.5) for _ in range(n_waypoints)])
    path = ToolPath(
        t=np.arange(n_waypoints) / rate,
        q=rng.uniform(-np.pi, np.pi, (n_waypoints, 6)),
        T_arm_base_tool=T,
        rate_hz=rate,
        gripper=rng.uniform(0, 1, n_waypoints) if gripper else None,
    )
    pts = rng.normal(size=(n_points, 3)) * [0.3, 0.2, 0.1] + [0, 0, 0.6]
    if colors == "8bit":  # what the camera delivers: uint8 / 255
        c = rng.integers(0, 256, (n_points, 3)) / 255.0
    elif colors == "float":
        c = rng.uniform(0, 1, (n_points, 3))
    else:
        c = None
    return Task(
        name=name,
        site=site,
        T_map_base_park=random_T(rng, 3.0),
        q_sample=rng.uniform(-np.pi, np.pi, 6),
        T_arm_base_camera=random_T(rng, 0.5),
        cloud=PointCloud(pts, c),
        path=path,
        robot_id="ur5e-7",
        created=datetime(2026, 11, 22, 9, 30, 15, 123456, tzinfo=UTC),
        description="switch the valve",
        meta={"target_x": 0.1234567890123, "trials": 3, "note": "red dot"},
    )


def assert_same_task(a: Task, b: Task, *, color_tol: float = 0.0) -> None:
    """Everything equal bit for bit, colors within ``color_tol``."""
    for f in ("name", "site", "robot_id", "created", "description", "meta", "format_version"):
        assert getattr(a, f) == getattr(b, f), f
    for f in ("T_map_base_park", "q_sample", "T_arm_base_camera"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    for f in ("t", "q", "T_arm_base_tool"):
        assert np.array_equal(getattr(a.path, f), getattr(b.path, f)), f
    assert a.path.rate_hz == b.path.rate_hz
    if a.path.gripper is None:
        assert b.path.gripper is None
    else:
        assert np.array_equal(a.path.gripper, b.path.gripper)
    assert np.array_equal(a.cloud.points, b.cloud.points)
    assert a.cloud.frame == b.cloud.frame
    if a.cloud.colors is None:
        assert b.cloud.colors is None
    else:
        assert np.abs(a.cloud.colors - b.cloud.colors).max() <= color_tol


@pytest.fixture
def store(tmp_path: Path):
    with TaskStore(tmp_path / "tasks.db") as s:
        yield s


# ------------------------------------------------------------------------------ validation


def _replace(task: Task, **kw) -> dict:
    d = {
        f: getattr(task, f)
        for f in (
            "name",
            "site",
            "T_map_base_park",
            "q_sample",
            "T_arm_base_camera",
            "cloud",
            "path",
            "robot_id",
            "created",
            "description",
            "meta",
            "format_version",
        )
    }
    d.update(kw)
    return d


def test_task_fields_are_read_only_float64_copies() -> None:
    q = np.zeros(6, dtype=np.float32)
    task = Task(**_replace(make_task(), q_sample=q))
    assert task.q_sample.dtype == np.float64
    q[0] = 1.0
    assert task.q_sample[0] == 0.0  # a copy
    with pytest.raises(ValueError):
        task.path.q[0, 0] = 1.0
    assert task.path.duration == pytest.approx(39 / 30.0)
    assert len(task.path) == 40 and task.has_colors


def test_naive_created_is_local_time_and_stored_in_utc() -> None:
    naive = datetime(2026, 1, 2, 3, 4, 5)
    task = Task(**_replace(make_task(), created=naive))
    assert task.created.tzinfo == UTC
    assert task.created == naive.astimezone(UTC)
    other = datetime(2026, 1, 2, 3, 4, 5, tzinfo=timezone(timedelta(hours=2)))
    assert Task(**_replace(make_task(), created=other)).created.hour == 1


def _bad_rotation() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] *= 1.01  # a scaled rotation is not rigid
    return T


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("name", "bad name", "name"),
        ("name", "", "name"),
        ("name", "..", "name"),
        ("site", "", "site"),
        ("T_map_base_park", np.eye(3), r"T_map_base_park must have shape \(4, 4\)"),
        ("T_map_base_park", np.full((4, 4), np.nan), "T_map_base_park contains NaN"),
        ("T_map_base_park", _bad_rotation(), "T_map_base_park rotation is not a proper"),
        ("T_arm_base_camera", np.diag([1.0, 1.0, -1.0, 1.0]), "T_arm_base_camera rotation"),
        ("q_sample", np.zeros(5), r"q_sample must have shape \(6,\)"),
        ("cloud", PointCloud(np.zeros((0, 3)), np.zeros((0, 3))), "cloud.points is empty"),
        ("cloud", PointCloud(np.zeros((2, 3)), np.full((2, 3), 1.5)), r"cloud.colors.*\[0, 1\]"),
        ("cloud", PointCloud(np.full((2, 3), np.inf), None), "cloud.points contains NaN or inf"),
        ("cloud", np.zeros((3, 3)), "cloud must be a PointCloud"),
        ("meta", {"x": [1, 2]}, r"meta\['x'\]"),
        ("meta", {"x": float("nan")}, r"meta\['x'\] must be finite"),
        ("format_version", FORMAT_VERSION + 1, "format_version"),
        ("created", "2026-01-01", "created must be a datetime"),
    ],
)
def test_task_validation_names_the_field(field: str, value: object, match: str) -> None:
    with pytest.raises(InvalidInputError, match=match):
        Task(**_replace(make_task(), **{field: value}))


def _path_kw(**kw) -> dict:
    p = make_task().path
    d = {
        "t": p.t,
        "q": p.q,
        "T_arm_base_tool": p.T_arm_base_tool,
        "rate_hz": p.rate_hz,
        "gripper": p.gripper,
    }
    d.update(kw)
    return d


@pytest.mark.parametrize(
    ("field", "make", "match"),
    [
        ("t", lambda t: t + 0.1, "path.t must start at 0"),
        ("t", lambda t: np.r_[t[:5], t[4], t[6:]], r"strictly increasing: t\[4\]"),
        ("t", lambda t: np.r_[t[:-1], np.nan], "path.t contains NaN"),
        ("t", lambda t: t[:-1], r"path.q must have shape \(39, 6\)"),
        ("q", lambda q: q[:, :5], r"path.q must have shape \(40, 6\)"),
        ("T_arm_base_tool", lambda T: T[:, :3], r"path.T_arm_base_tool must have shape"),
        ("T_arm_base_tool", lambda T: np.r_[T[:7], T[7:8] * 2, T[8:]], r"T_arm_base_tool\[7\]"),
        ("rate_hz", lambda r: 0.0, "path.rate_hz must be finite and > 0"),
        ("rate_hz", lambda r: "fast", "path.rate_hz must be a number"),
        ("gripper", lambda g: g + 1.0, r"path.gripper must lie in \[0, 1\]"),
        ("gripper", lambda g: g[:3], r"path.gripper must have shape \(40,\)"),
    ],
)
def test_tool_path_validation_names_the_field(field: str, make, match: str) -> None:
    kw = _path_kw()
    kw[field] = make(kw[field])
    with pytest.raises(InvalidInputError, match=match):
        ToolPath(**kw)


# ------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("gripper", [True, False])
def test_db_round_trip_is_bit_exact_for_8bit_colors(store: TaskStore, gripper: bool) -> None:
    task = make_task(gripper=gripper)
    store.save(task)
    assert_same_task(task, store.load("valve"))  # colors exact: uint8/255 survive uchar


def test_db_round_trip_float_colors_within_half_a_level(store: TaskStore) -> None:
    task = make_task(colors="float", n_points=2000)
    store.save(task)
    back = store.load("valve")
    err = np.abs(back.cloud.colors - task.cloud.colors)
    assert err.max() <= 0.5 / 255 + 1e-12
    assert err.max() > 0.1 / 255  # really quantized to 8 bits (the documented choice)
    assert_same_task(task, back, color_tol=0.5 / 255 + 1e-12)


def test_db_round_trip_colorless_cloud(store: TaskStore) -> None:
    task = make_task(colors="none")
    assert not task.has_colors
    store.save(task)
    back = store.load("valve")
    assert back.cloud.colors is None and not back.has_colors
    assert_same_task(task, back)
    assert not store.list()[0].has_colors


def test_memory_store_and_contains() -> None:
    with TaskStore(":memory:") as s:
        s.save(make_task("a"))
        assert "a" in s and "b" not in s
        assert s.names() == ["a"]


def test_open3d_reads_our_ply_and_we_read_open3ds(tmp_path: Path) -> None:
    """An independent PLY implementation agrees with ours in both directions."""
    import open3d as o3d

    task = make_task()
    ply = tmp_path / "ours.ply"
    ply.write_bytes(formats.cloud_to_ply(task.cloud))
    pc = o3d.io.read_point_cloud(str(ply))
    assert np.array_equal(np.asarray(pc.points), task.cloud.points)
    assert np.abs(np.asarray(pc.colors) - task.cloud.colors).max() < 1e-12

    theirs = tmp_path / "theirs.ply"
    o3d.io.write_point_cloud(str(theirs), pc, write_ascii=False)
    back = formats.ply_to_cloud(theirs.read_bytes(), "camera", str(theirs))
    assert np.allclose(back.points, task.cloud.points, atol=1e-6)
    assert np.abs(back.colors - task.cloud.colors).max() <= 0.5 / 255 + 1e-12


def test_list_summarizes_without_loading(store: TaskStore) -> None:
    assert store.list() == []
    store.save(make_task("b_task", seed=1, n_points=123, n_waypoints=10, site="2'"))
    store.save(make_task("a_task", seed=2))
    infos = store.list()
    assert [i.name for i in infos] == ["a_task", "b_task"]
    b = infos[1]
    assert (b.site, b.n_points, b.n_waypoints, b.robot_id) == ("2'", 123, 10, "ur5e-7")
    assert b.duration == pytest.approx(9 / 30.0) and b.rate_hz == 30.0
    assert b.created == datetime(2026, 11, 22, 9, 30, 15, 123456, tzinfo=UTC)


def test_missing_task_is_a_clear_error(store: TaskStore) -> None:
    with pytest.raises(TaskNotFoundError, match=r"no task 'nope'.*the store is empty"):
        store.load("nope")
    store.save(make_task("valve"))
    store.save(make_task("cup"))
    msg = r"no task 'nope' in .*tasks.db; stored: cup, valve"
    with pytest.raises(TaskNotFoundError, match=msg):
        store.load("nope")
    with pytest.raises(TaskNotFoundError):
        store.delete("nope")
    err = TaskNotFoundError("x", ["a"])
    assert isinstance(err, UnknownNameError) and isinstance(err, KeyError)
    assert isinstance(err, MMPAError) and err.valid == ["a"]


def test_overwrite_semantics(store: TaskStore) -> None:
    store.save(make_task(seed=0, site="1"))
    with pytest.raises(TaskExistsError, match=r"already exists"):
        store.save(make_task(seed=1, site="2"))
    assert store.load("valve").site == "1"  # the refused save changed nothing
    new = make_task(seed=1, site="2", n_points=77)
    store.save(new, overwrite=True)
    assert_same_task(new, store.load("valve"))
    con = sqlite3.connect(store.path)
    for table in ("tasks", "clouds", "paths"):
        assert con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0] == 1, table
    con.close()


def test_delete_removes_the_blobs(store: TaskStore) -> None:
    store.save(make_task("a"))
    store.save(make_task("b"))
    store.delete("a")
    assert store.names() == ["b"]
    con = sqlite3.connect(store.path)
    assert [r[0] for r in con.execute("SELECT task FROM clouds")] == ["b"]
    assert [r[0] for r in con.execute("SELECT task FROM paths")] == ["b"]
    con.close()


# ----------------------------------------------------------------------------- transactions


def _counts(db: Path) -> tuple[int, int, int]:
    con = sqlite3.connect(db)
    try:
        return tuple(
            con.execute(f"SELECT COUNT(*) FROM {t}").fetchone()[0]
            for t in ("tasks", "clouds", "paths")
        )
    finally:
        con.close()


def test_failure_mid_save_rolls_everything_back(store: TaskStore, monkeypatch) -> None:
    old = make_task(seed=0)
    store.save(old)
    calls = []

    def broken(cloud: PointCloud) -> bytes:
        calls.append(len(cloud))  # reached after the old task was deleted, path row written
        raise RuntimeError("disk full while serializing the cloud")

    monkeypatch.setattr("mmpa.tasks.store.cloud_to_ply", broken)
    with pytest.raises(RuntimeError, match=r"disk full"):
        store.save(make_task("other", seed=1))
    with pytest.raises(RuntimeError, match=r"disk full"):
        store.save(make_task(seed=2), overwrite=True)
    assert len(calls) == 2
    assert _counts(store.path) == (1, 1, 1)
    monkeypatch.undo()
    assert store.names() == ["valve"]
    assert_same_task(old, store.load("valve"))  # the overwritten task survived intact
    store.save(make_task("other", seed=1))  # the store still works
    assert _counts(store.path) == (2, 2, 2)


def test_crash_mid_save_leaves_no_half_task(tmp_path: Path) -> None:
    """A process killed inside the transaction (os._exit, no cleanup) leaves the store as it
    was: SQLite's journal rolls the half-written task back on the next open."""
    db = tmp_path / "tasks.db"
    with TaskStore(db) as s:
        s.save(make_task("kept"))
    script = textwrap.dedent(
        f"""
        import os, sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_tasks import make_task
        import mmpa.tasks.store as st
        def die(cloud):
            os._exit(3)
        st.cloud_to_ply = die
        st.TaskStore({str(db)!r}).save(make_task("kept", seed=5), overwrite=True)
        """
    )
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=120)
    assert res.returncode == 3, res.stderr.decode()
    with TaskStore(db) as s:
        assert s.names() == ["kept"]
        assert_same_task(make_task("kept"), s.load("kept"))
        assert s.con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    assert _counts(db) == (1, 1, 1)


# -------------------------------------------------------------------------- tamper & corrupt


def _exec(db: Path, sql: str, *args: object) -> None:
    con = sqlite3.connect(db)
    con.execute(sql, args)
    con.commit()
    con.close()


def _blob(db: Path, sql: str) -> bytes:
    con = sqlite3.connect(db)
    b = bytes(con.execute(sql).fetchone()[0])
    con.close()
    return b


def _flip(b: bytes, i: int) -> bytes:
    a = bytearray(b)
    a[i] ^= 0x01
    return bytes(a)


def test_flipped_byte_in_cloud_blob_is_refused(store: TaskStore) -> None:
    store.save(make_task())
    ply = _blob(store.path, "SELECT ply FROM clouds")
    _exec(store.path, "UPDATE clouds SET ply = ?", _flip(ply, len(ply) - 5))
    with pytest.raises(CorruptTaskError, match=r"task 'valve'.*cloud \(clouds.ply.*SHA-256"):
        store.load("valve")


def test_truncated_cloud_blob_is_refused(store: TaskStore) -> None:
    store.save(make_task())
    ply = _blob(store.path, "SELECT ply FROM clouds")
    _exec(store.path, "UPDATE clouds SET ply = ?", ply[: len(ply) // 2])
    with pytest.raises(CorruptTaskError, match=r"cloud.*SHA-256 mismatch"):
        store.load("valve")


@pytest.mark.parametrize("column", ["t", "q", "T_arm_base_tool", "gripper"])
def test_flipped_byte_in_path_blob_is_refused(store: TaskStore, column: str) -> None:
    store.save(make_task())
    b = _blob(store.path, f"SELECT {column} FROM paths")
    _exec(store.path, f"UPDATE paths SET {column} = ?", _flip(b, 11))
    with pytest.raises(CorruptTaskError, match=r"path arrays.*SHA-256 mismatch"):
        store.load("valve")


def test_flipped_byte_in_the_database_file_is_refused(tmp_path: Path) -> None:
    """Corruption on disk, below SQLite: one bit of the cloud's vertex data in the file."""
    db = tmp_path / "tasks.db"
    with TaskStore(db) as s:
        s.save(make_task(n_points=50))
        ply = _blob(db, "SELECT ply FROM clouds")
    raw = db.read_bytes()
    body = ply[ply.index(b"end_header\n") + 11 :]
    at = raw.index(body[:64])
    assert raw.count(body[:64]) == 1
    db.write_bytes(_flip(raw, at + 40))
    with TaskStore(db) as s, pytest.raises(CorruptTaskError, match=r"cloud.*SHA-256"):
        s.load("valve")


@pytest.mark.parametrize(
    ("sql", "args"),
    [
        ("UPDATE tasks SET site = ?", ("2",)),
        ("UPDATE tasks SET T_map_base_park = ?", ("[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]",)),
        ("UPDATE tasks SET rate_hz = ?", (60.0,)),
        ("UPDATE tasks SET meta_json = ?", ('{"trials":4}',)),
        ("UPDATE tasks SET created = ?", ("2020-01-01T00:00:00+00:00",)),
    ],
)
def test_altered_metadata_column_is_refused(store: TaskStore, sql: str, args: tuple) -> None:
    store.save(make_task())
    _exec(store.path, sql, *args)
    with pytest.raises(CorruptTaskError, match=r"metadata.*header_sha256"):
        store.load("valve")


def test_missing_blob_row_is_refused(store: TaskStore) -> None:
    store.save(make_task())
    _exec(store.path, "DELETE FROM clouds")
    with pytest.raises(CorruptTaskError, match=r"table 'clouds' is missing"):
        store.load("valve")


# --------------------------------------------------------------------------- schema / paths


def test_schema_version_recorded_and_newer_refused(tmp_path: Path) -> None:
    db = tmp_path / "tasks.db"
    with TaskStore(db) as s:
        assert s.schema_version() == SCHEMA_VERSION
    with TaskStore(db) as s:  # reopening does not migrate twice
        rows = s.con.execute("SELECT version FROM schema_version").fetchall()
        assert [r[0] for r in rows] == list(range(1, SCHEMA_VERSION + 1))
    _exec(db, "INSERT INTO schema_version VALUES (?, 'later', '9.9')", SCHEMA_VERSION + 1)
    with pytest.raises(UnsupportedVersionError, match=f"schema version {SCHEMA_VERSION + 1}"):
        TaskStore(db)


def test_task_of_newer_format_refused(store: TaskStore) -> None:
    store.save(make_task())
    _exec(store.path, "UPDATE tasks SET format_version = ?", FORMAT_VERSION + 1)
    with pytest.raises(UnsupportedVersionError, match=r"format version.*upgrade mmpa"):
        store.load("valve")


def test_not_a_task_store_is_refused(tmp_path: Path) -> None:
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(CorruptTaskError, match=r"junk.db: not a usable SQLite"):
        TaskStore(junk)
    other = tmp_path / "other.db"
    _exec(other, "CREATE TABLE things (x)")
    with pytest.raises(CorruptTaskError, match=r"not an mmpa task store"):
        TaskStore(other)
    with pytest.raises(InvalidInputError, match=r"is a directory"):
        TaskStore(tmp_path)


def test_default_store_path(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv("MMPA_TASKS_DB", raising=False)
    monkeypatch.delenv("XDG_DATA_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_store_path() == tmp_path / "home/.local/share/mmpa/tasks.db"
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert default_store_path() == tmp_path / "xdg/mmpa/tasks.db"
    monkeypatch.setenv("MMPA_TASKS_DB", str(tmp_path / "deep/dir/my.db"))
    assert default_store_path() == tmp_path / "deep/dir/my.db"
    with TaskStore() as s:  # creates the parent directories
        s.save(make_task())
    assert (tmp_path / "deep/dir/my.db").is_file()
    assert os.environ["MMPA_TASKS_DB"].endswith("my.db")


def test_older_schema_is_migrated_in_order(tmp_path: Path, monkeypatch) -> None:
    """A later mmpa adds migration 2: opening a version-1 store applies it once, keeps data."""
    import mmpa.tasks.store as st

    db = tmp_path / "tasks.db"
    with TaskStore(db) as s:
        s.save(make_task())
    monkeypatch.setattr(st, "SCHEMA_VERSION", 2)
    monkeypatch.setitem(
        st.MIGRATIONS, 2, ("ALTER TABLE tasks ADD COLUMN operator TEXT NOT NULL DEFAULT ''",)
    )
    with TaskStore(db) as s:
        assert s.schema_version() == 2
        cols = [r[1] for r in s.con.execute("PRAGMA table_info(tasks)")]
        assert "operator" in cols
        assert_same_task(make_task(), s.load("valve"))
    with TaskStore(db) as s:
        assert [r[0] for r in s.con.execute("SELECT version FROM schema_version")] == [1, 2]


def test_dataclasses_replace_revalidates() -> None:
    import dataclasses

    task = make_task()
    other = dataclasses.replace(task, name="valve_copy")
    assert other.name == "valve_copy" and np.array_equal(other.path.q, task.path.q)
    with pytest.raises(InvalidInputError, match=r"name"):
        dataclasses.replace(task, name="no/slash")
