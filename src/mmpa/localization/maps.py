"""Occupancy grids: ROS ``map_server`` I/O, rasterization of boxes and discs, distance field.

A :class:`OccupancyGrid` stores ``data`` as ROS ``nav_msgs/OccupancyGrid`` does: row 0 is the
BOTTOM of the map (smallest y), values -1 (unknown), 0 (free) .. 100 (occupied). The PGM image
that ``map_server`` reads has row 0 at the TOP, so rows are flipped on read and on write.

Map YAML fields (``map_server``): ``image``, ``resolution`` (m/cell), ``origin``
``[x, y, yaw]`` (pose of the lower-left cell's corner in ``map``), ``negate``,
``occupied_thresh``, ``free_thresh``, ``mode`` (trinary | scale | raw, default trinary).
Extra keys are ignored by ``map_server``; mmpa stores the surveyed reflector landmarks under
``reflectors`` (``positions`` (N, 2) m in ``map``, ``radius`` m).

This module never imports the simulator; the twin's map is rasterized from boxes and discs that
the mission layer extracts from the scene.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from scipy import ndimage

from mmpa.errors import ConfigError, InvalidInputError
from mmpa.geometry import Array

__all__ = [
    "Box2D",
    "OccupancyGrid",
    "load_map",
    "rasterize",
    "read_pgm",
    "save_map",
    "write_pgm",
]

_REQUIRED = ("image", "resolution", "origin", "occupied_thresh", "free_thresh", "negate")


@dataclass(frozen=True)
class Box2D:
    """An obstacle footprint: rectangle (``size`` = (lx, ly)) or disc (``radius``) at
    ``center`` (m, map) with heading ``yaw`` (rad)."""

    center: tuple[float, float]
    size: tuple[float, float] = (0.0, 0.0)
    yaw: float = 0.0
    radius: float = 0.0


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
        self.data = np.asarray(self.data, dtype=np.int8)
        if self.data.ndim != 2 or self.data.size == 0:
            raise InvalidInputError(f"map data must be a non-empty 2D array, got {self.data.shape}")
        if not (np.isfinite(self.resolution) and self.resolution > 0):
            raise InvalidInputError(f"map resolution must be positive, got {self.resolution}")
        if abs(self.origin[2]) > 1e-9:
            raise InvalidInputError("rotated map origins (yaw != 0) are not supported")
        self.reflectors = np.asarray(self.reflectors, dtype=float).reshape(-1, 2)

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


# --- PGM -----------------------------------------------------------------------------------


def _pgm_tokens(buf: bytes, count: int) -> tuple[list[int], int]:
    """Read ``count`` whitespace-separated header integers (skipping # comments)."""
    out: list[int] = []
    i = 2
    while len(out) < count:
        while i < len(buf) and buf[i : i + 1].isspace():
            i += 1
        if i < len(buf) and buf[i : i + 1] == b"#":
            while i < len(buf) and buf[i : i + 1] not in (b"\n", b"\r"):
                i += 1
            continue
        j = i
        while j < len(buf) and not buf[j : j + 1].isspace():
            j += 1
        if j == i:
            raise ConfigError("PGM header truncated")
        out.append(int(buf[i:j]))
        i = j
    return out, i + 1  # one whitespace byte after maxval


def read_pgm(path: str | Path) -> np.ndarray:
    """Read a binary (P5) or ASCII (P2) PGM; returns (H, W) uint8/uint16 with row 0 at the top."""
    path = Path(path)
    try:
        buf = path.read_bytes()
    except OSError as e:
        raise ConfigError(f"cannot read map image {path}: {e.strerror}") from None
    magic = buf[:2]
    if magic not in (b"P5", b"P2"):
        raise ConfigError(f"{path}: not a PGM image (magic {magic!r}; expected P5 or P2)")
    try:
        (w, h, maxval), start = _pgm_tokens(buf, 3)
        if magic == b"P5":
            dt = np.dtype(">u2") if maxval > 255 else np.uint8
            img = np.frombuffer(buf, dtype=dt, count=w * h, offset=start).reshape(h, w)
        else:
            vals = np.array(buf[start:].split()[: w * h], dtype=np.int64)
            img = vals.reshape(h, w)
    except (ValueError, IndexError) as e:
        raise ConfigError(f"{path}: malformed PGM image ({e})") from None
    return np.asarray(img).astype(np.uint16 if maxval > 255 else np.uint8)


def write_pgm(path: str | Path, img: np.ndarray) -> None:
    """Write (H, W) uint8 as binary P5 (row 0 at the top)."""
    img = np.asarray(img, dtype=np.uint8)
    h, w = img.shape
    Path(path).write_bytes(f"P5\n{w} {h}\n255\n".encode() + img.tobytes())


# --- map_server YAML -------------------------------------------------------------------------


def load_map(yaml_path: str | Path) -> OccupancyGrid:
    """Load a ``map_server`` map (as written by Gmapping / Cartographer / nav2 map_saver).

    Conversion (map_server ``loadMapFromFile``): ``p = (255 - v) / 255`` (or ``v / 255`` when
    ``negate``); trinary: ``p > occupied_thresh`` -> 100, ``p < free_thresh`` -> 0, else -1;
    scale: linear in between; raw: the pixel value. Only the first channel of the image is
    used (PGM is single channel; other formats are not supported without an image library).
    """
    yaml_path = Path(yaml_path)
    try:
        meta = yaml.safe_load(yaml_path.read_text())
    except OSError as e:
        raise ConfigError(f"cannot read map YAML {yaml_path}: {e.strerror}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{yaml_path}: not valid YAML: {e}") from None
    if not isinstance(meta, dict):
        raise ConfigError(f"{yaml_path}: a map YAML must be a mapping")
    missing = [k for k in _REQUIRED if k not in meta]
    if missing:
        raise ConfigError(f"{yaml_path}: map YAML lacks required field(s) {', '.join(missing)}")
    try:
        res = float(meta["resolution"])
        origin = tuple(float(v) for v in meta["origin"])
        occ_t, free_t = float(meta["occupied_thresh"]), float(meta["free_thresh"])
        negate = bool(int(meta["negate"]))
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{yaml_path}: malformed map field ({e})") from None
    if len(origin) != 3:
        raise ConfigError(f"{yaml_path}: origin must be [x, y, yaw], got {meta['origin']}")
    mode = str(meta.get("mode", "trinary"))
    if mode not in ("trinary", "scale", "raw"):
        raise ConfigError(f"{yaml_path}: mode must be trinary, scale or raw, got {mode!r}")
    img_path = Path(str(meta["image"]))
    if not img_path.is_absolute():
        img_path = yaml_path.parent / img_path
    img = read_pgm(img_path).astype(float)
    maxval = 65535.0 if img.max() > 255 else 255.0
    if mode == "raw":
        data = np.clip(img, -1, 100)
    else:
        p = img / maxval if negate else (maxval - img) / maxval
        data = np.full(img.shape, -1.0)
        data[p > occ_t] = 100
        data[p < free_t] = 0
        if mode == "scale":
            mid = (p >= free_t) & (p <= occ_t)
            data[mid] = np.round(99 * (p[mid] - free_t) / (occ_t - free_t))
    data = np.flipud(data).astype(np.int8)  # image row 0 is the top; ROS row 0 is the bottom
    refl = np.zeros((0, 2))
    radius = 0.0
    extra = meta.get("reflectors")
    if isinstance(extra, dict):
        refl = np.asarray(extra.get("positions", []), float).reshape(-1, 2)
        radius = float(extra.get("radius", 0.0))
    return OccupancyGrid(data, res, origin, refl, radius, occ_t, free_t)  # type: ignore[arg-type]


def save_map(grid: OccupancyGrid, yaml_path: str | Path) -> Path:
    """Write ``<name>.yaml`` + ``<name>.pgm`` as nav2 ``map_saver`` does (trinary: occupied 0,
    free 254, unknown 205), with the reflector landmarks under the extra key ``reflectors``."""
    yaml_path = Path(yaml_path)
    yaml_path.parent.mkdir(parents=True, exist_ok=True)
    pgm = yaml_path.with_suffix(".pgm")
    img = np.full(grid.data.shape, 205, dtype=np.uint8)
    img[grid.data >= 65] = 0
    img[(grid.data >= 0) & (grid.data < 20)] = 254
    write_pgm(pgm, np.flipud(img))
    meta = {
        "image": pgm.name,
        "mode": "trinary",
        "resolution": float(grid.resolution),
        "origin": [float(v) for v in grid.origin],
        "negate": 0,
        "occupied_thresh": float(grid.occupied_thresh),
        "free_thresh": float(grid.free_thresh),
        "reflectors": {
            "radius": float(grid.reflector_radius),
            "positions": [[float(x), float(y)] for x, y in grid.reflectors],
        },
    }
    yaml_path.write_text(yaml.safe_dump(meta, sort_keys=False))
    return yaml_path
