"""Byte formats of a task: the cloud as PLY, the path as float64 blobs or a CSV, checksums.

Decisions (DESIGN.md "Storage"):

- Cloud: binary little-endian PLY 1.0 with ``double x, y, z`` (bit-exact points) and, for a
  colored cloud, ``uchar red, green, blue``. 8-bit colors are what the camera delivers
  (``RGBDFrame.to_point_cloud`` divides uint8 by 255), so they round-trip bit-exactly; any
  other color in [0, 1] comes back within 0.5/255. A colorless cloud has no color properties.
  Open3D, CloudCompare and MeshLab read the file; the reader here accepts any binary
  little-endian vertex-only PLY with scalar properties (e.g. one written by Open3D).
- Path in the database: one little-endian float64 blob per array, and a SHA-256 over the
  blobs (with their names and lengths), checked before anything is parsed.
- Path in a bundle: ``path.csv``, one row per waypoint, columns ``t, q1..q6, x, y, z, qx, qy,
  qz, qw, gripper`` for people (quaternion x, y, z, w with w >= 0; gripper empty when the
  task has none), then ``r11..r33``, the rotation matrix row-major, so that the round trip
  is bit-exact (a quaternion is not). Floats are written with ``repr`` (shortest exact).
  On import the quaternion must agree with the matrix.
- Header: the task's metadata as canonical JSON (sorted keys, repr floats, no NaN) whose
  SHA-256 covers every field that is not in a blob, including the blob checksums and, from
  format version 2, the path duration (what ``mmpa tasks list`` shows without the blobs).
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
from collections.abc import Mapping
from datetime import datetime
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from mmpa.core.errors import CorruptTaskError, InvalidInputError
from mmpa.robot.interfaces import PointCloud
from mmpa.tasks.model import Task, ToolPath

__all__ = [
    "PATH_COLUMNS",
    "check_blob_sizes",
    "check_path_sizes",
    "check_ply_size",
    "cloud_to_ply",
    "csv_to_path",
    "header_digest",
    "header_record",
    "path_blobs",
    "path_digest",
    "path_from_blobs",
    "path_to_csv",
    "ply_to_cloud",
    "sha256",
]

PATH_COLUMNS: tuple[str, ...] = (
    "t",
    *(f"q{i}" for i in range(1, 7)),
    "x",
    "y",
    "z",
    "qx",
    "qy",
    "qz",
    "qw",
    "gripper",
    *(f"r{i}{j}" for i in range(1, 4) for j in range(1, 4)),
)
_QUAT_TOL = 1e-5  # agreement of the CSV quaternion with the CSV rotation matrix


def sha256(data: bytes) -> str:
    """Hex SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


# ---------------------------------------------------------------------------------------- PLY

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "<i2",
    "int16": "<i2",
    "ushort": "<u2",
    "uint16": "<u2",
    "int": "<i4",
    "int32": "<i4",
    "uint": "<u4",
    "uint32": "<u4",
    "float": "<f4",
    "float32": "<f4",
    "double": "<f8",
    "float64": "<f8",
}


def cloud_to_ply(cloud: PointCloud) -> bytes:
    """Binary little-endian PLY: ``double x y z`` and, if colored, ``uchar red green blue``."""
    p = np.asarray(cloud.points, dtype=np.float64)
    n = p.shape[0]
    fields: list[tuple[str, str]] = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if cloud.colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.empty(n, dtype=np.dtype(fields))
    rec["x"], rec["y"], rec["z"] = p[:, 0], p[:, 1], p[:, 2]
    if cloud.colors is not None:
        c8 = np.rint(np.clip(np.asarray(cloud.colors, dtype=np.float64), 0, 1) * 255.0)
        rec["red"], rec["green"], rec["blue"] = c8[:, 0], c8[:, 1], c8[:, 2]
    props = "".join(
        f"property {'double' if t == '<f8' else 'uchar'} {name}\n" for name, t in fields
    )
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by mmpa\n"
        f"element vertex {n}\n{props}end_header\n"
    )
    return header.encode("ascii") + rec.tobytes()


def _ply_header(data: bytes, source: str) -> tuple[int, np.dtype, int]:
    """The vertex count, the vertex record dtype and the body offset of a binary
    little-endian vertex-only PLY (``data``: the file, or its first bytes)."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise CorruptTaskError(f"{source}: not a PLY file (missing 'ply' or 'end_header')")
    try:
        lines = data[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError:
        raise CorruptTaskError(f"{source}: PLY header is not ASCII") from None
    n: int | None = None
    fields: list[tuple[str, str]] = []
    fmt = None
    for line in lines:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1:]
        elif tok[0] == "element":
            if n is not None or len(tok) != 3 or tok[1] != "vertex":
                raise CorruptTaskError(f"{source}: only one 'element vertex N' is supported")
            try:
                n = int(tok[2])
            except ValueError:
                raise CorruptTaskError(f"{source}: bad vertex count {tok[2]!r}") from None
        elif tok[0] == "property":
            if n is None or len(tok) != 3 or tok[1] not in _PLY_TYPES:
                raise CorruptTaskError(f"{source}: unsupported PLY property line {line!r}")
            fields.append((tok[2], _PLY_TYPES[tok[1]]))
        else:
            raise CorruptTaskError(f"{source}: unexpected PLY header line {line!r}")
    if fmt != ["binary_little_endian", "1.0"]:
        raise CorruptTaskError(f"{source}: format {fmt} is not binary_little_endian 1.0")
    names = [f[0] for f in fields]
    if n is None or not {"x", "y", "z"} <= set(names):
        raise CorruptTaskError(f"{source}: needs a vertex element with x, y, z properties")
    try:
        dtype = np.dtype(fields)
    except (TypeError, ValueError) as e:
        raise CorruptTaskError(f"{source}: bad PLY properties: {e}") from None
    return n, dtype, end + len(b"end_header\n")


def check_ply_size(head: bytes, size: int, n_points: int, source: str = "cloud.ply") -> None:
    """Check a stored PLY from its first bytes ``head`` and its ``size`` (bytes) without
    reading it all: the header promises ``n_points`` vertices and the file holds exactly
    their bytes (a truncated or padded blob fails); CorruptTaskError naming ``source``."""
    n, dtype, off = _ply_header(head, source)
    if n != n_points:
        raise CorruptTaskError(f"{source}: {n} vertices, the task record says {n_points}")
    if size - off != n * dtype.itemsize:
        raise CorruptTaskError(
            f"{source}: vertex data has {size - off} bytes, the header promises "
            f"{n} x {dtype.itemsize} = {n * dtype.itemsize} (truncated or padded)"
        )


def ply_to_cloud(data: bytes, frame: str = "camera", source: str = "cloud.ply") -> PointCloud:
    """Parse a binary little-endian vertex-only PLY; CorruptTaskError naming ``source``."""
    n, dtype, off = _ply_header(data, source)
    check_ply_size(data, len(data), n, source)
    names = list(dtype.names or ())
    rec = np.frombuffer(data[off:], dtype=dtype, count=n)
    pts = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    colors = None
    rgb = ("red", "green", "blue")
    if all(c in names for c in rgb):
        colors = np.stack([rec[c] for c in rgb], axis=1).astype(np.float64)
        if dtype["red"].kind in "iu":
            colors /= float(np.iinfo(dtype["red"]).max)
    try:
        return PointCloud(pts, colors, frame)
    except InvalidInputError as e:
        raise CorruptTaskError(f"{source}: {e}") from None


# --------------------------------------------------------------------------------------- path

_BLOB_NAMES = ("t", "q", "T_arm_base_tool", "gripper")


def path_blobs(path: ToolPath) -> dict[str, bytes | None]:
    """Little-endian float64 bytes of each path array (``gripper`` None when absent)."""

    def b(a: np.ndarray | None) -> bytes | None:
        return None if a is None else np.ascontiguousarray(a, dtype="<f8").tobytes()

    return {k: b(getattr(path, k)) for k in _BLOB_NAMES}


def path_digest(blobs: dict[str, bytes | None]) -> str:
    """SHA-256 over the path blobs, each prefixed by its name and length (or 'none')."""
    h = hashlib.sha256()
    for k in _BLOB_NAMES:
        v = blobs[k]
        h.update(f"{k}:{'none' if v is None else len(v)}:".encode())
        if v is not None:
            h.update(v)
    return h.hexdigest()


_PATH_SHAPES = {"t": (), "q": (6,), "T_arm_base_tool": (4, 4), "gripper": ()}


def check_path_sizes(sizes: dict[str, int | None], n: int, source: str = "path") -> None:
    """Check the byte sizes of the path blobs (None: absent; only ``gripper`` may be) against
    ``n`` waypoints of float64 arrays; CorruptTaskError naming ``source`` and the array."""
    for k in _BLOB_NAMES:
        size = sizes.get(k)
        if size is None:
            if k != "gripper":
                raise CorruptTaskError(f"{source}.{k} is missing")
            continue
        want = 8 * n * int(np.prod(_PATH_SHAPES[k]))
        if size != want:
            raise CorruptTaskError(
                f"{source}.{k} has {size} bytes, expected {want} for {n} waypoints"
            )


def path_from_blobs(
    blobs: dict[str, bytes | None], n: int, rate_hz: float, source: str = "path"
) -> ToolPath:
    """Inverse of :func:`path_blobs` for ``n`` waypoints; CorruptTaskError on a size mismatch."""
    check_path_sizes({k: None if v is None else len(v) for k, v in blobs.items()}, n, source)
    arrays: dict[str, np.ndarray | None] = {}
    for k in _BLOB_NAMES:
        v = blobs[k]
        shape = (n, *_PATH_SHAPES[k])
        arrays[k] = None if v is None else np.frombuffer(v, "<f8").reshape(shape).astype(float)
    try:
        return ToolPath(
            arrays["t"], arrays["q"], arrays["T_arm_base_tool"], rate_hz, arrays["gripper"]
        )
    except InvalidInputError as e:
        raise CorruptTaskError(f"{source}: {e}") from None


def _quat_xyzw(R: np.ndarray) -> np.ndarray:
    q = Rotation.from_matrix(R).as_quat()
    return np.where(q[:, 3:4] < 0, -q, q)


def path_to_csv(path: ToolPath) -> bytes:
    """``path.csv`` bytes (see the module docstring for the columns)."""
    T = path.T_arm_base_tool
    quat = _quat_xyzw(T[:, :3, :3])
    out = io.StringIO()
    out.write(",".join(PATH_COLUMNS) + "\n")
    for i in range(len(path)):
        vals = [path.t[i], *path.q[i], *T[i, :3, 3], *quat[i]]
        row = [repr(float(v)) for v in vals]
        row.append("" if path.gripper is None else repr(float(path.gripper[i])))
        row += [repr(float(v)) for v in T[i, :3, :3].ravel()]
        out.write(",".join(row) + "\n")
    return out.getvalue().encode("ascii")


def csv_to_path(data: bytes, rate_hz: float, source: str = "path.csv") -> ToolPath:
    """Parse ``path.csv``; CorruptTaskError naming the row and column of any problem."""
    try:
        rows = list(csv.reader(io.StringIO(data.decode("ascii"))))
    except (UnicodeDecodeError, csv.Error) as e:
        raise CorruptTaskError(f"{source}: not a readable CSV ({e})") from None
    if not rows or tuple(c.strip() for c in rows[0]) != PATH_COLUMNS:
        raise CorruptTaskError(f"{source}: header must be {','.join(PATH_COLUMNS)}")
    body = rows[1:]
    if not body:
        raise CorruptTaskError(f"{source}: no waypoints")
    n, m = len(body), len(PATH_COLUMNS)
    vals = np.empty((n, m))
    grip_missing = np.zeros(n, dtype=bool)
    gi = PATH_COLUMNS.index("gripper")
    for i, row in enumerate(body):
        if len(row) != m:
            raise CorruptTaskError(f"{source}: row {i + 2} has {len(row)} columns, expected {m}")
        for j, cell in enumerate(row):
            if j == gi and cell == "":
                grip_missing[i] = True
                vals[i, j] = 0.0
                continue
            try:
                vals[i, j] = float(cell)
            except ValueError:
                raise CorruptTaskError(
                    f"{source}: row {i + 2}, column {PATH_COLUMNS[j]!r}: {cell!r} is not a number"
                ) from None
    if grip_missing.any() and not grip_missing.all():
        raise CorruptTaskError(f"{source}: column 'gripper' is empty in some rows but not all")
    col = {c: k for k, c in enumerate(PATH_COLUMNS)}
    T = np.zeros((n, 4, 4))
    T[:, 3, 3] = 1.0
    T[:, :3, :3] = vals[:, col["r11"] :].reshape(n, 3, 3)
    T[:, :3, 3] = vals[:, [col["x"], col["y"], col["z"]]]
    quat = vals[:, [col["qx"], col["qy"], col["qz"], col["qw"]]]
    norm = np.linalg.norm(quat, axis=1)
    if not np.all(np.isfinite(vals[:, col["r11"] :])) or np.any(~np.isfinite(norm) | (norm == 0)):
        raise CorruptTaskError(f"{source}: non-finite rotation or zero quaternion")
    R_q = Rotation.from_quat(quat).as_matrix()
    err = np.abs(R_q - T[:, :3, :3]).max(axis=(1, 2))
    if np.any(err > _QUAT_TOL):
        i = int(np.argmax(err))
        raise CorruptTaskError(
            f"{source}: row {i + 2}: quaternion (qx..qw) and rotation (r11..r33) disagree "
            f"by {err[i]:.2e}"
        )
    try:
        return ToolPath(
            vals[:, 0],
            vals[:, 1:7],
            T,
            rate_hz,
            None if grip_missing.all() else vals[:, gi],
        )
    except InvalidInputError as e:
        raise CorruptTaskError(f"{source}: {e}") from None


# ------------------------------------------------------------------------------------- header


def header_record(task: Task, cloud_sha256: str, path_sha256: str) -> dict[str, Any]:
    """Every non-blob field of ``task`` plus the blob checksums, as JSON-able values.

    The record of ``task.format_version``: version 1 lacks ``duration`` (s)."""
    rec: dict[str, Any] = {
        "format_version": task.format_version,
        "name": task.name,
        "site": task.site,
        "robot_id": task.robot_id,
        "created": task.created.isoformat(),
        "description": task.description,
        "meta": dict(task.meta),
        "T_map_base_park": task.T_map_base_park.tolist(),
        "q_sample": task.q_sample.tolist(),
        "T_arm_base_camera": task.T_arm_base_camera.tolist(),
        "rate_hz": float(task.path.rate_hz),
        "n_points": len(task.cloud),
        "n_waypoints": len(task.path),
        "has_colors": task.has_colors,
        "cloud_frame": task.cloud.frame,
        "cloud_sha256": cloud_sha256,
        "path_sha256": path_sha256,
    }
    if task.format_version >= 2:
        rec["duration"] = task.path.duration
    return rec


def header_digest(record: dict[str, Any]) -> str:
    """SHA-256 of the canonical JSON of a header record (sorted keys, repr floats)."""
    text = json.dumps(record, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return sha256(text.encode("utf-8"))


def parse_created(value: str, source: str) -> datetime:
    """ISO 8601 time stamp; CorruptTaskError naming ``source`` if malformed."""
    try:
        return datetime.fromisoformat(value)
    except (TypeError, ValueError):
        raise CorruptTaskError(f"{source}: 'created' {value!r} is not an ISO 8601 time") from None


def check_blob_sizes(row: Mapping[str, Any], n_points: int, n_waypoints: int, where: str) -> None:
    """Check a task's stored blobs from their SQL types, lengths and the PLY's first bytes
    (``row``: ``c_task`` / ``p_task`` None when the ``clouds`` / ``paths`` row is missing,
    ``ply_head``, and ``<blob>_type`` / ``<blob>_len`` of ``ply``, ``t``, ``q``,
    ``T_arm_base_tool``, ``gripper``): what a task listing can verify without reading the
    blobs. CorruptTaskError naming ``where``, as a full load would."""
    if row["c_task"] is None or row["p_task"] is None:
        missing = "clouds" if row["c_task"] is None else "paths"
        raise CorruptTaskError(f"{where}: its row in table {missing!r} is missing")
    if row["ply_type"] != "blob":
        raise CorruptTaskError(f"{where}: clouds.ply is not a blob")
    check_ply_size(row["ply_head"], row["ply_len"], n_points, f"{where}: clouds.ply")
    sizes: dict[str, int | None] = {}
    for k in _BLOB_NAMES:
        if row[f"{k}_type"] not in ("blob", "null"):
            raise CorruptTaskError(f"{where}: paths.{k} is not a blob")
        sizes[k] = row[f"{k}_len"]
    check_path_sizes(sizes, n_waypoints, f"{where}: paths")
