"""A task as a plain directory bundle: ``task.yaml`` + ``cloud.ply`` + ``path.csv``.

``task.yaml`` holds the metadata and poses (floats written exactly), the format version, the
size and SHA-256 of both data files, the SHA-256 of the path arrays and of the whole metadata
record (``header_sha256``, the same value the database stores). Reading checks all of them,
so a truncated or edited bundle is refused with :class:`~mmpa.core.errors.CorruptTaskError`
naming the file and what mismatched; a bundle from a newer mmpa raises
:class:`~mmpa.core.errors.UnsupportedVersionError`.

Reading trusts nothing in the directory: every file must be a regular file inside it (a
symbolic link, or anything else, is refused before it is opened), its size is checked with
``fstat`` before a byte is read (and never more than :data:`MAX_FILE_BYTES`), and
``task.yaml`` is parsed by :func:`mmpa.core.yamlio.load_yaml_text` (safe types, no aliases).
Writing builds the whole bundle in a temporary directory next to the target and renames it
into place, so an export that fails at any point leaves the old bundle as it was.
"""

from __future__ import annotations

import dataclasses
import os
import secrets
import shutil
import stat
from pathlib import Path
from typing import Any

import yaml

from mmpa.core.errors import (
    ConfigError,
    CorruptTaskError,
    InvalidInputError,
    TaskExistsError,
    UnsupportedVersionError,
)
from mmpa.core.yamlio import MAX_YAML_BYTES, load_yaml_text
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

__all__ = ["BUNDLE_FILES", "MAX_FILE_BYTES", "read_bundle", "write_bundle"]

TASK_YAML, CLOUD_PLY, PATH_CSV = "task.yaml", "cloud.ply", "path.csv"
BUNDLE_FILES = (TASK_YAML, CLOUD_PLY, PATH_CSV)
#: Largest ``cloud.ply`` / ``path.csv`` read (bytes): ~70 M colored points, far above a scan.
MAX_FILE_BYTES = 1 << 30


def _write_file(path: Path, data: bytes) -> None:
    with open(path, "xb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


def write_bundle(task: Task, directory: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``task`` into ``directory`` (created if needed); returns the directory.

    Refuses (TaskExistsError) to replace an existing bundle unless ``overwrite``, and
    (InvalidInputError) to replace a directory that holds anything besides a bundle. The
    three files are written (and fsync'ed) into a new directory next to ``directory``, which
    then takes its place by rename: a failure at any point before leaves the old bundle
    complete; a crash between the two renames of an overwrite leaves both the old bundle
    (``.NAME.old-*``) and the new one (``.NAME.tmp-*``) complete beside it.
    """
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise InvalidInputError(f"bundle destination {d} exists and is not a directory")
    real = d.resolve() if d.is_symlink() else d  # keep a link to the bundle working
    try:
        old: list[str] = sorted(p.name for p in real.iterdir()) if real.is_dir() else []
    except OSError as e:
        raise InvalidInputError(f"cannot read bundle destination {d}: {e.strerror or e}") from None
    present = [f for f in BUNDLE_FILES if f in old]
    if present and not overwrite:
        raise TaskExistsError(
            f"{d} already holds a task bundle ({', '.join(present)}); choose another directory "
            "or overwrite (CLI: --overwrite)"
        )
    other = [n for n in old if n not in BUNDLE_FILES]
    if other:
        shown = ", ".join(other[:5]) + (" ..." if len(other) > 5 else "")
        raise InvalidInputError(
            f"bundle destination {d} holds other files ({shown}); export into a new or empty "
            "directory (a bundle directory holds only task.yaml, cloud.ply and path.csv)"
        )
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
    _replace_dir(real, {CLOUD_PLY: ply, PATH_CSV: csv, TASK_YAML: text.encode("utf-8")})
    return d


def _replace_dir(d: Path, files: dict[str, bytes]) -> None:
    """Make ``d`` a directory holding exactly ``files`` (name -> bytes), by rename."""
    try:
        d.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InvalidInputError(
            f"cannot create the folder of bundle {d}: {e.strerror or e}"
        ) from None
    tag = f"{os.getpid()}-{secrets.token_hex(4)}"
    tmp = d.parent / f".{d.name}.tmp-{tag}"
    backup = d.parent / f".{d.name}.old-{tag}"
    try:
        os.mkdir(tmp)
        if d.is_dir():
            os.chmod(tmp, stat.S_IMODE(d.stat().st_mode))
        for name, data in files.items():
            _write_file(tmp / name, data)
        _fsync_dir(tmp)
        if d.is_dir():
            os.rename(d, backup)
            try:
                os.rename(tmp, d)
            except BaseException:
                os.rename(backup, d)
                raise
            _remove_tree(backup)
        else:
            os.rename(tmp, d)
        _fsync_dir(d.parent)
    except OSError as e:
        raise InvalidInputError(f"cannot write bundle {d}: {e.strerror or e}") from None
    finally:
        if tmp.exists():
            _remove_tree(tmp)


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


def _read_regular(d: Path, name: str, limit: int, size: int | None = None) -> bytes:
    """The bytes of the regular file ``d/name``: at most ``limit``, exactly ``size`` if given.

    Refuses a symbolic link (even one pointing inside ``d``), a device, a FIFO or a
    directory, a file larger than ``limit`` and one whose size is not ``size``, each before
    a byte is read (CorruptTaskError naming the file).
    """
    p = d / name
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        raise CorruptTaskError(f"{p}: missing from the bundle") from None
    except OSError as e:
        raise CorruptTaskError(f"{p}: cannot read: {e.strerror or e}") from None
    if stat.S_ISLNK(st.st_mode):
        raise CorruptTaskError(
            f"{p}: is a symbolic link (to {os.readlink(p)}); a bundle holds regular files only"
        )
    if not stat.S_ISREG(st.st_mode):
        raise CorruptTaskError(f"{p}: not a regular file; a bundle holds regular files only")
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(p, flags)
    except OSError as e:  # replaced by a link since lstat
        raise CorruptTaskError(f"{p}: cannot open as a regular file: {e.strerror or e}") from None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise CorruptTaskError(f"{p}: not a regular file; a bundle holds regular files only")
        if size is not None and st.st_size != size:
            what = "truncated" if st.st_size < size else "longer than recorded"
            raise CorruptTaskError(
                f"{p}: {what}: {st.st_size} bytes, {TASK_YAML} records {size} bytes"
            )
        if st.st_size > limit:
            raise CorruptTaskError(
                f"{p}: {st.st_size} bytes, more than the {limit} a bundle file may have"
            )
        data = f.read(limit + 1)  # the file may grow after fstat
    if len(data) > limit or (size is not None and len(data) != size):
        raise CorruptTaskError(f"{p}: changed size while it was read")
    return data


def _read_checked(d: Path, name: str, size: int, digest: str) -> bytes:
    """``d/name`` if it has ``size`` bytes and SHA-256 ``digest``; the size is compared with
    the file's ``fstat`` before anything is read (a huge or sparse file is not read)."""
    if not 0 <= size <= MAX_FILE_BYTES:
        raise CorruptTaskError(
            f"{d / TASK_YAML}: records {size} bytes for {name}, outside the 0..{MAX_FILE_BYTES} "
            "a bundle file may have"
        )
    data = _read_regular(d, name, MAX_FILE_BYTES, size)
    got = sha256(data)
    if got != digest:
        raise CorruptTaskError(
            f"{d / name}: SHA-256 mismatch: {TASK_YAML} records {digest[:16]}..., file has "
            f"{got[:16]}... (the file was modified)"
        )
    return data


def read_bundle(directory: str | Path) -> Task:
    """Read and verify the bundle in ``directory`` (see the module docstring)."""
    d = Path(directory)
    if not d.is_dir():
        raise InvalidInputError(f"task bundle directory {d} does not exist")
    y = d / TASK_YAML
    if not os.path.lexists(y):
        raise CorruptTaskError(f"{y}: missing; {d} is not a task bundle")
    raw = _read_regular(d, TASK_YAML, MAX_YAML_BYTES)
    try:
        doc = load_yaml_text(raw.decode("utf-8"), str(y))
    except UnicodeDecodeError as e:
        raise CorruptTaskError(f"{y}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except ConfigError as e:
        raise CorruptTaskError(f"{e} (truncated or edited?)") from None
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
    if _field(doc, "cloud.has_colors", bool) != task.has_colors:
        raise CorruptTaskError(
            f"{y}: cloud.has_colors differs from {CLOUD_PLY} (which has "
            f"{'colors' if task.has_colors else 'no colors'})"
        )
    if _field(doc, "path.duration_s", (int, float)) != path.duration:
        raise CorruptTaskError(
            f"{y}: path.duration_s differs from the last time stamp of {PATH_CSV} "
            f"({path.duration!r} s)"
        )
    record = header_record(task, sha256(ply), arrays_sha)  # the rules of the file's version
    want = _field(doc, "header_sha256", str)
    if header_digest(record) != want:
        raise CorruptTaskError(
            f"{y}: metadata checksum mismatch (header_sha256): a field of {TASK_YAML} was "
            "edited after export"
        )
    if version < FORMAT_VERSION:  # verified as written; read as the current version
        task = dataclasses.replace(task, format_version=FORMAT_VERSION)
    return task
