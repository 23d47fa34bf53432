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
:class:`~mmpa.core.errors.CorruptTaskError`. Every write is one ``BEGIN IMMEDIATE`` transaction:
a failure or a crash at any point leaves the store as it was. Migrations live in
:data:`MIGRATIONS` (version -> SQL statements) and run in order, each in a transaction; a
store written by a newer mmpa raises :class:`~mmpa.core.errors.UnsupportedVersionError`.

No SQLite exception leaves this module: a damaged page, a dropped table or column (checked
on open) or a value of the wrong type in a column raise CorruptTaskError naming the file
(and the task and column); a lock held by another process for longer than the busy timeout
raises :class:`StoreLockedError`. Opening an up-to-date store takes no write lock.
"""

from __future__ import annotations

import json
import math
import os
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any

from mmpa import __version__
from mmpa.core.errors import (
    CorruptTaskError,
    InvalidInputError,
    MMPAError,
    TaskExistsError,
    TaskNotFoundError,
    UnsupportedVersionError,
)
from mmpa.tasks.bundle import read_bundle, write_bundle
from mmpa.tasks.formats import (
    check_blob_sizes,
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
from mmpa.tasks.schema import LIST_SQL, MIGRATIONS, SCHEMA_VERSION

__all__ = [
    "DEFAULT_BUSY_TIMEOUT_S",
    "MIGRATIONS",
    "SCHEMA_VERSION",
    "StoreLockedError",
    "TaskStore",
    "default_store_path",
]

#: How long (s) a call waits for another process's lock before StoreLockedError.
DEFAULT_BUSY_TIMEOUT_S = 30.0
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

    return __version__


#: Columns each table must have (a later schema may add more); checked on open.
_COLUMNS: dict[str, tuple[str, ...]] = {
    "schema_version": ("version", "applied", "mmpa_version"),
    "tasks": (
        "name",
        "site",
        "robot_id",
        "created",
        "description",
        "format_version",
        "meta_json",
        "T_map_base_park",
        "q_sample",
        "T_arm_base_camera",
        "rate_hz",
        "n_points",
        "n_waypoints",
        "duration",
        "has_colors",
        "cloud_frame",
        "cloud_sha256",
        "path_sha256",
        "header_sha256",
    ),
    "clouds": ("task", "ply"),
    "paths": ("task", "t", "q", "T_arm_base_tool", "gripper"),
}
_TEXT = ("name", "site", "robot_id", "created", "description", "cloud_frame")
_TEXT += ("cloud_sha256", "path_sha256", "header_sha256")
_JSON_COLS = {
    "meta_json": "meta",
    "T_map_base_park": "T_map_base_park",
    "q_sample": "q_sample",
    "T_arm_base_camera": "T_arm_base_camera",
}
_SQL_TYPE = {int: "integer", float: "real", str: "text", bytes: "blob", type(None): "NULL"}


def _busy_timeout(timeout: float | None) -> float:
    """``timeout`` s, else ``$MMPA_TASKS_BUSY_TIMEOUT``, else :data:`DEFAULT_BUSY_TIMEOUT_S`."""
    source = "timeout"
    if timeout is None:
        env = os.environ.get("MMPA_TASKS_BUSY_TIMEOUT")
        if not env:
            return DEFAULT_BUSY_TIMEOUT_S
        source = "$MMPA_TASKS_BUSY_TIMEOUT"
        try:
            timeout = float(env)
        except ValueError:
            raise InvalidInputError(f"{source} must be a number of seconds, got {env!r}") from None
    if isinstance(timeout, bool) or not isinstance(timeout, int | float):
        raise InvalidInputError(f"{source} must be a number of seconds, got {timeout!r}")
    if not (math.isfinite(timeout) and timeout >= 0.0):
        raise InvalidInputError(f"{source} must be finite and >= 0 s, got {timeout!r}")
    return float(timeout)


def _is_locked(e: sqlite3.Error) -> bool:
    name = getattr(e, "sqlite_errorname", "") or ""
    return name.startswith(("SQLITE_BUSY", "SQLITE_LOCKED")) or "is locked" in str(e)


class StoreLockedError(MMPAError):
    """Another process holds the task store's lock for longer than the busy timeout."""


class TaskStore:
    """Taught tasks in one SQLite file; ``path`` None -> :func:`default_store_path`.

    Creates the parent directories and the schema on first use. ``":memory:"`` gives a
    private in-memory store. Use as a context manager or call :meth:`close`.

    ``timeout`` (s; None: ``$MMPA_TASKS_BUSY_TIMEOUT``, else 30) is how long a call waits
    for another process's lock before it raises :class:`StoreLockedError`. Every SQLite
    error is reported as an :class:`~mmpa.core.errors.MMPAError` naming the file: a damaged
    file, a dropped table or column, or a column of the wrong type raise
    :class:`~mmpa.core.errors.CorruptTaskError`.
    """

    def __init__(self, path: str | Path | None = None, *, timeout: float | None = None) -> None:
        self.timeout = _busy_timeout(timeout)
        if path is None:
            path = default_store_path()
        self.path = path if str(path) == ":memory:" else Path(path).expanduser()
        self._con: sqlite3.Connection | None = None
        if isinstance(self.path, Path):
            if self.path.is_dir():
                raise InvalidInputError(f"task store {self.path} is a directory, not a file")
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as e:
                raise InvalidInputError(
                    f"cannot create the folder of task store {self.path}: {e.strerror or e}"
                ) from None
        try:
            self._con = sqlite3.connect(str(self.path), isolation_level=None, timeout=self.timeout)
        except sqlite3.Error as e:
            raise InvalidInputError(f"cannot open task store {self.path}: {e}") from None
        self._con.row_factory = sqlite3.Row
        try:
            with self._guard("not a usable SQLite task store"):
                self._con.execute("PRAGMA foreign_keys = ON")
                self._migrate()
                self._check_schema()
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
            con, self._con = self._con, None
            with suppress(sqlite3.Error):
                con.close()

    @property
    def con(self) -> sqlite3.Connection:
        if self._con is None:
            raise InvalidInputError(f"task store {self.path} is closed")
        return self._con

    def _sql_error(self, e: sqlite3.Error, what: str) -> MMPAError:
        """The MMPAError for SQLite's ``e`` raised while doing ``what``."""
        if _is_locked(e):
            return StoreLockedError(
                f"task store {self.path} is locked by another process (waited "
                f"{self.timeout:g} s); try again when it is done (SQLite: {e})"
            )
        return CorruptTaskError(
            f"{self.path}: {what} (SQLite: {e}); the file is damaged or its tables were "
            "edited outside mmpa"
        )

    @contextmanager
    def _guard(self, what: str) -> Iterator[None]:
        """Re-raise any ``sqlite3.Error`` of the block as :meth:`_sql_error` (no traceback)."""
        try:
            yield
        except sqlite3.Error as e:
            raise self._sql_error(e, what) from None
        except UnicodeDecodeError as e:  # sqlite3 decodes TEXT values (and the schema) as UTF-8
            raise CorruptTaskError(
                f"{self.path}: {what} (text that is not UTF-8: {e.reason} at byte {e.start}); "
                "the file is damaged or its tables were edited outside mmpa"
            ) from None

    def _rollback(self) -> None:
        if self._con is not None and self._con.in_transaction:
            with suppress(sqlite3.Error):
                self._con.execute("ROLLBACK")

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One write transaction: committed if the block returns, rolled back otherwise."""
        con = self.con
        con.execute("BEGIN IMMEDIATE")
        try:
            yield con
        except BaseException:
            self._rollback()
            raise
        con.execute("COMMIT")

    @contextmanager
    def _snapshot(self) -> Iterator[sqlite3.Connection]:
        """One read transaction: every SELECT of the block sees the same state."""
        con = self.con
        con.execute("BEGIN")
        try:
            yield con
        except BaseException:
            self._rollback()
            raise
        con.execute("COMMIT")

    def schema_version(self) -> int:
        """The schema version of the open store."""
        with self._guard("cannot read the schema version"):
            return self._read_version()

    def _read_version(self) -> int:
        tables = {
            r[0] for r in self.con.execute("SELECT name FROM sqlite_master WHERE type='table'")
        }
        if "schema_version" not in tables:
            if tables:
                raise CorruptTaskError(
                    f"{self.path} is an SQLite database but not an mmpa task store "
                    f"(tables: {', '.join(sorted(tables))}, no schema_version)"
                )
            return 0
        value = self.con.execute("SELECT MAX(version) FROM schema_version").fetchone()[0]
        if value is None:
            return 0
        if isinstance(value, bool) or not isinstance(value, int):
            raise CorruptTaskError(
                f"{self.path}: schema_version.version holds {value!r}, not an integer"
            )
        if value < 1:  # versions start at 1; migrating "from" -1 would look up version 0
            raise CorruptTaskError(
                f"{self.path}: schema_version.version holds {value}, expected 1 or more"
            )
        return value

    def _migrate(self) -> None:
        current = self._read_version()  # a read: an up-to-date store needs no write lock
        if current == SCHEMA_VERSION:
            return
        with self._tx() as con:
            current = self._read_version()  # again, under the write lock
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

    def _check_schema(self) -> None:
        """CorruptTaskError naming any table or column the store lacks."""
        for table, want in _COLUMNS.items():
            have = {r[1] for r in self.con.execute(f"PRAGMA table_info({table})")}
            if not have:
                raise CorruptTaskError(f"{self.path}: table {table!r} is missing")
            lack = [c for c in want if c not in have]
            if lack:
                raise CorruptTaskError(
                    f"{self.path}: table {table!r} lacks column(s) {', '.join(lack)}"
                )

    # ------------------------------------------------------------------------------- tasks

    def names(self) -> list[str]:
        """Stored task names, sorted."""
        with self._guard("cannot read the task names"):
            names = [r[0] for r in self.con.execute("SELECT name FROM tasks ORDER BY name")]
        for n in names:  # the key column allows NULL and blobs when edited outside mmpa
            if not isinstance(n, str):
                kind = _SQL_TYPE.get(type(n), type(n).__name__)
                raise CorruptTaskError(
                    f"{self.path}: column tasks.name holds {n!r:.40} ({kind}), expected text; "
                    "the file was edited outside mmpa"
                )
        return names

    def __contains__(self, name: object) -> bool:
        with self._guard("cannot look up a task"):
            row = self.con.execute("SELECT 1 FROM tasks WHERE name = ?", (name,)).fetchone()
        return row is not None

    def _not_found(self, name: str) -> TaskNotFoundError:
        return TaskNotFoundError(name, self.names(), str(self.path))

    def save(self, task: Task, *, overwrite: bool = False) -> None:
        """Store ``task`` in one transaction; TaskExistsError if the name is taken and not
        ``overwrite``. On any failure the store keeps what it had (the old task included)."""
        if not isinstance(task, Task):
            raise InvalidInputError(f"save() needs a Task, got {type(task).__name__}")
        blobs = path_blobs(task.path)
        ply = cloud_to_ply(task.cloud)
        rec = header_record(task, sha256(ply), path_digest(blobs))
        values = {
            **{k: rec[k] for k in _TEXT if k in rec},
            "format_version": rec["format_version"],
            **{col: json.dumps(rec[key], **_JSON) for col, key in _JSON_COLS.items()},
            "rate_hz": rec["rate_hz"],
            "n_points": rec["n_points"],
            "n_waypoints": rec["n_waypoints"],
            "duration": task.path.duration,
            "has_colors": int(rec["has_colors"]),
            "header_sha256": header_digest(rec),
        }
        cols = _COLUMNS["tasks"]
        insert = f"INSERT INTO tasks ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})"
        with self._guard(f"cannot save task {task.name!r}"), self._tx() as con:
            if con.execute("SELECT 1 FROM tasks WHERE name = ?", (task.name,)).fetchone():
                if not overwrite:
                    raise TaskExistsError(
                        f"task {task.name!r} already exists in {self.path}; pass "
                        "overwrite=True (CLI: --overwrite) or delete it first"
                    )
                con.execute("DELETE FROM tasks WHERE name = ?", (task.name,))
            con.execute(
                "INSERT INTO paths (task, t, q, T_arm_base_tool, gripper) VALUES (?, ?, ?, ?, ?)",
                (task.name, blobs["t"], blobs["q"], blobs["T_arm_base_tool"], blobs["gripper"]),
            )
            con.execute("INSERT INTO clouds (task, ply) VALUES (?, ?)", (task.name, ply))
            con.execute(insert, tuple(values[c] for c in cols))

    def _record(self, row: sqlite3.Row, where: str) -> dict[str, Any]:
        """The header record of a ``tasks`` row, every column type-checked and
        ``header_sha256`` verified; CorruptTaskError / UnsupportedVersionError naming the
        column."""

        def bad(col: str, want: str) -> CorruptTaskError:
            v = row[col]
            kind = _SQL_TYPE.get(type(v), type(v).__name__)
            shown = repr(v) if len(repr(v)) <= 40 else repr(v)[:40] + "..."
            return CorruptTaskError(f"{where}: column tasks.{col} holds {shown} ({kind}), {want}")

        def integer(col: str) -> int:
            v = row[col]
            if isinstance(v, bool) or not isinstance(v, int):
                raise bad(col, "expected an integer")
            return v

        def real(col: str) -> float:
            v = row[col]
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise bad(col, "expected a finite number")
            return float(v)

        version = integer("format_version")
        if version > FORMAT_VERSION:
            raise UnsupportedVersionError(
                f"{where} has format version {version}, newer than this mmpa reads "
                f"({FORMAT_VERSION}); upgrade mmpa"
            )
        if version < 1:
            raise bad("format_version", f"expected 1..{FORMAT_VERSION}")
        rec: dict[str, Any] = {"format_version": version}
        for col in _TEXT:
            if not isinstance(row[col], str):
                raise bad(col, "expected text")
            rec[col] = row[col]
        for col, key in _JSON_COLS.items():
            try:
                rec[key] = json.loads(row[col])
            except (TypeError, ValueError):
                raise bad(col, "expected JSON text") from None
        rec["rate_hz"] = real("rate_hz")
        rec["n_points"] = integer("n_points")
        rec["n_waypoints"] = integer("n_waypoints")
        if integer("has_colors") not in (0, 1):
            raise bad("has_colors", "expected 0 or 1")
        rec["has_colors"] = bool(row["has_colors"])
        duration = real("duration")
        if version >= 2:
            rec["duration"] = duration
        header = rec.pop("header_sha256")
        try:
            ok = header_digest(rec) == header
        except (TypeError, ValueError):  # a NaN in the JSON columns
            ok = False
        if not ok:
            raise CorruptTaskError(
                f"{where}: metadata (table 'tasks') does not match its header_sha256; "
                "a column was altered"
            )
        rec["duration"] = duration
        return rec

    def load(self, name: str) -> Task:
        """The task ``name``, every checksum verified (TaskNotFoundError, CorruptTaskError,
        UnsupportedVersionError, StoreLockedError)."""
        with self._guard(f"cannot read task {name!r}"), self._snapshot() as con:
            row = con.execute("SELECT * FROM tasks WHERE name = ?", (name,)).fetchone()
            cloud_row = con.execute("SELECT ply FROM clouds WHERE task = ?", (name,)).fetchone()
            path_row = con.execute("SELECT * FROM paths WHERE task = ?", (name,)).fetchone()
        if row is None:
            raise self._not_found(name)
        where = f"task {name!r} in {self.path}"
        rec = self._record(row, where)
        if cloud_row is None or path_row is None:
            missing = "clouds" if cloud_row is None else "paths"
            raise CorruptTaskError(f"{where}: its row in table {missing!r} is missing")
        if not isinstance(cloud_row["ply"], bytes):
            raise CorruptTaskError(f"{where}: clouds.ply is not a blob")
        ply = cloud_row["ply"]
        got = sha256(ply)
        if got != rec["cloud_sha256"]:
            raise CorruptTaskError(
                f"{where}: cloud (clouds.ply, {len(ply)} bytes) SHA-256 mismatch: stored "
                f"{rec['cloud_sha256'][:16]}..., computed {got[:16]}..."
            )
        blobs: dict[str, bytes | None] = {}
        for k in ("t", "q", "T_arm_base_tool", "gripper"):
            v = path_row[k]
            if v is not None and not isinstance(v, bytes):
                raise CorruptTaskError(f"{where}: paths.{k} is not a blob")
            blobs[k] = v
        got = path_digest(blobs)
        if got != rec["path_sha256"]:
            raise CorruptTaskError(
                f"{where}: path arrays (paths.t/q/T_arm_base_tool/gripper) SHA-256 mismatch: "
                f"stored {rec['path_sha256'][:16]}..., computed {got[:16]}..."
            )
        path = path_from_blobs(blobs, rec["n_waypoints"], rec["rate_hz"], f"{where}: paths")
        cloud = ply_to_cloud(ply, rec["cloud_frame"], f"{where}: clouds.ply")
        for col, stored, actual in (
            ("n_points", rec["n_points"], len(cloud)),
            ("has_colors", rec["has_colors"], cloud.colors is not None),
            ("duration", rec["duration"], path.duration),
        ):
            if stored != actual:
                raise CorruptTaskError(
                    f"{where}: column tasks.{col} = {stored!r} but the stored data give {actual!r}"
                )
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
                format_version=FORMAT_VERSION,  # older records are read as the current one
            )
        except InvalidInputError as e:
            raise CorruptTaskError(f"{where}: {e}") from None

    def list(self) -> list[TaskInfo]:
        """A summary of every task, sorted by name. Each row's types and ``header_sha256``
        are verified, and its blobs are there with the sizes the row promises (their first
        bytes and lengths only: a missing or truncated cloud or path is CorruptTaskError
        naming the task, as :meth:`load` would say; checksums are left to :meth:`load`)."""
        with self._guard("cannot list the tasks"):
            rows = self.con.execute(LIST_SQL).fetchall()
        out = []
        for r in rows:
            name = r["name"]
            where = f"task {name!r} in {self.path}"
            rec = self._record(r, where)
            check_blob_sizes(r, rec["n_points"], rec["n_waypoints"], where)
            out.append(
                TaskInfo(
                    name=rec["name"],
                    site=rec["site"],
                    created=parse_created(rec["created"], f"task {name!r} in {self.path}"),
                    n_points=rec["n_points"],
                    n_waypoints=rec["n_waypoints"],
                    duration=rec["duration"],
                    robot_id=rec["robot_id"],
                    description=rec["description"],
                    has_colors=rec["has_colors"],
                    rate_hz=rec["rate_hz"],
                )
            )
        return out

    def delete(self, name: str) -> None:
        """Remove ``name`` and its blobs in one transaction (TaskNotFoundError if absent)."""
        with self._guard(f"cannot delete task {name!r}"), self._tx() as con:
            deleted = con.execute("DELETE FROM tasks WHERE name = ?", (name,)).rowcount
            if deleted == 0:
                raise self._not_found(name)

    def export(self, name: str, directory: str | Path, *, overwrite: bool = False) -> Path:
        """Write the verified task ``name`` as a bundle into ``directory``; returns it."""
        return write_bundle(self.load(name), directory, overwrite=overwrite)

    def import_bundle(self, directory: str | Path, *, overwrite: bool = False) -> Task:
        """Verify the bundle in ``directory`` and save its task; returns the task."""
        task = read_bundle(directory)
        self.save(task, overwrite=overwrite)
        return task
