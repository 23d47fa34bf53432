"""Occupancy grids: the grid, rasterization of boxes and discs, distance field (the
``map_server`` file format is :mod:`mmpa.maps.map_server`).

A :class:`OccupancyGrid` stores ``data`` as ROS ``nav_msgs/OccupancyGrid`` does: row 0 is the
BOTTOM of the map (smallest y), values -1 (unknown), 0 (free) .. 100 (occupied). The PGM image
that ``map_server`` reads has row 0 at the TOP, so rows are flipped on read and on write.

Map YAML fields (``map_server``): ``image``, ``resolution`` (m/cell), ``origin``
``[x, y, yaw]`` (pose of the lower-left cell's corner in ``map``), ``negate``,
``occupied_thresh``, ``free_thresh``, ``mode`` (trinary | scale | raw, default trinary).
The occupancy values of an image are those of Nav2's ``map_io.cpp`` (``loadMapFromFile`` /
``tryWriteMapToFile``): see :func:`occupancy_from_image` and :func:`image_from_occupancy`.
Extra keys are ignored by ``map_server``; mmpa stores the surveyed reflector landmarks under
``reflectors``: a list of reflector map entries ``{id, x, y, radius}``, the name of a
reflector map file (:mod:`mmpa.maps.reflector_map`), or the earlier form
``{positions: [[x, y], ...], radius}``.

This module never imports the simulator; the twin's map is rasterized from boxes and discs that
the mission layer extracts from the scene.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array

__all__ = [
    "Box2D",
    "OccupancyGrid",
    "rasterize",
]


@dataclass(frozen=True)
class Box2D:
    """An obstacle footprint: rectangle (``size`` = (lx, ly)) or disc (``radius``) at
    ``center`` (m, map) with heading ``yaw`` (rad)."""

    center: tuple[float, float]
    size: tuple[float, float] = (0.0, 0.0)
    yaw: float = 0.0
    radius: float = 0.0


def _cells(data: object) -> np.ndarray:
    """``data`` as int8 cells after checking it: a non-empty 2D array of integers in
    ``{-1, 0..100}`` (a cast alone would wrap 200 to -56, or truncate 50.7 to 50)."""
    try:
        a = np.asarray(data)
    except (TypeError, ValueError) as e:
        raise InvalidInputError(f"map data must be a 2D array of cells, got {e}") from None
    if a.ndim != 2 or a.size == 0:
        raise InvalidInputError(f"map data must be a non-empty 2D array, got {a.shape}")
    if a.dtype.kind in "iub":
        bad = (a < -1) | (a > 100)
    elif a.dtype.kind == "f":
        bad = ~np.isfinite(a) | (a < -1) | (a > 100) | (a != np.round(a))
    else:
        raise InvalidInputError(f"map data must hold integers -1..100, got dtype {a.dtype}")
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise InvalidInputError(
            "map cell values must be -1 (unknown) or 0..100 (occupancy %), got "
            f"{a[r, c].item()!r} at row {r}, column {c} ({int(bad.sum())} bad cell(s))"
        )
    return a.astype(np.int8)


@dataclass
class OccupancyGrid:
    """A 2D occupancy grid in ROS layout (row 0 = bottom).

    ``data`` (H, W) int8 in {-1, 0..100}; ``resolution`` m/cell; ``origin`` (x, y, yaw) of the
    lower-left corner of cell (0, 0). ``reflectors`` (N, 2) surveyed landmarks (may be empty),
    ``reflector_radius`` m.
    """

    data: np.ndarray
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    reflectors: Array = field(default_factory=lambda: np.zeros((0, 2)))
    reflector_radius: float = 0.0
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196

    def __post_init__(self) -> None:
        self.data = _cells(self.data)
        if not (np.isfinite(self.resolution) and self.resolution > 0):
            raise InvalidInputError(f"map resolution must be positive, got {self.resolution}")
        if len(self.origin) != 3 or not np.isfinite(np.asarray(self.origin, float)).all():
            raise InvalidInputError(f"map origin must be 3 finite numbers, got {self.origin}")
        if abs(self.origin[2]) > 1e-9:
            raise InvalidInputError("rotated map origins (yaw != 0) are not supported")
        refl = np.asarray(self.reflectors, dtype=float)
        if refl.size == 0:
            refl = np.zeros((0, 2))
        if refl.ndim != 2 or refl.shape[1] != 2 or not np.isfinite(refl).all():
            raise InvalidInputError(
                f"map reflectors must be a finite (N, 2) array, got shape {refl.shape}"
            )
        self.reflectors = refl
        if not (np.isfinite(self.reflector_radius) and self.reflector_radius >= 0):
            raise InvalidInputError(
                f"reflector radius must be finite and >= 0 m, got {self.reflector_radius}"
            )
        if not 0.0 <= self.free_thresh < self.occupied_thresh <= 1.0:
            raise InvalidInputError(
                "map thresholds must satisfy 0 <= free_thresh < occupied_thresh <= 1, got "
                f"{self.free_thresh}, {self.occupied_thresh}"
            )

    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    @property
    def occupied(self) -> np.ndarray:
        """(H, W) bool: cells at or above 65 % occupancy (ROS: 100)."""
        return self.data >= 65

    @property
    def free(self) -> np.ndarray:
        return (self.data >= 0) & (self.data < 20)

    def world_to_cell(self, xy: Array) -> tuple[np.ndarray, np.ndarray]:
        """(..., 2) map points -> (col, row) integer cell indices (may fall outside)."""
        xy = np.asarray(xy, float)
        c = np.floor((xy[..., 0] - self.origin[0]) / self.resolution).astype(np.int64)
        r = np.floor((xy[..., 1] - self.origin[1]) / self.resolution).astype(np.int64)
        return c, r

    def cell_to_world(self, col: Array, row: Array) -> Array:
        """Cell centers (m) of integer indices, shape (..., 2)."""
        x = self.origin[0] + (np.asarray(col) + 0.5) * self.resolution
        y = self.origin[1] + (np.asarray(row) + 0.5) * self.resolution
        return np.stack([x, y], axis=-1)

    def inside(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        return (col >= 0) & (col < self.width) & (row >= 0) & (row < self.height)

    def distance_field(self, max_dist: float = 2.0) -> Array:
        """(H, W) Euclidean distance (m) from each cell center to the nearest occupied cell
        center, clipped at ``max_dist`` (Nav2's ``laser_likelihood_max_dist``)."""
        occ = self.occupied
        if not occ.any():
            return np.full(self.data.shape, max_dist)
        d = ndimage.distance_transform_edt(~occ) * self.resolution
        return np.minimum(d, max_dist)

    def signed_distance_field(self, max_dist: float = 2.0, offset: float = 0.5) -> Array:
        """(H, W) signed distance (m) from each cell center to the nearest obstacle SURFACE,
        positive outside, negative inside, clipped to ``[-max_dist, max_dist]``.

        The surface is put ``offset`` cells (of ``resolution`` ``s``) out from the centers of
        the occupied cells on the boundary (0.5: the cell edge, where a surface lies on average
        when cells are occupied by their center): ``phi = d_out - offset s`` in unoccupied
        cells (``d_out``: EDT to the nearest occupied center, :meth:`distance_field`) and
        ``phi = -(d_in - (1 - offset) s)`` in occupied ones (``d_in``: EDT to the nearest
        unoccupied center). Across a boundary the field then falls by ``s`` per cell, so its
        bilinear interpolation is the signed distance to a straight surface, and a point behind
        the surface is as far from it as one in front (the unsigned field is 0 everywhere
        inside an obstacle)."""
        occ = self.occupied
        if not occ.any():
            return np.full(self.data.shape, max_dist)
        s = self.resolution
        d_out = ndimage.distance_transform_edt(~occ) * s
        phi = d_out - offset * s
        if (~occ).any():
            d_in = ndimage.distance_transform_edt(occ) * s
            phi = np.where(occ, -(d_in - (1.0 - offset) * s), phi)
        return np.clip(phi, -max_dist, max_dist)

    def nbytes(self) -> int:
        return int(self.data.nbytes)


def rasterize(
    boxes: list[Box2D],
    bounds: tuple[float, float, float, float],
    resolution: float = 0.05,
    reflectors: Array | None = None,
    reflector_radius: float = 0.0,
    warp: Callable[[Array], Array] | None = None,
) -> OccupancyGrid:
    """Occupancy grid of ``bounds`` = (xmin, ymin, xmax, ymax) with every cell whose center lies
    in a box (or disc) occupied (100) and all others free (0). Thin obstacles (narrower than a
    cell) still mark the cell holding their center line.

    ``warp``: a smooth displacement field ``u(p)`` ((..., 2) m -> (..., 2) m; with an
    ``on_grid(xs, ys)`` method giving (H, W, 2) on the cell centers, that is used) by which
    the map is distorted: a world point ``q`` appears in the map at ``q + u(q)``, so the cell
    centered at ``p`` shows the world at ``p - u(p)`` (the inverse to first order in the
    field's gradient, ~sigma / length: 0.3 % for a 10 mm / 3 m field). The reflector
    landmarks are not moved (they carry their own survey error)."""
    xmin, ymin, xmax, ymax = bounds
    if not (xmax > xmin and ymax > ymin):
        raise InvalidInputError(f"map bounds must have xmax > xmin and ymax > ymin, got {bounds}")
    if resolution <= 0:
        raise InvalidInputError(f"resolution must be positive, got {resolution}")
    w = int(np.ceil((xmax - xmin) / resolution))
    h = int(np.ceil((ymax - ymin) / resolution))
    xs = xmin + (np.arange(w) + 0.5) * resolution
    ys = ymin + (np.arange(h) + 0.5) * resolution
    X, Y = np.meshgrid(xs, ys)
    if warp is not None:
        on_grid = getattr(warp, "on_grid", None)  # a faster tensor-grid evaluation, if any
        u = np.asarray(on_grid(xs, ys) if on_grid else warp(np.stack([X, Y], axis=-1)), float)
        X, Y = X - u[..., 0], Y - u[..., 1]
    occ = np.zeros((h, w), dtype=bool)
    half = resolution / 2
    for b in boxes:
        dx, dy = X - b.center[0], Y - b.center[1]
        if b.radius > 0:
            occ |= dx * dx + dy * dy <= max(b.radius, half) ** 2
            continue
        c, s = np.cos(b.yaw), np.sin(b.yaw)
        u = c * dx + s * dy
        v = -s * dx + c * dy
        occ |= (np.abs(u) <= max(b.size[0] / 2, half)) & (np.abs(v) <= max(b.size[1] / 2, half))
    data = np.where(occ, 100, 0).astype(np.int8)
    refl = np.zeros((0, 2)) if reflectors is None else np.asarray(reflectors, float)
    return OccupancyGrid(data, resolution, (xmin, ymin, 0.0), refl, reflector_radius)


# --- images ----------------------------------------------------------------------------------
