"""The task store: one SQLite file (stdlib ``sqlite3``), DESIGN.md "Storage".

Layout (schema version 1)::

    schema_version(version, applied, mmpa_version)   one row per applied migration
    tasks(name PK, site, robot_id, created, description, format_version, meta_json,
          T_map_base_park, q_sample, T_arm_base_camera,        JSON, exact floats
          rate_hz, n_points, n_waypoints, duration, has_colors, cloud_frame,
          cloud_sha256, path_sha256, header_sha256)
    clouds(task PK -> tasks, ply BLOB)                          binary PLY (formats.py)
    paths(task PK -> tasks, t, q, T_arm_base_tool, gripper)     little-endian float64 blobs

``header_sha256`` covers every ``tasks`` column that :meth:`TaskStore.load` reads (and the
blob checksums), so an edited row, blob or a missing blob row is refused with
:class:`~mmpa.errors.CorruptTaskError`. Every write is one ``BEGIN IMMEDIATE`` transaction:
a failure or a crash at any point leaves the store as it was. Migrations live in
:data:`MIGRATIONS` (version -> SQL statements) and run in order, each in a transaction; a
store written by a newer mmpa raises :class:`~mmpa.errors.UnsupportedVersionError`.
"""

from __future__ import annotations

import json
import os
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any

from mmpa.errors import (
    CorruptTaskError,
    InvalidInputError,
    TaskExistsError,
    TaskNotFoundError,
    UnsupportedVersionError,
)
from mmpa.tasks.bundle import read_bundle, write_bundle
from mmpa.tasks.formats import (
    cloud_to_ply,
    header_digest,
    header_record,
    parse_created,
    path_blobs,
    path_digest,
    path_from_blobs,
    ply_to_cloud,
    sha256,
)
from mmpa.tasks.model import FORMAT_VERSION, Task, TaskInfo

__all__ = ["MIGRATIONS", "SCHEMA_VERSION", "TaskStore", "default_store_path"]

SCHEMA_VERSION = 1
MIGRATIONS: dict[int, tuple[str, ...]] = {
    1: (
        """CREATE TABLE schema_version (
            version INTEGER PRIMARY KEY, applied TEXT NOT NULL, mmpa_version TEXT NOT NULL)""",
        """CREATE TABLE tasks (
            name TEXT PRIMARY KEY,
            site TEXT NOT NULL,
            robot_id TEXT NOT NULL,
            created TEXT NOT NULL,
            description TEXT NOT NULL,
            format_version INTEGER NOT NULL,
            meta_json TEXT NOT NULL,
            T_map_base_park TEXT NOT NULL,
            q_sample TEXT NOT NULL,
            T_arm_base_camera TEXT NOT NULL,
            rate_hz REAL NOT NULL,
            n_points INTEGER NOT NULL,
            n_waypoints INTEGER NOT NULL,
            duration REAL NOT NULL,
            has_colors INTEGER NOT NULL,
            cloud_frame TEXT NOT NULL,
            cloud_sha256 TEXT NOT NULL,
            path_sha256 TEXT NOT NULL,
            header_sha256 TEXT NOT NULL)""",
        """CREATE TABLE clouds (
            task TEXT PRIMARY KEY
                REFERENCES tasks(name) ON DELETE CASCADE DEFERRABLE INITIALLY DEFERRED,
            ply BLOB NOT NULL)""",
        """CREATE TABLE paths (
            task TEXT PRIMARY KEY
                REFERENCES tasks(name) ON DELETE CASCADE DEFERRABLE INITIALLY DEFERRED,
            t BLOB NOT NULL,
            q BLOB NOT NULL,
            T_arm_base_tool BLOB NOT NULL,
            gripper BLOB)""",
    ),
}

_JSON = {"separators": (",", ":"), "allow_nan": False}


def default_store_path() -> Path:
    """``$MMPA_TASKS_DB``, else ``$XDG_DATA_HOME/mmpa/tasks.db``, else
    ``~/.local/share/mmpa/tasks.db``."""
    env = os.environ.get("MMPA_TASKS_DB")
    if env:
        return Path(env).expanduser()
    data = os.environ.get("XDG_DATA_HOME")
    base = Path(data).expanduser() if data else Path.home() / ".local" / "share"
    return base / "mmpa" / "tasks.db"


def _mmpa_version() -> str:
    from mmpa import __version__

    return __version__


class TaskStore:
    """Taught tasks in one SQLite file; ``path`` None -> :func:`default_store_path`.

    Creates the parent directories and the schema on first use. ``":memory:"`` gives a
    private in-memory store. Use as a context manager or call :meth:`close`.
    """

    def __init__(self, path: str | Path | None = None) -> None:
        if path is None:
            path = default_store_path()
        self.path = path if str(path) == ":memory:" else Path(path).expanduser()
        if isinstance(self.path, Path):
            if self.path.is_dir():
                raise InvalidInputError(f"task store {self.path} is a directory, not a file")
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._con: sqlite3.Connection | None = sqlite3.connect(
            str(self.path), isolation_level=None, timeout=30.0
        )
        self._con.row_factory = sqlite3.Row
        try:
            self._con.execute("PRAGMA foreign_keys = ON")
            self._migrate()
        except sqlite3.DatabaseError as e:
            self.close()
            raise CorruptTaskError(f"{self.path}: not a usable SQLite task store ({e})") from None
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ connection & schema

    def __repr__(self) -> str:
        return f"TaskStore({str(self.path)!r})"

    def __enter__(self) -> TaskStore:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the connection (idempotent)."""
        if self._con is not None:
            self._con.close()
            self._con = None

    @property
    def con(self) -> sqlite3.Connection:
        if self._con is None:
            raise InvalidInputError(f"task store {self.path} is closed")
        return self._con

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One write transaction: committed if the block returns, rolled back otherwise."""
        con = self.con
        con.execute("BEGIN IMMEDIATE")
        try:
            yield con
        except BaseException:
            con.execute("ROLLBACK")
            raise
        con.execute("COMMIT")

    def schema_version(self) -> int:
        """The schema version of the open store."""
        row = self.con.execute("SELECT MAX(version) FROM schema_version").fetchone()
        return int(row[0] or 0)

    def _migrate(self) -> None:
        with self._tx() as con:
            tables = {
                r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")
            }
            if "schema_version" in tables:
                current = self.schema_version()
            elif tables:
                raise CorruptTaskError(
                    f"{self.path} is an SQLite database but not an mmpa task store "
                    f"(tables: {', '.join(sorted(tables))}, no schema_version)"
                )
            else:
                current = 0
            if current > SCHEMA_VERSION:
                raise UnsupportedVersionError(
                    f"task store {self.path} has schema version {current}, newer than this "
                    f"mmpa {_mmpa_version()} reads (up to {SCHEMA_VERSION}); upgrade mmpa"
                )
            for v in range(current + 1, SCHEMA_VERSION + 1):
                for stmt in MIGRATIONS[v]:
                    con.execute(stmt)
                con.execute(
                    "INSERT INTO schema_version VALUES (?, ?, ?)",
                    (v, datetime.now(UTC).isoformat(), _mmpa_version()),
                )

    # ------------------------------------------------------------------------------- tasks

    def names(self) -> list[str]:
        """Stored task names, sorted."""
        return [r[0] for r in self.con.execute("SELECT name FROM tasks ORDER BY name")]

    def __contains__(self, name: object) -> bool:
        row = self.con.execute("SELECT 1 FROM tasks WHERE name = ?", (name,)).fetchone()
        return row is not None

    def _not_found(self, name: str) -> TaskNotFoundError:
        return TaskNotFoundError(name, self.names(), str(self.path))

    def save(self, task: Task, *, overwrite: bool = False) -> None:
        """Store ``task`` in one transaction; TaskExistsError if the name is taken and not
        ``overwrite``. On any failure the store keeps what it had (the old task included)."""
        if not isinstance(task, Task):
            raise InvalidInputError(f"save() needs a Task, got {type(task).__name__}")
        with self._tx() as con:
            if con.execute("SELECT 1 FROM tasks WHERE name = ?", (task.name,)).fetchone():
                if not overwrite:
                    raise TaskExistsError(
                        f"task {task.name!r} already exists in {self.path}; pass "
                        "overwrite=True (CLI: --overwrite) or delete it first"
                    )
                con.execute("DELETE FROM tasks WHERE name = ?", (task.name,))
            blobs = path_blobs(task.path)
            con.execute(
                "INSERT INTO paths VALUES (?, ?, ?, ?, ?)",
                (task.name, blobs["t"], blobs["q"], blobs["T_arm_base_tool"], blobs["gripper"]),
            )
            ply = cloud_to_ply(task.cloud)
            con.execute("INSERT INTO clouds VALUES (?, ?)", (task.name, ply))
            rec = header_record(task, sha256(ply), path_digest(blobs))
            con.execute(
                "INSERT INTO tasks VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                (
                    rec["name"],
                    rec["site"],
                    rec["robot_id"],
                    rec["created"],
                    rec["description"],
                    rec["format_version"],
                    json.dumps(rec["meta"], sort_keys=True, **_JSON),
                    json.dumps(rec["T_map_base_park"], **_JSON),
                    json.dumps(rec["q_sample"], **_JSON),
                    json.dumps(rec["T_arm_base_camera"], **_JSON),
                    rec["rate_hz"],
                    rec["n_points"],
                    rec["n_waypoints"],
                    task.path.duration,
                    int(rec["has_colors"]),
                    rec["cloud_frame"],
                    rec["cloud_sha256"],
                    rec["path_sha256"],
                    header_digest(rec),
                ),
            )

    def load(self, name: str) -> Task:
        """The task ``name``, every checksum verified (TaskNotFoundError, CorruptTaskError)."""
        con = self.con
        con.execute("BEGIN")  # one consistent snapshot of the three rows
        try:
            row = con.execute("SELECT * FROM tasks WHERE name = ?", (name,)).fetchone()
            cloud_row = con.execute("SELECT ply FROM clouds WHERE task = ?", (name,)).fetchone()
            path_row = con.execute("SELECT * FROM paths WHERE task = ?", (name,)).fetchone()
        finally:
            con.execute("COMMIT")
        if row is None:
            raise self._not_found(name)
        where = f"task {name!r} in {self.path}"
        if row["format_version"] > FORMAT_VERSION:
            raise UnsupportedVersionError(
                f"{where} has format version {row['format_version']}, newer than this mmpa "
                f"reads ({FORMAT_VERSION}); upgrade mmpa"
            )
        if cloud_row is None or path_row is None:
            missing = "clouds" if cloud_row is None else "paths"
            raise CorruptTaskError(f"{where}: its row in table {missing!r} is missing")
        ply = bytes(cloud_row["ply"])
        got = sha256(ply)
        if got != row["cloud_sha256"]:
            raise CorruptTaskError(
                f"{where}: cloud (clouds.ply, {len(ply)} bytes) SHA-256 mismatch: stored "
                f"{row['cloud_sha256'][:16]}..., computed {got[:16]}..."
            )
        blobs = {
            k: None if path_row[k] is None else bytes(path_row[k])
            for k in ("t", "q", "T_arm_base_tool", "gripper")
        }
        got = path_digest(blobs)
        if got != row["path_sha256"]:
            raise CorruptTaskError(
                f"{where}: path arrays (paths.t/q/T_arm_base_tool/gripper) SHA-256 mismatch: "
                f"stored {row['path_sha256'][:16]}..., computed {got[:16]}..."
            )
        try:
            rec: dict[str, Any] = {
                "format_version": row["format_version"],
                "name": row["name"],
                "site": row["site"],
                "robot_id": row["robot_id"],
                "created": row["created"],
                "description": row["description"],
                "meta": json.loads(row["meta_json"]),
                "T_map_base_park": json.loads(row["T_map_base_park"]),
                "q_sample": json.loads(row["q_sample"]),
                "T_arm_base_camera": json.loads(row["T_arm_base_camera"]),
                "rate_hz": row["rate_hz"],
                "n_points": row["n_points"],
                "n_waypoints": row["n_waypoints"],
                "has_colors": bool(row["has_colors"]),
                "cloud_frame": row["cloud_frame"],
                "cloud_sha256": row["cloud_sha256"],
                "path_sha256": row["path_sha256"],
            }
            ok = header_digest(rec) == row["header_sha256"]
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise CorruptTaskError(
                f"{where}: metadata (table 'tasks') does not match its header_sha256; "
                "a column was altered"
            )
        path = path_from_blobs(blobs, rec["n_waypoints"], rec["rate_hz"], f"{where}: paths")
        cloud = ply_to_cloud(ply, rec["cloud_frame"], f"{where}: clouds.ply")
        if len(cloud) != rec["n_points"] or (cloud.colors is not None) != rec["has_colors"]:
            raise CorruptTaskError(f"{where}: cloud does not match n_points/has_colors")
        try:
            return Task(
                name=rec["name"],
                site=rec["site"],
                T_map_base_park=rec["T_map_base_park"],
                q_sample=rec["q_sample"],
                T_arm_base_camera=rec["T_arm_base_camera"],
                cloud=cloud,
                path=path,
                robot_id=rec["robot_id"],
                created=parse_created(rec["created"], where),
                description=rec["description"],
                meta=rec["meta"],
                format_version=rec["format_version"],
            )
        except InvalidInputError as e:
            raise CorruptTaskError(f"{where}: {e}") from None

    def list(self) -> list[TaskInfo]:
        """A summary of every task, sorted by name (blobs are not read or verified)."""
        rows = self.con.execute(
            "SELECT name, site, created, n_points, n_waypoints, duration, robot_id, "
            "description, has_colors, rate_hz FROM tasks ORDER BY name"
        ).fetchall()
        out = []
        for r in rows:
            try:
                created = datetime.fromisoformat(r["created"])
            except (TypeError, ValueError):
                created = datetime.fromtimestamp(0, UTC)
            out.append(
                TaskInfo(
                    name=r["name"],
                    site=r["site"],
                    created=created,
                    n_points=int(r["n_points"]),
                    n_waypoints=int(r["n_waypoints"]),
                    duration=float(r["duration"]),
                    robot_id=r["robot_id"],
                    description=r["description"],
                    has_colors=bool(r["has_colors"]),
                    rate_hz=float(r["rate_hz"]),
                )
            )
        return out

    def delete(self, name: str) -> None:
        """Remove ``name`` and its blobs in one transaction (TaskNotFoundError if absent)."""
        with self._tx() as con:
            if con.execute("DELETE FROM tasks WHERE name = ?", (name,)).rowcount == 0:
                raise self._not_found(name)

    def export(self, name: str, directory: str | Path, *, overwrite: bool = False) -> Path:
        """Write the verified task ``name`` as a bundle into ``directory``; returns it."""
        return write_bundle(self.load(name), directory, overwrite=overwrite)

    def import_bundle(self, directory: str | Path, *, overwrite: bool = False) -> Task:
        """Verify the bundle in ``directory`` and save its task; returns the task."""
        task = read_bundle(directory)
        self.save(task, overwrite=overwrite)
        return task
