"""Taught tasks (paper 000 §3.1) and their store (DESIGN.md "Storage").

``Task`` / ``ToolPath`` hold what one-shot teaching records; ``TaskStore`` keeps them in one
SQLite file with checksums and transactions; ``write_bundle`` / ``read_bundle`` (and
``TaskStore.export`` / ``import_bundle``) move a task as a directory of ``task.yaml`` +
``cloud.ply`` + ``path.csv``. No pickle anywhere.
"""

from __future__ import annotations

from mmpa.core.errors import (
    CorruptTaskError,
    TaskExistsError,
    TaskNotFoundError,
    UnsupportedVersionError,
)
from mmpa.tasks.bundle import read_bundle, write_bundle
from mmpa.tasks.model import FORMAT_VERSION, Task, TaskInfo, ToolPath
from mmpa.tasks.store import (
    DEFAULT_BUSY_TIMEOUT_S,
    SCHEMA_VERSION,
    StoreLockedError,
    TaskStore,
    default_store_path,
)

__all__ = [
    "DEFAULT_BUSY_TIMEOUT_S",
    "FORMAT_VERSION",
    "SCHEMA_VERSION",
    "CorruptTaskError",
    "StoreLockedError",
    "Task",
    "TaskExistsError",
    "TaskInfo",
    "TaskNotFoundError",
    "TaskStore",
    "ToolPath",
    "UnsupportedVersionError",
    "default_store_path",
    "read_bundle",
    "write_bundle",
]
