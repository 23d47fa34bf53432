"""A reflector map: the surveyed laser reflectors of a site, in a file of their own.

File format (YAML, read through :func:`mmpa.core.yamlio.load_yaml`)::

    frame_id: map          # optional; the only frame accepted is ``map``
    reflectors:
      - {id: 0, x: 1.25, y: -0.40, radius: 0.04}
      - {id: 1, x: 3.00, y: 2.10, radius: 0.04}

``id``: an integer, unique in the file; ``x``, ``y``: the reflector's axis (m, ``map`` frame);
``radius``: the cylinder's radius (m, > 0). At least one reflector; no two closer than
:data:`MIN_SEPARATION`. The same entry format may be embedded in (or referenced by) a
``map_server`` map YAML's ``reflectors`` key (:func:`mmpa.maps.map_server.load_map`).
"""

from __future__ import annotations

from dataclasses import dataclass
from numbers import Integral
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial import cKDTree

from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.core.yamlio import finite_number, load_yaml

__all__ = [
    "MIN_SEPARATION",
    "ReflectorMap",
    "load_reflector_map",
    "parse_reflector_entries",
    "save_reflector_map",
]

#: Two reflectors closer than this (m) are the same reflector entered twice.
MIN_SEPARATION = 1e-6

_ENTRY_KEYS = ("id", "x", "y", "radius")


def _first_problem(ids: np.ndarray, xy: np.ndarray, radius: np.ndarray) -> tuple[int, str] | None:
    """The first inconsistency as (entry index, message), or None."""
    if len(ids) == 0:
        return -1, "a reflector map needs at least one reflector"
    for i in range(len(ids)):
        if not np.isfinite(xy[i]).all():
            return i, f"position must be finite, got ({xy[i, 0]}, {xy[i, 1]})"
        if not (np.isfinite(radius[i]) and radius[i] > 0):
            return i, f"radius must be a finite number > 0 m, got {radius[i]}"
    seen: dict[int, int] = {}
    for i, k in enumerate(ids.tolist()):
        if k in seen:
            return i, f"id {k} is taken by entry {seen[k]}"
        seen[k] = i
    pairs = cKDTree(xy).query_pairs(MIN_SEPARATION, output_type="ndarray")
    if len(pairs):
        a, b = sorted(pairs[0].tolist())
        return b, f"at the position of entry {a} ({xy[a, 0]}, {xy[a, 1]}): a duplicate reflector"
    return None


@dataclass(frozen=True)
class ReflectorMap:
    """Surveyed reflectors: ``ids`` (N,) int64, ``xy`` (N, 2) m in ``frame_id``, ``radius``
    (N,) m. The arrays are read-only; construction checks them (InvalidInputError)."""

    ids: np.ndarray
    xy: np.ndarray
    radius: np.ndarray
    frame_id: str = "map"

    def __post_init__(self) -> None:
        ids = np.asarray(self.ids)
        if ids.ndim != 1 or (ids.size and not np.issubdtype(ids.dtype, np.integer)):
            raise InvalidInputError(f"reflector ids must be a 1D integer array, got {ids.dtype}")
        ids = ids.astype(np.int64)
        xy = np.asarray(self.xy, dtype=float)
        radius = np.asarray(self.radius, dtype=float)
        n = len(ids)
        if xy.shape != (n, 2) or radius.shape != (n,):
            raise InvalidInputError(
                f"reflector map arrays disagree: ids {ids.shape}, xy {xy.shape} (want ({n}, 2)), "
                f"radius {radius.shape} (want ({n},))"
            )
        if self.frame_id != "map":
            raise InvalidInputError(f"reflector maps are in frame 'map', got {self.frame_id!r}")
        bad = _first_problem(ids, xy, radius)
        if bad is not None:
            i, msg = bad
            raise InvalidInputError(msg if i < 0 else f"reflector entry {i}: {msg}")
        for name, arr in (("ids", ids), ("xy", xy), ("radius", radius)):
            arr = arr.copy()
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return len(self.ids)

    def entries(self) -> list[dict[str, float | int]]:
        """The file's entry list (``id``, ``x``, ``y``, ``radius``), exact floats."""
        return [
            {"id": int(k), "x": float(p[0]), "y": float(p[1]), "radius": float(r)}
            for k, p, r in zip(self.ids, self.xy, self.radius, strict=True)
        ]


def parse_reflector_entries(entries: Any, what: str, field: str = "reflectors") -> ReflectorMap:
    """A :class:`ReflectorMap` from a parsed YAML list of ``{id, x, y, radius}`` mappings.

    ``what`` (the file) and ``field`` (the key holding the list) prefix every error, which
    names the entry index: ``site.yaml: reflectors[3].radius: must be > 0 m, got -0.04``.
    """
    if not isinstance(entries, list):
        raise ConfigError(
            f"{what}: {field}: must be a list of {{id, x, y, radius}} entries, "
            f"got {type(entries).__name__}"
        )
    if not entries:
        raise ConfigError(f"{what}: {field}: a reflector map needs at least one reflector")
    ids, xy, radius = [], [], []
    for i, e in enumerate(entries):
        where = f"{what}: {field}[{i}]"
        if not isinstance(e, dict):
            raise ConfigError(
                f"{where}: must be a mapping {{id, x, y, radius}}, got {type(e).__name__} {e!r}"
            )
        missing = [k for k in _ENTRY_KEYS if k not in e]
        extra = sorted(str(k) for k in e if k not in _ENTRY_KEYS)
        if missing or extra:
            raise ConfigError(
                f"{where}: needs exactly the keys id, x, y, radius"
                + (f"; missing {', '.join(missing)}" if missing else "")
                + (f"; unknown {', '.join(extra)}" if extra else "")
            )
        k = e["id"]
        if isinstance(k, bool) or not isinstance(k, Integral):
            raise ConfigError(f"{where}.id: must be an integer, got {k!r}")
        ids.append(int(k))
        xy.append((finite_number(e["x"], f"{where}.x"), finite_number(e["y"], f"{where}.y")))
        r = finite_number(e["radius"], f"{where}.radius")
        if r <= 0:
            raise ConfigError(f"{where}.radius: must be > 0 m, got {r}")
        radius.append(r)
    ids_a, xy_a, r_a = np.array(ids, np.int64), np.array(xy, float), np.array(radius, float)
    bad = _first_problem(ids_a, xy_a, r_a)
    if bad is not None:
        i, msg = bad
        raise ConfigError(f"{what}: {field}[{i}]: {msg}")
    return ReflectorMap(ids_a, xy_a, r_a)


def load_reflector_map(path: str | Path) -> ReflectorMap:
    """Read a reflector map file (see the module docstring); every error is a
    :class:`~mmpa.core.errors.ConfigError` naming the file (and the entry index)."""
    path = Path(path)
    doc = load_yaml(path)
    if not isinstance(doc, dict):
        raise ConfigError(
            f"{path}: a reflector map must be a mapping with a 'reflectors' list, "
            f"got {type(doc).__name__}"
        )
    extra = sorted(str(k) for k in doc if k not in ("frame_id", "reflectors"))
    if extra:
        raise ConfigError(f"{path}: unknown key(s) {', '.join(extra)}; valid: frame_id, reflectors")
    frame = doc.get("frame_id", "map")
    if frame != "map":
        raise ConfigError(f"{path}: frame_id: reflector maps are in frame 'map', got {frame!r}")
    if "reflectors" not in doc:
        raise ConfigError(f"{path}: lacks the required field 'reflectors'")
    return parse_reflector_entries(doc["reflectors"], str(path))


def save_reflector_map(rm: ReflectorMap, path: str | Path) -> Path:
    """Write ``rm`` as a reflector map file (floats written exactly: they round-trip)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"frame_id": rm.frame_id, "reflectors": rm.entries()}
    path.write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))
    return path
