"""`mmpa tasks list|show|export|import|delete` against a temporary database (--db)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from mmpa.cli.main import app
from mmpa.tasks import TaskStore
from test_tasks import assert_same_task, make_task

runner = CliRunner()


@pytest.fixture
def db(tmp_path: Path) -> Path:
    p = tmp_path / "tasks.db"
    with TaskStore(p) as s:
        s.save(make_task("valve"))
        s.save(make_task("cup", seed=1, colors="none", site="2'"))
    return p


def _run(*args: str, input: str | None = None):
    return runner.invoke(app, ["tasks", *args], input=input)


def test_list(db: Path, tmp_path: Path) -> None:
    res = _run("list", "--db", str(db))
    assert res.exit_code == 0, res.output
    assert "valve" in res.output and "cup" in res.output
    assert "2'" in res.output and "40 @ 30 Hz" in res.output
    res = _run("list", "--db", str(tmp_path / "empty.db"))
    assert res.exit_code == 0 and "no tasks stored yet" in res.output


def test_db_from_environment(db: Path, monkeypatch) -> None:
    monkeypatch.setenv("MMPA_TASKS_DB", str(db))
    res = _run("list")
    assert res.exit_code == 0 and "valve" in res.output


def test_show(db: Path) -> None:
    res = _run("show", "valve", "--db", str(db))
    assert res.exit_code == 0, res.output
    for text in ("checksums verified", "switch the valve", "ur5e-7", "500 points", "colored"):
        assert text in res.output, text
    assert "meta.trials" in res.output
    res = _run("show", "cup", "--db", str(db))
    assert res.exit_code == 0 and "colorless" in res.output and "gripper" in res.output


def test_show_missing_task_exits_2(db: Path) -> None:
    res = _run("show", "nope", "--db", str(db))
    assert res.exit_code == 2
    assert "error:" in res.output and "no task 'nope'" in res.output
    assert "cup, valve" in res.output


def test_export_import_round_trip(db: Path, tmp_path: Path) -> None:
    out = tmp_path / "bundle"
    res = _run("export", "valve", str(out), "--db", str(db))
    assert res.exit_code == 0, res.output
    assert (out / "task.yaml").is_file() and (out / "cloud.ply").is_file()
    res = _run("export", "valve", str(out), "--db", str(db))
    assert res.exit_code == 2 and "already holds a task bundle" in res.output
    other = tmp_path / "other.db"
    res = _run("import", str(out), "--db", str(other))
    assert res.exit_code == 0, res.output
    assert "imported task 'valve'" in res.output
    with TaskStore(other) as s:
        assert_same_task(make_task("valve"), s.load("valve"))
    res = _run("import", str(out), "--db", str(other))
    assert res.exit_code == 2 and "already exists" in res.output
    res = _run("import", str(out), "--overwrite", "--db", str(other))
    assert res.exit_code == 0, res.output


def test_import_tampered_bundle_exits_2(db: Path, tmp_path: Path) -> None:
    out = tmp_path / "bundle"
    assert _run("export", "cup", str(out), "--db", str(db)).exit_code == 0
    ply = out / "cloud.ply"
    ply.write_bytes(ply.read_bytes()[:-1])
    res = _run("import", str(out), "--db", str(tmp_path / "x.db"))
    assert res.exit_code == 2
    assert "cloud.ply" in res.output and "truncated" in res.output
    with TaskStore(tmp_path / "x.db") as s:
        assert s.names() == []


def test_delete(db: Path) -> None:
    res = _run("delete", "cup", "--db", str(db), input="n\n")
    assert res.exit_code == 1 and "not deleted" in res.output
    res = _run("delete", "cup", "--db", str(db), input="y\n")
    assert res.exit_code == 0, res.output
    res = _run("delete", "valve", "--yes", "--db", str(db))
    assert res.exit_code == 0, res.output
    with TaskStore(db) as s:
        assert s.names() == []
    res = _run("delete", "valve", "--yes", "--db", str(db))
    assert res.exit_code == 2 and "no task 'valve'" in res.output


def test_corrupt_database_exits_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.db"
    bad.write_bytes(b"\x00" * 4096)
    res = _run("list", "--db", str(bad))
    assert res.exit_code == 2 and "error:" in res.output
