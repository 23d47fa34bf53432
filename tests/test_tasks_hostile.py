"""Hostile inputs to the task store and bundles (issue 22): damaged or edited SQLite files,
a lock held by another process, tampered summary columns, symbolic links and huge files in a
bundle, an export that fails midway, and a YAML alias bomb. Every case must end in a clear
MMPAError naming the file, never a raw sqlite3 / Python traceback or a silent wrong value."""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

import mmpa.tasks.bundle as bundle_mod
from mmpa.cli.main import app
from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.tasks import (
    FORMAT_VERSION,
    CorruptTaskError,
    StoreLockedError,
    TaskStore,
    read_bundle,
    write_bundle,
)
from mmpa.tasks.bundle import MAX_FILE_BYTES
from test_tasks import assert_same_task, make_task

runner = CliRunner()


def _exec(db: Path, *sql: str) -> None:
    con = sqlite3.connect(db)
    for s in sql:
        con.execute(s)
    con.commit()
    con.close()


@pytest.fixture
def db(tmp_path: Path) -> Path:
    p = tmp_path / "hostile.db"
    with TaskStore(p) as s:
        s.save(make_task("valve"))
    return p


def _cli(*args: str, env: dict[str, str] | None = None):
    return runner.invoke(app, ["tasks", *args], env=env)


def _assert_clean_cli_error(res, *needles: str) -> None:
    """Exit 2, printed 'error:' and each needle; no exception other than typer's exit."""
    assert res.exit_code == 2, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    flat = " ".join(res.output.split())  # rich may wrap long paths
    assert "error:" in flat
    for n in needles:
        assert n in flat, (n, res.output)


def _api_list(p: Path) -> None:
    with TaskStore(p) as s:
        s.list()


def _api_show(p: Path) -> None:
    with TaskStore(p) as s:
        s.load("valve")


# ---------------------------------------------------------------------------- 1. corruption


def _recreate_tasks_without(db: Path, column: str) -> None:
    con = sqlite3.connect(db)
    cols = [r[1] for r in con.execute("PRAGMA table_info(tasks)") if r[1] != column]
    con.executescript(
        f"""CREATE TABLE t2 AS SELECT {", ".join(cols)} FROM tasks;
        DROP TABLE tasks; ALTER TABLE t2 RENAME TO tasks;"""
    )
    con.close()


def _smash_tasks_page(db: Path) -> None:
    con = sqlite3.connect(db)
    root = con.execute("SELECT rootpage FROM sqlite_master WHERE name = 'tasks'").fetchone()[0]
    size = con.execute("PRAGMA page_size").fetchone()[0]
    con.close()
    raw = bytearray(db.read_bytes())
    raw[(root - 1) * size : root * size] = b"\xa5" * size
    db.write_bytes(bytes(raw))


CORRUPTIONS = {
    "garbage page": (_smash_tasks_page, r"malformed"),
    "drop tasks": (lambda p: _exec(p, "DROP TABLE tasks"), r"table 'tasks' is missing"),
    "drop clouds": (lambda p: _exec(p, "DROP TABLE clouds"), r"table 'clouds' is missing"),
    "drop paths": (lambda p: _exec(p, "DROP TABLE paths"), r"table 'paths' is missing"),
    "drop schema_version": (
        lambda p: _exec(p, "DROP TABLE schema_version"),
        r"not an mmpa task store",
    ),
    "drop column duration": (
        lambda p: _exec(p, "ALTER TABLE tasks DROP COLUMN duration"),
        r"table 'tasks' lacks column\(s\) duration",
    ),
    "recreate without n_points": (
        lambda p: _recreate_tasks_without(p, "n_points"),
        r"table 'tasks' lacks column\(s\) n_points",
    ),
    "text n_points": (
        lambda p: _exec(p, "UPDATE tasks SET n_points = 'abc'"),
        r"column tasks.n_points holds 'abc' \(text\), expected an integer",
    ),
    "text n_waypoints": (
        lambda p: _exec(p, "UPDATE tasks SET n_waypoints = 'forty'"),
        r"tasks.n_waypoints holds 'forty' \(text\)",
    ),
    "text format_version": (
        lambda p: _exec(p, "UPDATE tasks SET format_version = 'v2'"),
        r"tasks.format_version holds 'v2' \(text\)",
    ),
    "text rate_hz": (
        lambda p: _exec(p, "UPDATE tasks SET rate_hz = 'fast'"),
        r"tasks.rate_hz holds 'fast' \(text\), expected a finite number",
    ),
    "text duration": (
        lambda p: _exec(p, "UPDATE tasks SET duration = 'long'"),
        r"tasks.duration holds 'long' \(text\)",
    ),
    "blob has_colors": (
        lambda p: _exec(p, "UPDATE tasks SET has_colors = x'00'"),
        r"tasks.has_colors holds b'\\x00' \(blob\)",
    ),
    "null site": (
        lambda p: _recreate_and_null(p, "site"),
        r"tasks.site holds None \(NULL\), expected text",
    ),
    "non-json pose": (
        lambda p: _exec(p, "UPDATE tasks SET q_sample = '[1, 2'"),
        r"tasks.q_sample holds '\[1, 2' \(text\), expected JSON",
    ),
}


def _recreate_and_null(db: Path, column: str) -> None:
    """NOT NULL forbids NULL, so rebuild the table without constraints first."""
    con = sqlite3.connect(db)
    con.executescript(
        f"""CREATE TABLE t2 AS SELECT * FROM tasks; DROP TABLE tasks;
        ALTER TABLE t2 RENAME TO tasks; UPDATE tasks SET {column} = NULL;"""
    )
    con.close()


@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_corrupt_store_is_a_clear_error_in_api_and_cli(db: Path, case: str) -> None:
    corrupt, match = CORRUPTIONS[case]
    corrupt(db)
    for call in (_api_list, _api_show):
        with pytest.raises(CorruptTaskError, match=match) as info:
            call(db)
        assert "hostile.db" in str(info.value)
    for args in (("list",), ("show", "valve")):
        _assert_clean_cli_error(_cli(*args, "--db", str(db)), "hostile.db")


def test_corrupt_store_is_a_clear_error_on_write_too(db: Path) -> None:
    _smash_tasks_page(db)
    with TaskStore(db) as s:
        with pytest.raises(
            CorruptTaskError, match=r"hostile.db: cannot save task 'cup'.*malformed"
        ):
            s.save(make_task("cup"))
        with pytest.raises(CorruptTaskError, match=r"malformed"):
            s.delete("valve")
    _assert_clean_cli_error(_cli("delete", "valve", "--yes", "--db", str(db)), "malformed")


def test_a_bad_row_names_the_task(db: Path) -> None:
    with TaskStore(db) as s:
        s.save(make_task("cup", seed=1))
    _exec(db, "UPDATE tasks SET n_points = 'abc' WHERE name = 'cup'")
    with TaskStore(db) as s:
        with pytest.raises(CorruptTaskError, match=r"task 'cup' in .*hostile.db: column"):
            s.list()
        assert_same_task(make_task("valve"), s.load("valve"))  # the good task still loads


# -------------------------------------------------------------------------------- 2. locks


def _hold(db: Path, mode: str) -> sqlite3.Connection:
    con = sqlite3.connect(db, isolation_level=None)
    con.execute(f"BEGIN {mode}")
    if mode == "IMMEDIATE":
        con.execute("UPDATE tasks SET site = site")
    return con


def test_exclusive_lock_is_reported_as_locked_not_corrupt(db: Path) -> None:
    other = _hold(db, "EXCLUSIVE")
    try:
        t0 = time.perf_counter()
        with pytest.raises(StoreLockedError, match=r"hostile.db is locked by another process"):
            TaskStore(db, timeout=0.2)
        waited = time.perf_counter() - t0
        assert 0.15 <= waited < 3.0  # the busy timeout was honoured, then a clear error
    finally:
        other.close()
    with TaskStore(db, timeout=0.2) as s:  # opened before the lock is taken
        other = _hold(db, "EXCLUSIVE")
        try:
            for call in (s.list, lambda: s.load("valve"), s.names):
                with pytest.raises(StoreLockedError, match=r"waited 0.2 s"):
                    call()
        finally:
            other.close()
        assert [i.name for i in s.list()] == ["valve"]  # free again


def test_write_lock_blocks_writes_only(db: Path) -> None:
    other = _hold(db, "IMMEDIATE")
    try:
        with TaskStore(db, timeout=0.2) as s:  # opening an up-to-date store needs no write lock
            assert [i.name for i in s.list()] == ["valve"]
            assert_same_task(make_task("valve"), s.load("valve"))
            with pytest.raises(StoreLockedError, match=r"locked by another process"):
                s.save(make_task("cup"))
            with pytest.raises(StoreLockedError):
                s.delete("valve")
    finally:
        other.close()
    with TaskStore(db) as s:
        assert s.names() == ["valve"]


def test_locked_store_in_the_cli(db: Path) -> None:
    other = _hold(db, "EXCLUSIVE")
    try:
        env = {"MMPA_TASKS_BUSY_TIMEOUT": "0.1"}
        for args in (("list",), ("show", "valve")):
            res = _cli(*args, "--db", str(db), env=env)
            _assert_clean_cli_error(res, "locked by another process", "hostile.db")
            assert "damaged" not in res.output
    finally:
        other.close()


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), "3", True])
def test_bad_busy_timeout_is_refused(db: Path, bad) -> None:
    with pytest.raises(InvalidInputError, match=r"timeout"):
        TaskStore(db, timeout=bad)


def test_bad_busy_timeout_in_environment(db: Path, monkeypatch) -> None:
    monkeypatch.setenv("MMPA_TASKS_BUSY_TIMEOUT", "soon")
    with pytest.raises(InvalidInputError, match=r"MMPA_TASKS_BUSY_TIMEOUT.*'soon'"):
        TaskStore(db)
    monkeypatch.setenv("MMPA_TASKS_BUSY_TIMEOUT", "0.5")
    with TaskStore(db) as s:
        assert s.timeout == 0.5


# --------------------------------------------------------------- 3. duration and has_colors


def _canonical_sha(rec: dict) -> str:
    text = json.dumps(rec, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


def _row(db: Path) -> dict:
    con = sqlite3.connect(db)
    con.row_factory = sqlite3.Row
    row = dict(con.execute("SELECT * FROM tasks").fetchone())
    con.close()
    return row


def _record_of_row(row: dict) -> dict:
    """The header record rebuilt from a row independently of mmpa's code."""
    rec = {k: row[k] for k in ("name", "site", "robot_id", "created", "description")}
    rec.update({k: row[k] for k in ("format_version", "rate_hz", "n_points", "n_waypoints")})
    rec.update({k: row[k] for k in ("cloud_frame", "cloud_sha256", "path_sha256")})
    rec["meta"] = json.loads(row["meta_json"])
    for k in ("T_map_base_park", "q_sample", "T_arm_base_camera"):
        rec[k] = json.loads(row[k])
    rec["has_colors"] = bool(row["has_colors"])
    return rec


def test_header_covers_duration_and_has_colors(db: Path) -> None:
    row = _row(db)
    assert row["format_version"] == FORMAT_VERSION == 2
    rec = _record_of_row(row)
    assert row["duration"] == 39 / 30.0
    assert _canonical_sha(rec) != row["header_sha256"]  # without duration: not the digest
    rec["duration"] = 39 / 30.0
    assert _canonical_sha(rec) == row["header_sha256"]


@pytest.mark.parametrize(
    "sql",
    [
        "UPDATE tasks SET duration = 99.0",
        "UPDATE tasks SET duration = duration + 1e-12",
        "UPDATE tasks SET has_colors = 0",
    ],
)
def test_tampered_summary_column_is_detected(db: Path, sql: str) -> None:
    _exec(db, sql)
    for call in (_api_list, _api_show):
        with pytest.raises(CorruptTaskError, match=r"does not match its header_sha256"):
            call(db)
    _assert_clean_cli_error(_cli("list", "--db", str(db)), "header_sha256")


def test_has_colors_must_be_0_or_1(db: Path) -> None:
    _exec(db, "UPDATE tasks SET has_colors = 2")  # bool(2) would pass the digest
    with pytest.raises(CorruptTaskError, match=r"tasks.has_colors holds 2 .*expected 0 or 1"):
        _api_list(db)


def _make_v1(db: Path) -> None:
    """Rewrite the stored row as a version-1 record (digest without duration)."""
    row = _row(db)
    rec = _record_of_row(row)
    rec["format_version"] = 1
    _exec(db, f"UPDATE tasks SET format_version = 1, header_sha256 = '{_canonical_sha(rec)}'")


def test_version_1_store_stays_readable_and_is_upgraded_on_save(db: Path) -> None:
    _make_v1(db)
    with TaskStore(db) as s:
        (info,) = s.list()
        assert info.duration == 39 / 30.0 and info.has_colors
        task = s.load("valve")
        assert task.format_version == FORMAT_VERSION
        assert_same_task(make_task("valve"), task)
        s.save(task, overwrite=True)
    assert _row(db)["format_version"] == FORMAT_VERSION
    _exec(db, "UPDATE tasks SET duration = 99.0")
    with pytest.raises(CorruptTaskError, match=r"header_sha256"):
        _api_list(db)


def test_version_1_duration_tamper_is_caught_on_load(db: Path) -> None:
    _make_v1(db)
    _exec(db, "UPDATE tasks SET duration = 99.0")
    with TaskStore(db) as s:
        assert s.list()[0].duration == 99.0  # version 1 did not cover it: list cannot tell
        with pytest.raises(CorruptTaskError, match=r"tasks.duration = 99.0 but the stored data"):
            s.load("valve")


def test_version_1_bundle_is_read(tmp_path: Path) -> None:
    import yaml

    b = write_bundle(make_task(), tmp_path / "b")
    doc = yaml.safe_load((b / "task.yaml").read_text())
    rec = {
        k: doc[k]
        for k in (
            *("name", "site", "robot_id", "created", "description", "meta"),
            *("T_map_base_park", "q_sample", "T_arm_base_camera"),
        )
    }
    rec.update(
        format_version=1,
        rate_hz=doc["path"]["rate_hz"],
        n_points=doc["cloud"]["n_points"],
        n_waypoints=doc["path"]["n_waypoints"],
        has_colors=doc["cloud"]["has_colors"],
        cloud_frame=doc["cloud"]["frame"],
        cloud_sha256=doc["cloud"]["sha256"],
        path_sha256=doc["path"]["arrays_sha256"],
    )
    doc.update(format_version=1, header_sha256=_canonical_sha(rec))
    (b / "task.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    task = read_bundle(b)
    assert task.format_version == FORMAT_VERSION
    assert_same_task(make_task(), task)


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda d: d["path"].update(duration_s=99.0), r"path.duration_s differs"),
        (lambda d: d["cloud"].update(has_colors=False), r"cloud.has_colors differs"),
    ],
)
def test_tampered_bundle_summary_is_detected(tmp_path: Path, edit, match: str) -> None:
    import yaml

    b = write_bundle(make_task(), tmp_path / "b")
    doc = yaml.safe_load((b / "task.yaml").read_text())
    edit(doc)
    (b / "task.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    with pytest.raises(CorruptTaskError, match=match):
        read_bundle(b)


# ---------------------------------------------------------------- 4. links and huge files


@pytest.fixture
def bundle(tmp_path: Path) -> Path:
    return write_bundle(make_task(), tmp_path / "bundle")


@pytest.mark.parametrize("name", ["cloud.ply", "path.csv", "task.yaml"])
def test_symlink_out_of_the_bundle_is_refused(tmp_path: Path, bundle: Path, name: str) -> None:
    outside = tmp_path / f"outside-{name}"
    outside.write_bytes((bundle / name).read_bytes())  # identical bytes: checksums would pass
    (bundle / name).unlink()
    (bundle / name).symlink_to(outside)
    with pytest.raises(CorruptTaskError, match=rf"{name}: is a symbolic link"):
        read_bundle(bundle)


def test_symlink_inside_the_bundle_is_refused_too(bundle: Path) -> None:
    (bundle / "copy.csv").write_bytes((bundle / "path.csv").read_bytes())
    (bundle / "path.csv").unlink()
    (bundle / "path.csv").symlink_to("copy.csv")
    with pytest.raises(CorruptTaskError, match=r"path.csv: is a symbolic link"):
        read_bundle(bundle)


def test_fifo_is_refused_without_blocking(bundle: Path) -> None:
    (bundle / "cloud.ply").unlink()
    os.mkfifo(bundle / "cloud.ply")
    with pytest.raises(CorruptTaskError, match=r"cloud.ply: not a regular file"):
        read_bundle(bundle)


def _refused_without_reading(bundle: Path, match: str) -> None:
    """read_bundle raises CorruptTaskError matching ``match`` within 1 s, allocating < 32 MB
    (reading the 2 GiB file would allocate 2 GiB)."""
    import tracemalloc

    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(CorruptTaskError, match=match):
            read_bundle(bundle)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - t0 < 1.0
    assert peak < 32 << 20, peak


def test_huge_sparse_data_file_is_refused_before_reading(bundle: Path) -> None:
    os.truncate(bundle / "cloud.ply", 2 << 30)  # 2 GiB, sparse: costs no disk
    _refused_without_reading(bundle, r"cloud.ply: longer than recorded: 2147483648")


def test_huge_recorded_size_is_refused_before_reading(bundle: Path) -> None:
    import yaml

    y = bundle / "task.yaml"
    doc = yaml.safe_load(y.read_text())
    doc["cloud"]["bytes"] = 2 << 30
    y.write_text(yaml.safe_dump(doc, sort_keys=False))
    os.truncate(bundle / "cloud.ply", 2 << 30)
    _refused_without_reading(bundle, rf"records 2147483648 bytes .*0..{MAX_FILE_BYTES}")


def test_huge_sparse_task_yaml_is_refused_before_reading(bundle: Path) -> None:
    os.truncate(bundle / "task.yaml", 2 << 30)
    _refused_without_reading(bundle, r"task.yaml: 2147483648 bytes, more than")


# ---------------------------------------------------------------------- 5. atomic export


def _bundle_state(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


@pytest.mark.parametrize("fail_at", [1, 2, 3])
@pytest.mark.parametrize("exc", [OSError(28, "No space left on device"), RuntimeError("boom")])
def test_failed_overwrite_leaves_the_old_bundle(
    bundle: Path, monkeypatch, fail_at: int, exc: Exception
) -> None:
    before = _bundle_state(bundle)
    real = bundle_mod._write_file
    calls = []

    def flaky(path: Path, data: bytes) -> None:
        calls.append(path.name)
        if len(calls) == fail_at:
            raise exc
        real(path, data)

    monkeypatch.setattr(bundle_mod, "_write_file", flaky)
    with pytest.raises((InvalidInputError, RuntimeError)) as info:
        write_bundle(make_task(seed=1, site="2"), bundle, overwrite=True)
    if isinstance(exc, OSError):
        assert isinstance(info.value, MMPAError)
        assert "No space left on device" in str(info.value) and "bundle" in str(info.value)
    assert len(calls) == fail_at
    assert _bundle_state(bundle) == before  # untouched, byte for byte
    assert_same_task(make_task(), read_bundle(bundle))
    assert sorted(p.name for p in bundle.parent.iterdir()) == ["bundle"]  # no temp left


def test_failed_final_rename_restores_the_old_bundle(bundle: Path, monkeypatch) -> None:
    before = _bundle_state(bundle)
    real = os.rename

    def rename(src, dst):
        if ".tmp-" in str(src):
            raise OSError(5, "Input/output error")
        real(src, dst)

    monkeypatch.setattr(bundle_mod.os, "rename", rename)
    with pytest.raises(InvalidInputError, match=r"cannot write bundle .*Input/output error"):
        write_bundle(make_task(seed=1), bundle, overwrite=True)
    monkeypatch.setattr(bundle_mod.os, "rename", real)
    assert _bundle_state(bundle) == before
    assert sorted(p.name for p in bundle.parent.iterdir()) == ["bundle"]


def test_overwrite_replaces_the_whole_bundle(bundle: Path) -> None:
    os.chmod(bundle, 0o750)
    write_bundle(make_task(seed=1, site="2", colors="none"), bundle, overwrite=True)
    back = read_bundle(bundle)
    assert back.site == "2" and not back.has_colors
    assert_same_task(make_task(seed=1, site="2", colors="none"), back)
    assert (bundle.stat().st_mode & 0o777) == 0o750
    assert sorted(p.name for p in bundle.parent.iterdir()) == ["bundle"]


def test_export_refuses_a_directory_with_other_files(tmp_path: Path) -> None:
    d = tmp_path / "docs"
    d.mkdir()
    (d / "thesis.tex").write_text("precious")
    with pytest.raises(InvalidInputError, match=r"holds other files \(thesis.tex\)"):
        write_bundle(make_task(), d, overwrite=True)
    assert (d / "thesis.tex").read_text() == "precious"
    empty = tmp_path / "empty"
    empty.mkdir()
    assert_same_task(make_task(), read_bundle(write_bundle(make_task(), empty)))


def test_export_through_a_symlinked_directory(tmp_path: Path) -> None:
    real = write_bundle(make_task(), tmp_path / "real")
    link = tmp_path / "link"
    link.symlink_to(real)
    assert write_bundle(make_task(seed=1, site="2"), link, overwrite=True) == link
    assert link.is_symlink() and read_bundle(real).site == "2"


# ---------------------------------------------------------------------- 6. YAML alias bomb


def test_alias_bomb_task_yaml_is_refused_fast(bundle: Path) -> None:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, 10):
        lines.append(f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]")  # 9**10 leaves
    text = "\n".join(lines) + "\n"
    assert len(text) < 2048
    (bundle / "task.yaml").write_text(text)
    t0 = time.perf_counter()
    with pytest.raises(CorruptTaskError, match=r"task.yaml.*alias \*a0 is not accepted"):
        read_bundle(bundle)
    assert time.perf_counter() - t0 < 1.0
    with TaskStore(bundle.parent / "x.db") as s:
        with pytest.raises(CorruptTaskError, match=r"alias"):
            s.import_bundle(bundle)
        assert s.names() == []
    res = _cli("import", str(bundle), "--db", str(bundle.parent / "x.db"))
    _assert_clean_cli_error(res, "task.yaml", "alias")
