"""A task as a plain directory bundle: ``task.yaml`` + ``cloud.ply`` + ``path.csv``.

``task.yaml`` holds the metadata and poses (floats written exactly), the format version, the
size and SHA-256 of both data files, the SHA-256 of the path arrays and of the whole metadata
record (``header_sha256``, the same value the database stores). Reading checks all of them,
so a truncated or edited bundle is refused with :class:`~mmpa.errors.CorruptTaskError`
naming the file and what mismatched; a bundle from a newer mmpa raises
:class:`~mmpa.errors.UnsupportedVersionError`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from mmpa.errors import (
    CorruptTaskError,
    InvalidInputError,
    TaskExistsError,
    UnsupportedVersionError,
)
from mmpa.tasks.formats import (
    cloud_to_ply,
    csv_to_path,
    header_digest,
    header_record,
    parse_created,
    path_blobs,
    path_digest,
    path_to_csv,
    ply_to_cloud,
    sha256,
)
from mmpa.tasks.model import FORMAT_VERSION, Task

__all__ = ["BUNDLE_FILES", "read_bundle", "write_bundle"]

TASK_YAML, CLOUD_PLY, PATH_CSV = "task.yaml", "cloud.ply", "path.csv"
BUNDLE_FILES = (TASK_YAML, CLOUD_PLY, PATH_CSV)


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def write_bundle(task: Task, directory: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``task`` into ``directory`` (created if needed); returns the directory.

    Refuses (TaskExistsError) to replace an existing bundle unless ``overwrite``. The data
    files are written first and ``task.yaml`` last, each atomically, so an interrupted export
    leaves no ``task.yaml`` that points at missing data.
    """
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise InvalidInputError(f"bundle destination {d} exists and is not a directory")
    present = [f for f in BUNDLE_FILES if (d / f).exists()]
    if present and not overwrite:
        raise TaskExistsError(
            f"{d} already holds a task bundle ({', '.join(present)}); choose another directory "
            "or overwrite (CLI: --overwrite)"
        )
    d.mkdir(parents=True, exist_ok=True)
    ply = cloud_to_ply(task.cloud)
    csv = path_to_csv(task.path)
    path_sha = path_digest(path_blobs(task.path))
    record = header_record(task, sha256(ply), path_sha)
    doc: dict[str, Any] = {
        "format_version": task.format_version,
        "name": task.name,
        "site": task.site,
        "robot_id": task.robot_id,
        "created": record["created"],
        "description": task.description,
        "meta": record["meta"],
        "T_map_base_park": record["T_map_base_park"],
        "q_sample": record["q_sample"],
        "T_arm_base_camera": record["T_arm_base_camera"],
        "cloud": {
            "file": CLOUD_PLY,
            "frame": task.cloud.frame,
            "n_points": len(task.cloud),
            "has_colors": task.has_colors,
            "colors": "uchar (0..255)" if task.has_colors else "none",
            "bytes": len(ply),
            "sha256": record["cloud_sha256"],
        },
        "path": {
            "file": PATH_CSV,
            "rate_hz": record["rate_hz"],
            "n_waypoints": len(task.path),
            "duration_s": task.path.duration,
            "bytes": len(csv),
            "sha256": sha256(csv),
            "arrays_sha256": path_sha,
        },
        "header_sha256": header_digest(record),
    }
    text = "# mmpa task bundle: edit nothing; every field is covered by a checksum\n"
    text += yaml.dump(doc, Dumper=_Dumper, sort_keys=False, default_flow_style=False, width=120)
    _atomic_write(d / CLOUD_PLY, ply)
    _atomic_write(d / PATH_CSV, csv)
    _atomic_write(d / TASK_YAML, text.encode("utf-8"))
    return d


_MISSING = object()


class _Dumper(yaml.SafeDumper):
    """Block mappings; a list of scalars (a pose row, a joint vector) on one line."""


def _represent_list(dumper: yaml.SafeDumper, data: list) -> yaml.Node:
    flow = all(not isinstance(v, list | dict) for v in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_Dumper.add_representer(list, _represent_list)


def _field(doc: dict[str, Any], key: str, kind: type | tuple[type, ...]) -> Any:
    """``doc[a][b]`` for ``key='a.b'`` of type ``kind``; CorruptTaskError naming the field."""
    value: Any = doc
    for part in key.split("."):
        value = value.get(part, _MISSING) if isinstance(value, dict) else _MISSING
    if value is _MISSING:
        raise CorruptTaskError(f"{TASK_YAML}: missing field {key!r}")
    if isinstance(value, bool) and bool not in (kind if isinstance(kind, tuple) else (kind,)):
        raise CorruptTaskError(f"{TASK_YAML}: field {key!r} is a bool, expected {kind}")
    if not isinstance(value, kind):
        raise CorruptTaskError(
            f"{TASK_YAML}: field {key!r} has type {type(value).__name__}, expected "
            f"{getattr(kind, '__name__', kind)}"
        )
    return value


def _read_checked(d: Path, name: str, size: int, digest: str) -> bytes:
    p = d / name
    if not p.is_file():
        raise CorruptTaskError(f"{p}: missing from the bundle")
    data = p.read_bytes()
    if len(data) != size:
        what = "truncated" if len(data) < size else "longer than recorded"
        raise CorruptTaskError(f"{p}: {what}: {len(data)} bytes, {TASK_YAML} records {size} bytes")
    got = sha256(data)
    if got != digest:
        raise CorruptTaskError(
            f"{p}: SHA-256 mismatch: {TASK_YAML} records {digest[:16]}..., file has "
            f"{got[:16]}... (the file was modified)"
        )
    return data


def read_bundle(directory: str | Path) -> Task:
    """Read and verify the bundle in ``directory`` (see the module docstring)."""
    d = Path(directory)
    if not d.is_dir():
        raise InvalidInputError(f"task bundle directory {d} does not exist")
    y = d / TASK_YAML
    if not y.is_file():
        raise CorruptTaskError(f"{y}: missing; {d} is not a task bundle")
    try:
        doc = yaml.safe_load(y.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise CorruptTaskError(f"{y}: not valid YAML (truncated or edited?): {e}") from None
    if not isinstance(doc, dict):
        raise CorruptTaskError(f"{y}: expected a mapping of task fields")
    version = _field(doc, "format_version", int)
    if version > FORMAT_VERSION:
        raise UnsupportedVersionError(
            f"{y}: task format version {version} is newer than this mmpa reads "
            f"({FORMAT_VERSION}); upgrade mmpa"
        )
    ply = _read_checked(
        d, CLOUD_PLY, _field(doc, "cloud.bytes", int), _field(doc, "cloud.sha256", str)
    )
    csv = _read_checked(
        d, PATH_CSV, _field(doc, "path.bytes", int), _field(doc, "path.sha256", str)
    )
    rate = _field(doc, "path.rate_hz", (int, float))
    path = csv_to_path(csv, float(rate), str(d / PATH_CSV))
    arrays_sha = path_digest(path_blobs(path))
    if arrays_sha != _field(doc, "path.arrays_sha256", str):
        raise CorruptTaskError(f"{d / PATH_CSV}: path arrays do not match path.arrays_sha256")
    cloud = ply_to_cloud(ply, _field(doc, "cloud.frame", str), str(d / CLOUD_PLY))
    try:
        task = Task(
            name=_field(doc, "name", str),
            site=_field(doc, "site", str),
            T_map_base_park=_field(doc, "T_map_base_park", list),
            q_sample=_field(doc, "q_sample", list),
            T_arm_base_camera=_field(doc, "T_arm_base_camera", list),
            cloud=cloud,
            path=path,
            robot_id=_field(doc, "robot_id", str),
            created=parse_created(_field(doc, "created", str), str(y)),
            description=_field(doc, "description", str),
            meta=_field(doc, "meta", dict),
            format_version=version,
        )
    except InvalidInputError as e:
        raise CorruptTaskError(f"{y}: {e}") from None
    if _field(doc, "cloud.n_points", int) != len(cloud):
        raise CorruptTaskError(f"{y}: cloud.n_points differs from the {len(cloud)} points in ply")
    if _field(doc, "path.n_waypoints", int) != len(path):
        raise CorruptTaskError(f"{y}: path.n_waypoints differs from the {len(path)} csv rows")
    record = header_record(task, sha256(ply), arrays_sha)
    want = _field(doc, "header_sha256", str)
    if header_digest(record) != want:
        raise CorruptTaskError(
            f"{y}: metadata checksum mismatch (header_sha256): a field of {TASK_YAML} was "
            "edited after export"
        )
    return task
