"""The task store's SQLite schema: its version, the migrations (version -> SQL statements,
run in order, each in a transaction by :class:`~mmpa.tasks.store.TaskStore`), and the query
that lists every task with its blobs' types, sizes and first bytes (the layout is in
:mod:`mmpa.tasks.store`'s docstring)."""

from __future__ import annotations

__all__ = ["LIST_SQL", "MIGRATIONS", "SCHEMA_VERSION"]

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

#: every ``tasks`` column, with the types, sizes and first bytes of the task's blobs
LIST_SQL = (
    "SELECT tasks.*, clouds.task AS c_task, substr(CAST(clouds.ply AS BLOB), 1, 4096) AS ply_head, "
    "paths.task AS p_task, "
    + ", ".join(
        f"typeof({c}) AS {c.split('.')[1]}_type, length({c}) AS {c.split('.')[1]}_len"
        for c in ("clouds.ply", "paths.t", "paths.q", "paths.T_arm_base_tool", "paths.gripper")
    )
    + " FROM tasks LEFT JOIN clouds ON clouds.task = tasks.name"
    " LEFT JOIN paths ON paths.task = tasks.name ORDER BY tasks.name"
)
