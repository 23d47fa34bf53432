"""Reader of CARMEN laser logs (the classic ``*.log`` 2D lidar data sets: Intel lab, CSAIL,
Freiburg 079, ...): text lines in, :class:`~mmpa.robot.interfaces.LaserScan` out.

The lines used (everything else -- ``PARAM``, ``NEFF``, ``#`` comments, other messages -- is
skipped):

- ``FLASER n r_1 .. r_n x y theta odom_x odom_y odom_theta timestamp host logger_timestamp``:
  a front laser scan of ``n`` beams (m) and the robot pose (``x y theta``; in the
  *corrected* logs the SLAM-corrected pose, m and rad);
- ``ODOM x y theta tv rv accel timestamp host logger_timestamp``: wheel odometry poses. In the
  corrected logs the odometry restarts from the corrected pose right after each scan (an
  ``ODOM`` line equal to that scan's pose) and follows the wheels to the next scan, so the
  increment between scans ``k - 1`` and ``k`` is ``inv(P_restart) * P_last`` (SE(2)), with
  ``P_restart`` the first ``ODOM`` after scan ``k - 1`` and ``P_last`` the last ``ODOM``
  before scan ``k``.

Beam angles: beam ``i`` of ``n`` points at ``-fov / 2 + i * step`` (``fov = pi``),
counter-clockwise from the robot's right, i.e. the ROS convention with a positive
``angle_increment``; ``step = fov / n`` for an even ``n`` (180 beams 1 degree apart, 360
beams 0.5 degree apart: the last beam stops one step short of ``+fov / 2``) and ``fov / (n -
1)`` for an odd ``n`` (181, 361: both ends). Checked against the corrected poses: the odd
scans of each log projected onto a map (2.5 cm cells) built from its even scans have this
share of endpoints within 5 cm of an occupied cell -- intel (180 beams) 0.949 (``fov / (n -
1)``: 0.914, shifted by half a step: 0.916, clockwise: 0.102), freiburg-079 (360) 0.947
(0.937, 0.937, 0.184), csail (361) 0.905 (``fov / n``: 0.900, clockwise 0.080).

Readings at or above ``no_return`` (these logs write 81.83 / 81.91 m for "nothing seen") are
``inf`` (the ``LaserScan`` convention for no return).

:func:`parse_carmen` is pure (lines in); :func:`read_carmen` opens a file (``.gz`` too).
"""

from __future__ import annotations

import gzip
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.robot.interfaces import LaserScan

__all__ = ["CarmenLog", "parse_carmen", "read_carmen", "relative_pose"]


@dataclass(frozen=True)
class CarmenLog:
    """The scans of a CARMEN log with their poses.

    ``scans`` (N,) scans; ``poses`` (N, 3) the logged (corrected) pose of each scan ``[x, y,
    theta]`` (m, rad); ``increments`` (N, 3) the wheel odometry increment ``[dx, dy, dtheta]``
    from scan ``k - 1`` to scan ``k`` in the frame of scan ``k - 1`` (row 0: zeros);
    ``odometry`` (N, 3) the odometry poses obtained by chaining the increments from
    ``poses[0]``; ``stamps`` (N,) s."""

    scans: tuple[LaserScan, ...]
    poses: Array
    increments: Array
    odometry: Array
    stamps: Array

    def __len__(self) -> int:
        return len(self.scans)


def relative_pose(a: Array, b: Array) -> Array:
    """``inv(a) * b`` for SE(2) poses ``[x, y, theta]``: ``b`` in the frame of ``a``."""
    c, s = np.cos(a[2]), np.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    dth = (b[2] - a[2] + np.pi) % (2 * np.pi) - np.pi
    return np.array([c * dx + s * dy, -s * dx + c * dy, dth])


def _compose(a: Array, d: Array) -> Array:
    c, s = np.cos(a[2]), np.sin(a[2])
    th = (a[2] + d[2] + np.pi) % (2 * np.pi) - np.pi
    return np.array([a[0] + c * d[0] - s * d[1], a[1] + s * d[0] + c * d[1], th])


def _floats(tok: list[str], what: str, lineno: int) -> list[float]:
    try:
        v = [float(t) for t in tok]
    except ValueError:
        raise InvalidInputError(f"line {lineno}: {what} holds a non-number: {tok}") from None
    if not np.all(np.isfinite(v)):
        raise InvalidInputError(f"line {lineno}: {what} holds NaN/inf: {tok}")
    return v


def _scan(
    ranges: list[float], stamp: float, fov: float, no_return: float, lineno: int
) -> LaserScan:
    n = len(ranges)
    r = np.asarray(ranges, float)
    if np.any(r < 0):
        raise InvalidInputError(f"line {lineno}: negative range in FLASER")
    r[r >= no_return] = np.inf
    inc = fov / (n - 1) if n % 2 == 1 and n > 1 else fov / n
    return LaserScan(
        angle_min=-fov / 2,
        angle_max=-fov / 2 + inc * (n - 1),
        angle_increment=inc,
        time_increment=0.0,
        scan_time=0.0,
        range_min=0.0,
        range_max=float(no_return),
        ranges=r,
        intensities=np.zeros(n),
        stamp=stamp,
        frame_id="laser",
    )


def parse_carmen(lines: Iterable[str], fov: float = np.pi, no_return: float = 80.0) -> CarmenLog:
    """Parse the ``FLASER`` and ``ODOM`` lines of a CARMEN log (see the module docstring).

    ``fov`` rad the angle the ``n`` beams span (beam spacing ``fov / n``); ``no_return`` m:
    readings at or above it become ``inf``. Raises :class:`InvalidInputError` on a malformed
    ``FLASER``/``ODOM`` line (with its line number) or a log without scans."""
    if not (np.isfinite(fov) and 0 < fov <= 2 * np.pi):
        raise InvalidInputError(f"fov must be in (0, 2 pi], got {fov}")
    scans: list[LaserScan] = []
    poses: list[Array] = []
    stamps: list[float] = []
    incs: list[Array] = []
    restart: Array | None = None  # first ODOM after the last scan
    last: Array | None = None  # last ODOM seen
    for lineno, line in enumerate(lines, 1):
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "ODOM":
            if len(tok) < 4:
                raise InvalidInputError(f"line {lineno}: ODOM needs x y theta, got {line!r}")
            last = np.array(_floats(tok[1:4], "ODOM", lineno))
            if restart is None and scans:
                restart = last
        elif tok[0] == "FLASER":
            try:
                n = int(tok[1])
            except (IndexError, ValueError):
                raise InvalidInputError(f"line {lineno}: FLASER without a beam count") from None
            if n < 1 or len(tok) < 2 + n + 7:
                raise InvalidInputError(
                    f"line {lineno}: FLASER with {n} beams needs {2 + n + 7} fields, has {len(tok)}"
                )
            r = _floats(tok[2 : 2 + n], "FLASER ranges", lineno)
            pose = np.array(_floats(tok[2 + n : 5 + n], "FLASER pose", lineno))
            stamp = _floats(tok[8 + n : 9 + n], "FLASER timestamp", lineno)[0]
            if scans:
                inc = (
                    relative_pose(restart, last)
                    if restart is not None and last is not None
                    else relative_pose(poses[-1], pose)  # no odometry: the pose change
                )
            else:
                inc = np.zeros(3)
            scans.append(_scan(r, stamp, fov, no_return, lineno))
            poses.append(pose)
            stamps.append(stamp)
            incs.append(inc)
            restart = None
    if not scans:
        raise InvalidInputError("the log holds no FLASER scan")
    P = np.array(poses)
    odo = [P[0]]
    for d in incs[1:]:
        odo.append(_compose(odo[-1], d))
    return CarmenLog(tuple(scans), P, np.array(incs), np.array(odo), np.array(stamps))


def read_carmen(path: str | Path, fov: float = np.pi, no_return: float = 80.0) -> CarmenLog:
    """:func:`parse_carmen` on the file ``path`` (gzip-compressed if it ends in ``.gz``)."""
    p = Path(path)
    opener = gzip.open if p.suffix == ".gz" else open
    with opener(p, "rt", encoding="ascii", errors="replace") as f:
        return parse_carmen(f, fov, no_return)
