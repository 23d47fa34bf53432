"""Synthetic RGB-D hard cases for the registration's acceptance checks (issue 34 item 4).

A scene is a set of coloured boxes (walls, a table, objects) ray-cast by Open3D's
``RaycastingScene`` from a pinhole camera, so every pair of views has an exact relative pose:
the failures of real frames (a repeated structure, a planar scene with little texture, a
corridor that slides along one axis) can be built on purpose and the acceptance checks judged
against the truth.

Frames: the world is z up (m); a camera pose ``T_world_camera`` maps the camera optical frame
(x right, y down, z forward) to the world. :func:`look_at` builds one from an eye and a target
point. :func:`render` returns the camera-frame :class:`~mmpa.robot.interfaces.PointCloud` of
the visible surfaces (depth ``z`` in ``[0.2, max_depth]`` m) with Gaussian depth noise
``sigma_z = depth_noise_k z^2`` along the ray and colours from each box's ``texture``; the
truth of a pair is ``T_target_source = inv(T_world_target) T_world_source``.

Textures (a box's colour at a world point ``p``): ``"flat"`` its base colour; ``"stripes"``
base colour times ``0.6 + 0.4 (sin(2 pi p . a / period) > 0)`` along the box's ``axis`` ``a``;
``"noise"`` base colour times a smooth random field (sum of 12 seeded plane waves, 4-20 cm
wavelengths) in ``[0.55, 1]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from mmpa.core.geometry import Array
from mmpa.robot.interfaces import PointCloud

__all__ = ["Box", "Scene", "look_at", "render", "scene_cases"]


@dataclass(frozen=True)
class Box:
    """An axis-aligned box from corner ``lo`` to corner ``hi`` (world, m), coloured ``rgb``
    (in [0, 1]) with ``texture`` ("flat", "stripes", "noise"), ``period`` (m) and ``axis``
    (world unit vector) of the stripes, ``seed`` of the noise."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    rgb: tuple[float, float, float]
    texture: str = "flat"
    period: float = 0.05
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    seed: int = 0


@dataclass(frozen=True)
class Scene:
    """Boxes and named camera poses (``T_world_camera``, 4x4) of one hard case."""

    name: str
    boxes: tuple[Box, ...]
    views: dict[str, Array] = field(default_factory=dict)


def look_at(eye: Array, target: Array, up: Array = (0.0, 0.0, 1.0)) -> Array:
    """``T_world_camera`` of an optical-frame camera at ``eye`` whose z axis points at
    ``target`` and whose y axis (image down) points away from ``up``."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye
    return T


def _box_mesh(b: Box) -> o3d.t.geometry.TriangleMesh:
    lo, hi = np.asarray(b.lo, float), np.asarray(b.hi, float)
    m = o3d.geometry.TriangleMesh.create_box(*(hi - lo))
    m.translate(lo)
    return o3d.t.geometry.TriangleMesh.from_legacy(m)


def _noise(p: Array, seed: int) -> Array:
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(12, 3))
    k *= (2 * np.pi / rng.uniform(0.04, 0.2, 12) / np.linalg.norm(k, axis=1))[:, None]
    v = np.sin(p @ k.T + rng.uniform(0, 2 * np.pi, 12)).sum(axis=1) / np.sqrt(6.0)
    return 0.775 + 0.225 * np.tanh(v)


def _shade(b: Box, p: Array) -> Array:
    base = np.asarray(b.rgb, float)[None, :]
    if b.texture == "flat":
        return np.repeat(base, len(p), axis=0)
    if b.texture == "stripes":
        on = np.sin(2 * np.pi * (p @ np.asarray(b.axis, float)) / b.period) > 0
        return base * (0.6 + 0.4 * on)[:, None]
    if b.texture == "noise":
        return base * _noise(p, b.seed)[:, None]
    raise ValueError(f"unknown texture {b.texture!r}")


def render(
    scene: Scene,
    T_world_camera: Array,
    *,
    width: int = 320,
    height: int = 240,
    fx: float = 300.0,
    max_depth: float = 3.0,
    depth_noise_k: float = 0.002,
    seed: int = 0,
) -> PointCloud:
    """The camera-frame cloud of ``scene`` seen from ``T_world_camera`` (module docstring):
    one point per pixel hit within ``[0.2, max_depth]`` m, depth noise along the ray."""
    rs = o3d.t.geometry.RaycastingScene()
    for b in scene.boxes:
        rs.add_triangles(_box_mesh(b))
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d_cam = np.stack([(u - width / 2) / fx, (v - height / 2) / fx, np.ones_like(u)], -1)
    d_cam = d_cam.reshape(-1, 3)
    R, t = T_world_camera[:3, :3], T_world_camera[:3, 3]
    rays = np.hstack([np.repeat(t[None], len(d_cam), 0), d_cam @ R.T]).astype(np.float32)
    hit = rs.cast_rays(o3d.core.Tensor(rays))
    s = hit["t_hit"].numpy().astype(float)  # ray parameter: the depth z (d_cam has z = 1)
    gid = hit["geometry_ids"].numpy()
    keep = np.isfinite(s) & (s > 0.2) & (s < max_depth)
    s, gid, d_cam = s[keep], gid[keep], d_cam[keep]
    p_world = t + (d_cam * s[:, None]) @ R.T
    colors = np.empty_like(p_world)
    for i, b in enumerate(scene.boxes):
        m = gid == i
        colors[m] = _shade(b, p_world[m])
    rng = np.random.default_rng(seed)
    z = s + rng.normal(size=len(s)) * depth_noise_k * s * s
    return PointCloud(d_cam * z[:, None], np.clip(colors, 0.0, 1.0))


_WALL, _TABLE, _RED = (0.9, 0.9, 0.88), (0.6, 0.6, 0.6), (0.8, 0.2, 0.2)


def _row(period: float, jitter: float) -> tuple[Box, ...]:
    """A table against a wall and 12 like red boxes (6 x 15 x 15 cm) along the wall every
    ``period`` m, each moved along the row by a seeded uniform draw in ``+-jitter`` m."""
    boxes = [
        Box((-1.5, -0.5, -0.05), (1.5, 1.0, 0.0), _TABLE),
        Box((-1.5, 1.0, 0.0), (1.5, 1.05, 1.0), _WALL),
    ]
    dx = np.random.default_rng(7).uniform(-jitter, jitter, 12)
    for i in range(12):
        x = -0.6 + i * period + dx[i]
        boxes.append(Box((x, 0.8, 0.0), (x + 0.06, 0.95, 0.15), _RED))
    return tuple(boxes)


def _corridor(texture: str) -> tuple[Box, ...]:
    """A floor between two parallel walls 1.2 m apart, 7 m long (x), no end in sight."""
    return (
        Box((-3, -0.6, -0.05), (4, 0.6, 0), _TABLE, texture, seed=1),
        Box((-3, -0.65, 0), (4, -0.6, 1), _WALL, texture, seed=2),
        Box((-3, 0.6, 0), (4, 0.65, 1), _WALL, texture, seed=3),
    )


def _desk() -> tuple[Box, ...]:
    """A table with a smooth random texture and two flat objects (2-3 cm high)."""
    return (
        Box((-1, -1, -0.05), (1, 1, 0), _TABLE, "noise", seed=1),
        Box((0.05, 0.1, 0), (0.25, 0.25, 0.02), _RED),
        Box((-0.2, -0.15, 0), (-0.05, 0.05, 0.03), (0.2, 0.3, 0.7)),
    )


def scene_cases() -> dict[str, tuple[Scene, str]]:
    """The hard cases, each a :class:`Scene` with views ``"source"`` and ``"target"`` and
    what a registration of the pair must do, ``"refuse"`` or ``"accept"`` (within a few mm):

    - ``repeated``: 12 like red boxes every 10 cm; the camera moves 5 cm along the row (FGR's
      matches vote for the copies; the pose one period off fits as well): refuse;
    - ``irregular``: the same row, each box moved by up to 3 cm (no period), the camera
      5 cm: accept;
    - ``corridor``: a corridor without texture; the camera 3 cm along it (only the edges of
      the view and the depth crop say where it is): refuse;
    - ``desk``: a textured table with two flat objects, the camera 6 cm sideways: accept.
    """
    row_src = look_at((0.0, -0.3, 0.6), (0.0, 0.8, 0.05))
    cases = {
        "repeated": (
            _row(0.1, 0.0),
            row_src,
            look_at((0.05, -0.3, 0.6), (0.05, 0.8, 0.05)),
            "refuse",
        ),
        "irregular": (
            _row(0.1, 0.03),
            row_src,
            look_at((0.05, -0.3, 0.6), (0.05, 0.8, 0.05)),
            "accept",
        ),
        "corridor": (
            _corridor("flat"),
            look_at((0.0, 0.0, 0.5), (2.0, 0.0, 0.3)),
            look_at((0.03, 0.01, 0.5), (2.03, 0.0, 0.3)),
            "refuse",
        ),
        "desk": (
            _desk(),
            look_at((0.0, -0.3, 0.6), (0.0, 0.0, 0.0)),
            look_at((0.06, -0.3, 0.6), (0.06, 0.0, 0.0)),
            "accept",
        ),
    }
    return {
        k: (Scene(k, boxes, {"source": a, "target": b}), expect)
        for k, (boxes, a, b, expect) in cases.items()
    }
