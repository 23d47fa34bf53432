"""Hypothesis fuzz of the SQLite task store (issue 22): random bytes written at random offsets
of the database file, and random values written into random columns with raw sqlite3.
Every read through the store's API (``list``, ``load``, ``names``) either returns exactly
what was saved or raises an mmpa error (CorruptTaskError, TaskNotFoundError, ...): never
another exception type, never a task or summary that differs from the saved one.
Derandomized and bounded (``max_examples``): a few seconds on one core."""

from __future__ import annotations

import math
import sqlite3
from pathlib import Path

import pytest
from hypothesis import HealthCheck, assume, event, given, settings
from hypothesis import strategies as st

from mmpa.core.errors import MMPAError
from mmpa.tasks import Task, TaskStore
from test_tasks import assert_same_task, make_task

FUZZ = settings(
    max_examples=250,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
SAVED: dict[str, Task] = {
    "valve": make_task("valve", 0, n_points=60, n_waypoints=6),
    "cup": make_task("cup", 1, n_points=40, n_waypoints=4, colors="none", gripper=False),
}


@pytest.fixture(scope="module")
def master(tmp_path_factory) -> bytes:
    """The bytes of a store holding the two tasks of SAVED."""
    p = tmp_path_factory.mktemp("fuzz") / "master.db"
    with TaskStore(p) as s:
        for task in SAVED.values():
            s.save(task)
    return p.read_bytes()


@pytest.fixture(scope="module")
def columns(tmp_path_factory, master: bytes) -> list[tuple[str, str]]:
    p = tmp_path_factory.mktemp("cols") / "c.db"
    p.write_bytes(master)
    con = sqlite3.connect(p)
    cols = [
        (t, r[1])
        for t in ("tasks", "clouds", "paths", "schema_version")
        for r in con.execute(f"PRAGMA table_info({t})")
    ]
    con.close()
    return cols


def _read_everything(p: Path) -> int:
    """Every read of the API on ``p``; each one returns the saved content or raises an
    MMPAError (``names`` is an unverified index: it must hold text). Returns how many
    reads returned content (checked against SAVED)."""
    returned = 0
    try:
        store = TaskStore(p, timeout=0.5)
    except MMPAError:
        return 0
    with store as s:
        try:
            infos = s.list()
        except MMPAError:
            pass
        else:
            returned += 1
            for info in infos:
                assert info.name in SAVED, f"list() shows a task never saved: {info.name!r}"
                t = SAVED[info.name]
                assert (info.site, info.robot_id, info.description) == (
                    t.site,
                    t.robot_id,
                    t.description,
                )
                assert info.created == t.created
                assert info.n_points == len(t.cloud)
                assert info.n_waypoints == len(t.path.t)
                assert info.has_colors == (t.cloud.colors is not None)
                assert info.rate_hz == t.path.rate_hz
                assert math.isclose(info.duration, float(t.path.t[-1]), rel_tol=0, abs_tol=0)
        try:
            names = s.names()
        except MMPAError:
            names = list(SAVED)
        else:
            returned += 1  # an index, not verified (a renamed row shows): text only
            assert all(isinstance(n, str) for n in names), names
        for name in SAVED:
            try:
                task = s.load(name)
            except MMPAError:
                continue
            returned += 1
            assert_same_task(SAVED[name], task)
    return returned


@FUZZ
@given(
    st.lists(
        st.tuples(st.floats(0.0, 1.0, exclude_max=True), st.binary(min_size=1, max_size=24)),
        min_size=1,
        max_size=4,
    )
)
def test_random_bytes_in_the_file_never_give_a_wrong_task(
    tmp_path_factory, master: bytes, hits: list[tuple[float, bytes]]
) -> None:
    raw = bytearray(master)
    for where, junk in hits:
        off = int(where * len(raw))
        raw[off : off + len(junk)] = junk
    raw = raw[: len(master)]
    assume(bytes(raw) != master)
    p = tmp_path_factory.mktemp("bytes") / "t.db"
    p.write_bytes(bytes(raw))
    event(f"reads that returned content (verified): {_read_everything(p)} of 4")


values = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.binary(max_size=20),
)


@FUZZ
@given(st.data(), values, st.sampled_from(["valve", "cup", None]))
def test_random_values_in_random_columns_never_give_a_wrong_task(
    tmp_path_factory, master: bytes, columns: list[tuple[str, str]], data, value, row
) -> None:
    table, column = data.draw(st.sampled_from(columns), label="column")
    p = tmp_path_factory.mktemp("cols") / "t.db"
    p.write_bytes(master)
    con = sqlite3.connect(p)
    key = {"tasks": "name", "clouds": "task", "paths": "task"}.get(table)
    try:
        if key is None or row is None:  # every row of the table
            con.execute(f"UPDATE {table} SET {column} = ?", (value,))
        else:
            con.execute(f"UPDATE {table} SET {column} = ? WHERE {key} = ?", (value, row))
        con.commit()
    except sqlite3.Error:  # NOT NULL, a type the primary key refuses: not a corruption
        assume(False)
    finally:
        con.close()
    event(f"reads that returned content (verified): {_read_everything(p)} of 4")


def test_the_fuzz_checks_can_fail(tmp_path, master: bytes) -> None:
    """The oracle is not vacuous: an intact copy returns everything (2 tasks + list +
    names), and a hand-made wrong answer is caught by the same comparison."""
    p = tmp_path / "ok.db"
    p.write_bytes(master)
    assert _read_everything(p) == 4
    with TaskStore(p) as s:
        other = make_task("valve", 7, n_points=60, n_waypoints=6)
        with pytest.raises(AssertionError):
            assert_same_task(SAVED["valve"], other)
        assert_same_task(SAVED["valve"], s.load("valve"))
