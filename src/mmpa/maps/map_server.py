"""ROS ``map_server`` maps: the map YAML + PGM/PNG image, read and written as Nav2 does.

The PGM image that ``map_server`` reads has row 0 at the TOP, so rows are flipped on read and
on write (an :class:`~mmpa.maps.occupancy.OccupancyGrid` has row 0 at the bottom).

Map YAML fields (``map_server``): ``image``, ``resolution`` (m/cell), ``origin``
``[x, y, yaw]`` (pose of the lower-left cell's corner in ``map``), ``negate``,
``occupied_thresh``, ``free_thresh``, ``mode`` (trinary | scale | raw, default trinary).
The occupancy values of an image are those of Nav2's ``map_io.cpp`` (``loadMapFromFile`` /
``tryWriteMapToFile``): see :func:`occupancy_from_image` and :func:`image_from_occupancy`.
Extra keys are ignored by ``map_server``; mmpa stores the surveyed reflector landmarks under
``reflectors``: a list of reflector map entries ``{id, x, y, radius}``, the name of a
reflector map file (:mod:`mmpa.maps.reflector_map`), or the earlier form
``{positions: [[x, y], ...], radius}``.
"""

from __future__ import annotations

import dataclasses
import math
from numbers import Integral, Real
from pathlib import Path
from typing import Literal

import numpy as np
import yaml
from PIL import Image
from scipy.spatial import cKDTree

from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.core.geometry import Array
from mmpa.core.yamlio import finite_number, load_yaml
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.maps.reflector_map import (
    MIN_SEPARATION,
    ReflectorMap,
    load_reflector_map,
    parse_reflector_entries,
)

__all__ = [
    "QUANTUM_MAX",
    "MapMode",
    "image_from_occupancy",
    "load_map",
    "occupancy_from_image",
    "read_map_image",
    "read_pgm",
    "read_pgm_maxval",
    "replace_reflectors",
    "save_map",
    "write_pgm",
]

_REQUIRED = ("image", "resolution", "origin", "occupied_thresh", "free_thresh", "negate")


def _pgm_header(buf: bytes, path: Path) -> tuple[int, int, int, int]:
    """(width, height, maxval, offset of the pixel data) of a P2/P5 header (# comments
    skipped); every field is checked (ConfigError naming ``path`` and the field)."""
    out: list[int] = []
    i = 2
    names = ("width", "height", "maxval")
    while len(out) < 3:
        while i < len(buf) and buf[i : i + 1].isspace():
            i += 1
        if i < len(buf) and buf[i : i + 1] == b"#":
            while i < len(buf) and buf[i : i + 1] not in (b"\n", b"\r"):
                i += 1
            continue
        j = i
        while j < len(buf) and not buf[j : j + 1].isspace():
            j += 1
        tok = buf[i:j]
        name = names[len(out)]
        if not tok:
            raise ConfigError(f"{path}: PGM header truncated before {name}")
        if not tok.isdigit():
            raise ConfigError(f"{path}: PGM {name} must be a positive integer, got {tok!r}")
        out.append(int(tok))
        i = j
    w, h, maxval = out
    if w < 1 or h < 1:
        raise ConfigError(f"{path}: PGM image is {w} x {h}; width and height must be >= 1")
    if not 1 <= maxval <= 65535:
        raise ConfigError(f"{path}: PGM maxval must be in 1..65535, got {maxval}")
    return w, h, maxval, i + 1  # one whitespace byte after maxval


def read_pgm_maxval(path: str | Path) -> tuple[np.ndarray, int]:
    """Read a binary (P5) or ASCII (P2) PGM: ((H, W) uint8/uint16 pixel values with row 0 at
    the top, the header's maxval). Values above maxval are refused."""
    path = Path(path)
    try:
        buf = path.read_bytes()
    except OSError as e:
        raise ConfigError(f"cannot read map image {path}: {e.strerror}") from None
    magic = buf[:2]
    if magic not in (b"P5", b"P2"):
        raise ConfigError(f"{path}: not a PGM image (magic {magic!r}; expected P5 or P2)")
    w, h, maxval, start = _pgm_header(buf, path)
    dt = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)
    if magic == b"P5":
        need = w * h * dt.itemsize
        if len(buf) - start < need:
            raise ConfigError(
                f"{path}: PGM pixel data truncated: {max(len(buf) - start, 0)} bytes for a "
                f"{w} x {h} image with maxval {maxval} (need {need})"
            )
        img = np.frombuffer(buf, dtype=dt, count=w * h, offset=start).reshape(h, w)
    else:
        toks = buf[start:].split()
        if len(toks) < w * h:
            raise ConfigError(f"{path}: PGM holds {len(toks)} pixel values, need {w} x {h}")
        try:
            img = np.array([int(t) for t in toks[: w * h]], dtype=np.int64).reshape(h, w)
        except ValueError as e:
            raise ConfigError(f"{path}: malformed PGM pixel value ({e})") from None
    if img.size and (int(img.max()) > maxval or int(img.min()) < 0):
        raise ConfigError(f"{path}: PGM pixel value {int(img.max())} exceeds maxval {maxval}")
    return np.asarray(img).astype(np.uint16 if maxval > 255 else np.uint8), maxval


def read_pgm(path: str | Path) -> np.ndarray:
    """Read a binary (P5) or ASCII (P2) PGM; returns (H, W) uint8/uint16 with row 0 at the top
    (raw values; see :func:`read_pgm_maxval` for the maxval they are scaled by)."""
    return read_pgm_maxval(path)[0]


def write_pgm(path: str | Path, img: np.ndarray) -> None:
    """Write (H, W) uint8 as binary P5 (row 0 at the top)."""
    img = np.asarray(img, dtype=np.uint8)
    h, w = img.shape
    Path(path).write_bytes(f"P5\n{w} {h}\n255\n".encode() + img.tobytes())


#: GraphicsMagick's quantum range in the Q16 build ROS / Nav2 links (MaxRGB)
QUANTUM_MAX = 65535


def _to_quanta(v: np.ndarray, maxval: int) -> np.ndarray:
    """Pixel values of depth ``maxval`` -> Q16 quanta as GraphicsMagick scales them
    (``MaxRGB * v / maxval``, rounded; exact ``v * 257`` for 8-bit values)."""
    if maxval == QUANTUM_MAX:
        return v.astype(float)
    if maxval == 255:
        return v.astype(float) * 257.0
    return np.floor(v.astype(float) * QUANTUM_MAX / maxval + 0.5)


def read_map_image(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """A map image's pixels as Nav2's map_server (GraphicsMagick, Q16) sees them.

    Returns ``(rgb_sum, alpha)``: ``rgb_sum`` (H, W) float, the sum of the R, G, B quanta
    (each 0 .. :data:`QUANTUM_MAX`, scaled from the file's depth: a PGM's header maxval, 8 or
    16 bits otherwise; a grey pixel has R = G = B); ``alpha`` (H, W) float quanta
    (``QUANTUM_MAX`` = opaque) when the image has an alpha channel (PNG RGBA / LA, a palette
    with transparency), else None. Row 0 is the top.

    PGM (P2/P5, any maxval 1..65535) is read exactly by :func:`read_pgm_maxval`; every other
    format Pillow reads (PNG, BMP, TIFF, PPM, ...) through Pillow.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            magic = f.read(2)
    except OSError as e:
        raise ConfigError(f"cannot read map image {path}: {e.strerror}") from None
    if magic in (b"P2", b"P5"):
        img, maxval = read_pgm_maxval(path)
        return 3.0 * _to_quanta(img, maxval), None

    try:
        with Image.open(path) as im:
            im.load()
            if im.mode == "P" or im.mode == "PA":
                im = im.convert("RGBA" if "transparency" in im.info or im.mode == "PA" else "RGB")
            elif im.mode == "1":
                im = im.convert("L")
            elif im.mode in ("La", "RGBa", "CMYK", "YCbCr", "LAB", "HSV"):
                im = im.convert("RGBA" if im.mode.endswith("a") else "RGB")
            mode = im.mode
            arr = np.asarray(im)
    except Image.DecompressionBombError as e:
        raise ConfigError(f"{path}: image refused as too large ({e})") from None
    except (OSError, ValueError, SyntaxError) as e:
        raise ConfigError(
            f"{path}: not a map image Pillow can read (PGM, PNG, BMP, ...): {e}"
        ) from None
    if mode in ("L", "LA", "RGB", "RGBA"):
        q = _to_quanta(arr, 255)
    elif mode.startswith("I;16") or mode == "I":
        if arr.size and (int(arr.min()) < 0 or int(arr.max()) > QUANTUM_MAX):
            raise ConfigError(f"{path}: {mode} image values outside 0..65535")
        q = _to_quanta(arr, QUANTUM_MAX)
    else:
        raise ConfigError(f"{path}: image mode {mode!r} is not supported (grey, RGB, RGBA)")
    if q.ndim < 2 or q.shape[0] < 1 or q.shape[1] < 1:
        raise ConfigError(f"{path}: the image is {q.shape[:2]}; it must have pixels")
    if q.ndim == 2:
        return 3.0 * q, None
    if mode == "LA":
        return 3.0 * q[..., 0], q[..., 1]
    return q[..., 0] + q[..., 1] + q[..., 2], (q[..., 3] if mode == "RGBA" else None)


MapMode = Literal["trinary", "scale", "raw"]


def occupancy_from_image(
    rgb_sum: np.ndarray,
    alpha: np.ndarray | None,
    mode: MapMode,
    negate: bool,
    occupied_thresh: float,
    free_thresh: float,
) -> np.ndarray:
    """(H, W) int8 occupancy (-1, 0..100) of an image, in IMAGE row order, as Nav2's
    ``loadMapFromFile`` computes it (``rgb_sum``/``alpha`` from :func:`read_map_image`):

    ``shade`` = the mean of the R, G, B quanta (and, in trinary mode only, of the alpha
    quantum when the image has one) / ``QUANTUM_MAX``; ``occ = shade`` if ``negate`` else
    ``1 - shade``.

    * trinary: ``occupied_thresh < occ`` -> 100, else ``occ < free_thresh`` -> 0, else -1.
    * scale: a pixel not fully opaque -> -1; else as trinary beyond the thresholds, and in
      between ``rint((occ - free) / (occupied - free) * 100)``.
    * raw: ``v = round(shade * 255)`` (half away from zero); ``v`` in 0..100 -> ``v``, any
      other value (e.g. 255) -> -1. ``negate`` and alpha do not apply.
    """
    if mode == "trinary" and alpha is not None:
        shade = ((rgb_sum + alpha) / 4.0) / QUANTUM_MAX
    else:
        shade = (rgb_sum / 3.0) / QUANTUM_MAX
    if mode == "raw":
        v = np.floor(shade * 255.0 + 0.5)
        return np.where((v >= 0) & (v <= 100), v, -1).astype(np.int8)
    occ = shade if negate else 1.0 - shade
    out = np.full(shade.shape, -1, dtype=np.int8)
    is_occ = occupied_thresh < occ
    is_free = ~is_occ & (occ < free_thresh)
    out[is_occ] = 100
    out[is_free] = 0
    if mode == "scale":
        mid = ~is_occ & ~is_free
        out[mid] = np.rint((occ[mid] - free_thresh) / (occupied_thresh - free_thresh) * 100.0)
        if alpha is not None:
            out[alpha < QUANTUM_MAX] = -1
    return out


# --- map_server YAML -------------------------------------------------------------------------


def _num(meta: dict, key: str, where: Path) -> float:
    return finite_number(meta[key], f"{where}: {key}")


def _map_reflectors(value: object, yaml_path: Path) -> tuple[Array, float]:
    """The ``reflectors`` key of a map YAML -> ((N, 2) positions, radius m; 0 = not given).

    Accepted: a path (relative to the YAML) to a reflector map file; a list of reflector map
    entries ``{id, x, y, radius}`` (one radius for all); the mapping ``{positions: [[x, y],
    ...], radius: r}`` (mmpa's earlier form; ``radius`` >= 0, 0 = not given)."""
    if value is None or value == []:
        return np.zeros((0, 2)), 0.0
    if isinstance(value, str):
        p = Path(value)
        rm = load_reflector_map(p if p.is_absolute() else yaml_path.parent / p)
        entries_of = str(p)
    elif isinstance(value, list):
        rm = parse_reflector_entries(value, str(yaml_path))
        entries_of = "reflectors"
    elif isinstance(value, dict):
        extra = sorted(str(k) for k in value if k not in ("positions", "radius"))
        if extra:
            raise ConfigError(
                f"{yaml_path}: reflectors: unknown key(s) {', '.join(extra)}; "
                "valid: positions, radius"
            )
        radius = 0.0
        if "radius" in value:
            radius = _num(value, "radius", yaml_path)
            if radius < 0:
                raise ConfigError(f"{yaml_path}: reflectors.radius: must be >= 0 m, got {radius}")
        pos = value.get("positions", [])
        if not isinstance(pos, list):
            raise ConfigError(
                f"{yaml_path}: reflectors.positions: must be a list of [x, y], "
                f"got {type(pos).__name__}"
            )
        xy = np.zeros((len(pos), 2))
        for i, p in enumerate(pos):
            where = f"{yaml_path}: reflectors.positions[{i}]"
            if not isinstance(p, list) or len(p) != 2:
                raise ConfigError(f"{where}: must be a pair [x, y], got {p!r}")
            for j, v in enumerate(p):
                if isinstance(v, bool) or not isinstance(v, Real) or not math.isfinite(float(v)):
                    raise ConfigError(f"{where}: must be two finite numbers, got {p!r}")
                xy[i, j] = float(v)
        if len(xy) > 1:
            pairs = cKDTree(xy).query_pairs(MIN_SEPARATION, output_type="ndarray")
            if len(pairs):
                a, b = sorted(pairs[0].tolist())
                raise ConfigError(
                    f"{yaml_path}: reflectors.positions[{b}]: at the position of entry {a}: "
                    "a duplicate reflector"
                )
        return xy, radius
    else:
        raise ConfigError(
            f"{yaml_path}: reflectors: must be a reflector map file name, a list of "
            f"{{id, x, y, radius}} entries or {{positions, radius}}, got {type(value).__name__}"
        )
    radii = np.unique(rm.radius)
    if len(radii) > 1:
        raise ConfigError(
            f"{yaml_path}: reflectors ({entries_of}): the localizers use one reflector radius; "
            f"the entries give {', '.join(f'{r:g}' for r in radii)} m"
        )
    return np.array(rm.xy), float(radii[0])


def load_map(yaml_path: str | Path) -> OccupancyGrid:
    """Load a ``map_server`` map (as written by Gmapping / Cartographer / nav2 map_saver).

    The YAML is read through :func:`mmpa.core.yamlio.load_yaml`; the image (``image``, relative to
    the YAML) may be any format :func:`read_map_image` reads; the occupancy values are those of
    Nav2's ``loadMapFromFile`` (:func:`occupancy_from_image`: trinary, scale, raw; ``negate``;
    the alpha channel; a PGM's maxval). Checked, each error a ConfigError naming the file and
    the field: ``resolution`` finite > 0; ``origin`` a list of 3 finite numbers with yaw 0 (a
    rotated origin is refused: the grid's cell arithmetic assumes an axis-aligned map);
    ``0 <= free_thresh < occupied_thresh <= 1``; ``negate`` an integer or boolean; ``mode``.
    Reflector landmarks (the extra key ``reflectors``): see :func:`_map_reflectors`.
    """
    yaml_path = Path(yaml_path)
    meta = load_yaml(yaml_path)
    if not isinstance(meta, dict):
        raise ConfigError(f"{yaml_path}: a map YAML must be a mapping, got {type(meta).__name__}")
    missing = [k for k in _REQUIRED if k not in meta]
    if missing:
        raise ConfigError(f"{yaml_path}: map YAML lacks required field(s) {', '.join(missing)}")
    res = _num(meta, "resolution", yaml_path)
    if res <= 0:
        raise ConfigError(f"{yaml_path}: resolution: must be > 0 m/cell, got {res}")
    o = meta["origin"]
    if not isinstance(o, list) or len(o) != 3:
        raise ConfigError(f"{yaml_path}: origin: must be a list [x, y, yaw], got {o!r}")
    origin = tuple(_num({"origin": v}, "origin", yaml_path) for v in o)
    if origin[2] != 0.0:
        raise ConfigError(
            f"{yaml_path}: origin: yaw {origin[2]} rad; rotated map origins are not supported "
            "(rotate the image and set yaw 0)"
        )
    occ_t = _num(meta, "occupied_thresh", yaml_path)
    free_t = _num(meta, "free_thresh", yaml_path)
    for key, v in (("occupied_thresh", occ_t), ("free_thresh", free_t)):
        if not 0.0 <= v <= 1.0:
            raise ConfigError(f"{yaml_path}: {key}: must be in [0, 1], got {v}")
    if not free_t < occ_t:
        raise ConfigError(
            f"{yaml_path}: free_thresh ({free_t}) must be smaller than occupied_thresh ({occ_t})"
        )
    neg = meta["negate"]
    if not isinstance(neg, Integral):
        raise ConfigError(f"{yaml_path}: negate: must be 0, 1 or a boolean, got {neg!r}")
    negate = bool(neg)
    mode = meta.get("mode", "trinary")
    if mode not in ("trinary", "scale", "raw"):
        raise ConfigError(f"{yaml_path}: mode: must be trinary, scale or raw, got {mode!r}")
    image = meta["image"]
    if not isinstance(image, str) or not image:
        raise ConfigError(f"{yaml_path}: image: must be a file name, got {image!r}")
    img_path = Path(image)
    if not img_path.is_absolute():
        img_path = yaml_path.parent / img_path
    try:
        rgb_sum, alpha = read_map_image(img_path)
    except ConfigError as e:
        raise ConfigError(f"{yaml_path}: image: {e}") from None
    data = occupancy_from_image(rgb_sum, alpha, mode, negate, occ_t, free_t)
    data = np.flipud(data)  # image row 0 is the top; ROS row 0 is the bottom
    refl, radius = _map_reflectors(meta.get("reflectors"), yaml_path)
    return OccupancyGrid(data, res, origin, refl, radius, occ_t, free_t)  # type: ignore[arg-type]


def image_from_occupancy(
    data: np.ndarray, mode: MapMode, occupied_thresh: float, free_thresh: float
) -> np.ndarray:
    """The 8-bit image (IMAGE row order) Nav2's map_saver writes for ``data`` (ROS rows, int8):

    * trinary (grey): cell < 0 or > 100 -> 205; ``cell <= rint(free * 100)`` -> 254;
      ``rint(occupied * 100) <= cell`` -> 0; else 205.
    * scale (H, W, 4 RGBA): grey ``round((100 - cell) / 100 * 255)``, opaque; unknown cells
      grey 128, fully transparent.
    * raw (grey): the cell value; unknown 255.
    """
    d = np.flipud(np.asarray(data, dtype=np.int16))
    unknown = (d < 0) | (d > 100)
    if mode == "trinary":
        img = np.full(d.shape, 205, dtype=np.uint8)
        img[~unknown & (d <= int(np.rint(free_thresh * 100)))] = 254
        img[~unknown & (d >= int(np.rint(occupied_thresh * 100)))] = 0
        return img
    if mode == "raw":
        return np.where(unknown, 255, d).astype(np.uint8)
    if mode == "scale":
        g = np.where(unknown, 128, np.floor((100 - d) / 100 * 255 + 0.5)).astype(np.uint8)
        a = np.where(unknown, 0, 255).astype(np.uint8)
        return np.stack([g, g, g, a], axis=-1)
    raise InvalidInputError(f"map mode must be trinary, scale or raw, got {mode!r}")


def save_map(grid: OccupancyGrid, yaml_path: str | Path, mode: MapMode = "trinary") -> Path:
    """Write ``<name>.yaml`` + the image as nav2 ``map_saver`` does (:func:`image_from_occupancy`;
    ``<name>.pgm`` for trinary and raw, ``<name>.png`` with alpha for scale), with the grid's
    thresholds and the reflector landmarks under the extra key ``reflectors``: reflector map
    entries ``{id, x, y, radius}`` when the radius is known, else ``{positions, radius: 0}``."""
    yaml_path = Path(yaml_path)
    yaml_path.parent.mkdir(parents=True, exist_ok=True)
    img = image_from_occupancy(grid.data, mode, grid.occupied_thresh, grid.free_thresh)
    if mode == "scale":
        img_path = yaml_path.with_suffix(".png")
        Image.fromarray(img, "RGBA").save(img_path)
    else:
        img_path = yaml_path.with_suffix(".pgm")
        write_pgm(img_path, img)
    meta: dict[str, object] = {
        "image": img_path.name,
        "mode": mode,
        "resolution": float(grid.resolution),
        "origin": [float(v) for v in grid.origin],
        "negate": 0,
        "occupied_thresh": float(grid.occupied_thresh),
        "free_thresh": float(grid.free_thresh),
    }
    if len(grid.reflectors) and grid.reflector_radius > 0:
        n = len(grid.reflectors)
        rm = ReflectorMap(np.arange(n), grid.reflectors, np.full(n, grid.reflector_radius))
        meta["reflectors"] = rm.entries()
    elif len(grid.reflectors):
        meta["reflectors"] = {
            "radius": 0.0,
            "positions": [[float(x), float(y)] for x, y in grid.reflectors],
        }
    yaml_path.write_text(yaml.safe_dump(meta, sort_keys=False, default_flow_style=None))
    return yaml_path


def replace_reflectors(grid: OccupancyGrid, path: str | Path) -> OccupancyGrid:
    """``grid`` with its reflectors replaced by those of the reflector map file ``path``
    (:mod:`mmpa.maps.reflector_map`); they must share one radius (the localizers take one),
    else :class:`ConfigError`."""
    rm = load_reflector_map(path)
    if np.ptp(rm.radius) > 1e-9:
        raise ConfigError(
            f"{path}: reflectors of different radii ({np.unique(rm.radius)} m); the "
            "localizer takes one radius"
        )
    return dataclasses.replace(grid, reflectors=rm.xy.copy(), reflector_radius=float(rm.radius[0]))
