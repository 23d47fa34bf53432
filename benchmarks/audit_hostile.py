"""Hostile-case re-audit of issue 22: bad inputs and faults as a new user would make them.

Generates (seeded, deterministic) well over 800 bad inputs and faults across the classes
issue 22 names -- map_server maps, reflector maps, scenes, robot files, YAML alias bombs,
``--set`` config overrides, the localizers, the twin arm's joint commands, point clouds for
registration, task bundles, the SQLite task store and the CLI -- runs each as a small
callable and classifies the outcome:

- ``clear``: refused with an mmpa error (:class:`mmpa.core.errors.MMPAError`; pydantic errors
  count only when mmpa's loaders wrap them in ConfigError); a CLI run exiting non-zero with
  no traceback (in-process: an MMPAError or OSError escaping the app counts as clear because
  the ``mmpa`` console script prints those as one line);
- ``handled``: accepted, and the result is what mmpa documents for that input (NaN beams
  ignored with a finite estimate, ``Registration.ok = False`` with a reason, a bundle read
  back bit-identical); only cases with such a documented contract can land here;
- ``traceback``: any other exception escaping (TypeError, IndexError, sqlite3.*, raw
  pydantic ValidationError, ...), or a CLI run printing ``Traceback``;
- ``silent wrong``: accepted without an error although the input is invalid by construction;
- ``hang``: over the per-case time limit (SIGALRM in the case's worker process; the worker
  of each class is also watched from outside and killed if it stops reporting);
- ``data lost``: task-store cases only: after mmpa handled the fault, the store fails
  ``PRAGMA integrity_check``, or a task committed before the fault is missing or differs
  (for faults that do not themselves destroy it), or a read-only operation changed the file.

Run::

    MUJOCO_GL=osmesa PYOPENGL_PLATFORM=osmesa .venv/bin/python benchmarks/audit_hostile.py \
        [--out audit.json] [--only maps,scenes] [--seed 22]

Prints one table per class and the total, then every case that was not ``clear`` or
``handled`` with its input and outcome. Takes a few minutes on one core.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import hashlib
import json
import multiprocessing as mp
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np
import yaml

from mmpa.core.errors import MMPAError
from mmpa.robot.interfaces import RobotDevices

REPO = Path(__file__).resolve().parents[1]
CASE_LIMIT_S = 20.0  # per in-process case
CLI_LIMIT_S = 60.0  # per subprocess CLI case
OUTCOMES = ("clear", "handled", "traceback", "silent wrong", "hang", "data lost")
NAN, INF = float("nan"), float("inf")


class _Hang(BaseException):
    """Raised by SIGALRM when a case runs past its limit (BaseException: not swallowed)."""


class Handled(Exception):  # noqa: N818 - an outcome, not an error
    """Raised by a case's check when an accepted result is the documented handling."""


class SilentWrong(Exception):  # noqa: N818
    """Raised by a case's check when an accepted result is wrong."""


class DataLost(Exception):  # noqa: N818
    """Raised by a task-store case when the store lost committed data."""


@dataclasses.dataclass
class Case:
    cls: str
    name: str  # the input, in words (enough to reproduce it)
    fn: Callable[[], Any]  # runs the operation; raising = refused
    check: Callable[[Any], None] | None = None  # on acceptance: raise Handled / SilentWrong
    after: Callable[[], None] | None = None  # always run after fn: raise DataLost
    cli: bool = False  # fn returns a CliRunner result or a CompletedProcess


# ---------------------------------------------------------------------------- helpers


def _dump(doc: object) -> str:
    return yaml.safe_dump(doc, sort_keys=False, allow_unicode=True)


def _write(p: Path, doc: object) -> Path:
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(_dump(doc) if not isinstance(doc, str) else doc)
    return p


def _set(doc: Any, path: tuple, value: Any) -> Any:
    out = copy.deepcopy(doc)
    node = out
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return out


def _drop(doc: Any, path: tuple) -> Any:
    out = copy.deepcopy(doc)
    node = out
    for k in path[:-1]:
        node = node[k]
    del node[path[-1]]
    return out


def _leaves(doc: Any, path: tuple = ()) -> Iterator[tuple[tuple, Any]]:
    """Numeric (not bool) leaves of a nested YAML document."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _leaves(v, (*path, i))
    elif isinstance(doc, (int, float)) and not isinstance(doc, bool):
        yield path, doc


def _dotted(path: tuple) -> str:
    return ".".join(str(p) for p in path)


#: values no numeric field accepts
BAD_NUMBERS: list[Any] = [NAN, INF, -INF, "abc", [1.0, 2.0], {"a": 1}]


def _pick(rng: np.random.Generator, items: list, k: int) -> list:
    if k >= len(items):
        return list(items)
    idx = sorted(rng.choice(len(items), k, replace=False).tolist())
    return [items[i] for i in idx]


def _alias_bomb(levels: int = 9) -> str:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, levels):
        refs = ", ".join([f"*a{i - 1}"] * 9)
        lines.append(f"a{i}: &a{i} [{refs}]")
    return "\n".join(lines) + "\n"


def _digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest() if p.exists() else ""


# ============================================================================ 1. YAML


def yaml_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    """Alias bombs, oversize, non-UTF-8 and broken syntax in every YAML reader."""
    from mmpa.apps.demo import DemoConfig
    from mmpa.backends.twin.scene import load_scene
    from mmpa.core.config import load_config
    from mmpa.core.yamlio import load_yaml, load_yaml_text
    from mmpa.maps.map_server import load_map
    from mmpa.maps.reflector_map import load_reflector_map
    from mmpa.robot.robot_file import load_robot
    from mmpa.tasks import read_bundle

    d = tmp / "yaml"
    d.mkdir()
    bodies: dict[str, bytes] = {
        "alias bomb (9 levels)": _alias_bomb(9).encode(),
        "alias bomb (3 levels)": _alias_bomb(3).encode(),
        "single alias": b"a: &x 1\nb: *x\n",
        "merge key alias": b"base: &b {x: 1}\nderived:\n  <<: *b\n  y: 2\n",
        "python tag": b"a: !!python/object/apply:os.system ['true']\n",
        "unknown tag": b"a: !custom 3\n",
        "binary garbage": bytes(rng.integers(0, 256, 512, dtype=np.uint8)),
        "latin-1 text": "name: caf\xe9\n".encode("latin-1"),
        "unclosed bracket": b"a: [1, 2\n",
        "tab indentation": b"a:\n\tb: 1\n",
        "duplicate anchor": b"a: &x 1\nb: &x 2\nc: *x\n",
        "5 MB of YAML": b"a: " + b"x" * (5 * 1024 * 1024) + b"\n",
        "deep nesting 5000": b"[" * 5000 + b"]" * 5000,
    }
    files = {}
    for i, (label, body) in enumerate(bodies.items()):
        p = d / f"doc{i}.yaml"
        p.write_bytes(body)
        files[label] = p
    (d / "dir.yaml").mkdir()
    files["a directory"] = d / "dir.yaml"
    files["missing file"] = d / "nope.yaml"

    def _bundle_with(p: Path) -> Path:
        b = d / f"bundle-{p.stem}"
        b.mkdir(exist_ok=True)
        shutil.copy(p, b / "task.yaml") if p.is_file() else None
        return b

    readers: dict[str, Callable[[Path], Any]] = {
        "load_yaml": load_yaml,
        "load_map": load_map,
        "load_reflector_map": load_reflector_map,
        "load_scene": load_scene,
        "load_robot": load_robot,
        "load_config": lambda p: load_config(DemoConfig, p),
        "read_bundle": lambda p: read_bundle(_bundle_with(p)),
    }
    cases = []
    for rname, reader in readers.items():
        for label, p in files.items():
            if rname == "read_bundle" and label in ("a directory", "missing file"):
                continue
            cases.append(Case("yaml", f"{rname}({label})", lambda r=reader, p=p: r(p)))
    for label, body in bodies.items():
        if label in ("binary garbage", "latin-1 text"):
            continue
        text = body.decode()
        cases.append(Case("yaml", f"load_yaml_text({label})", lambda t=text: load_yaml_text(t)))
    return cases


# ============================================================================ 2. maps


def _good_pgm(w: int = 20, h: int = 20) -> bytes:
    img = np.full((h, w), 254, np.uint8)
    img[0, :] = img[-1, :] = img[:, 0] = img[:, -1] = 0
    return f"P5\n{w} {h}\n255\n".encode() + img.tobytes()


MAP_DOC = {
    "image": "m.pgm",
    "resolution": 0.05,
    "origin": [-0.5, -0.5, 0.0],
    "occupied_thresh": 0.65,
    "free_thresh": 0.196,
    "negate": 0,
    "mode": "trinary",
    "reflectors": [
        {"id": 0, "x": 0.1, "y": 0.1, "radius": 0.04},
        {"id": 1, "x": 0.3, "y": 0.1, "radius": 0.04},
        {"id": 2, "x": 0.1, "y": 0.3, "radius": 0.04},
    ],
}


def map_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    from mmpa.maps.map_server import load_map

    d = tmp / "maps"
    d.mkdir()
    (d / "m.pgm").write_bytes(_good_pgm())
    _write(d / "good.yaml", MAP_DOC)
    load_map(d / "good.yaml")  # the base is valid
    cases: list[Case] = []
    n = [0]

    def add(label: str, doc: object, image: bytes | None = None, name: str = "m.pgm") -> None:
        n[0] += 1
        sub = d / f"c{n[0]}"
        sub.mkdir()
        (sub / "m.pgm").write_bytes(_good_pgm())
        if image is not None:
            (sub / name).write_bytes(image)
        p = _write(sub / "map.yaml", doc)
        cases.append(Case("maps", label, lambda p=p: load_map(p)))

    # every scalar field: values no map_server field accepts
    fields = ["resolution", "occupied_thresh", "free_thresh"]
    for f in fields:
        for v in [*BAD_NUMBERS, None, True, -0.05]:
            add(f"{f}={v!r}", _set(MAP_DOC, (f,), v))
    for v in [0, 0.0, -1e-9]:
        add(f"resolution={v!r}", _set(MAP_DOC, ("resolution",), v))
    for f, v in [("occupied_thresh", 1.5), ("free_thresh", -0.1), ("free_thresh", 0.9)]:
        add(f"{f}={v!r}", _set(MAP_DOC, (f,), v))
    for i in range(3):
        for v in [*BAD_NUMBERS, None, True]:
            add(f"origin[{i}]={v!r}", _set(MAP_DOC, ("origin", i), v))
    for v in ["0,0,0", 5, None, [0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [], {"x": 0}]:
        add(f"origin={v!r}", _set(MAP_DOC, ("origin",), v))
    add("origin yaw 0.3 (rotated map)", _set(MAP_DOC, ("origin", 2), 0.3))
    for v in [NAN, "yes please", 0.5, [0], None, {"a": 1}]:
        add(f"negate={v!r}", _set(MAP_DOC, ("negate",), v))
    for v in ["bogus", 3, None, NAN, ["raw"], ""]:
        add(f"mode={v!r}", _set(MAP_DOC, ("mode",), v))
    for v in ["", None, 3, NAN, ["m.pgm"], "missing.pgm", ".", "/nonexistent/m.pgm"]:
        add(f"image={v!r}", _set(MAP_DOC, ("image",), v))
    for k in ["image", "resolution", "origin", "occupied_thresh", "free_thresh", "negate"]:
        add(f"without {k}", _drop(MAP_DOC, (k,)))
    for v in [[], "just text", 42, None]:
        add(f"whole document = {v!r}", v)
    # broken images
    good = _good_pgm()
    images: dict[str, bytes] = {
        "empty image file": b"",
        "PGM header only": b"P5\n20 20\n255\n",
        "PGM with half the pixels": good[: len(good) // 2],
        "PGM width 0": b"P5\n0 20\n255\n",
        "PGM negative width": b"P5\n-20 20\n255\n" + good[13:],
        "PGM maxval 0": b"P5\n20 20\n0\n" + good[13:],
        "PGM maxval 70000": b"P5\n20 20\n70000\n" + good[13:],
        "PGM 100000 x 100000 header, 400 bytes": b"P5\n100000 100000\n255\n" + good[13:],
        "PGM non-numeric size": b"P5\nab cd\n255\n" + good[13:],
        "P2 ASCII with words": b"P2\n2 2\n255\nzero one two three\n",
        "PNG signature only": b"\x89PNG\r\n\x1a\n",
        "PNG signature + garbage": b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4,
        "text file": b"this is not an image\n",
    }
    for _ in range(12):  # random truncations of a valid PGM inside its header and pixels
        cut = int(rng.integers(0, len(good) - 1))
        images[f"PGM truncated at byte {cut}"] = good[:cut]
    for i in range(8):  # random bytes
        images[f"random bytes #{i}"] = bytes(rng.integers(0, 256, 200, dtype=np.uint8))
    for label, img in images.items():
        add(label, MAP_DOC, img)
        if label in ("PNG signature + garbage", "text file", "empty image file"):
            add(f"{label} as .png", _set(MAP_DOC, ("image",), "m.png"), img, "m.png")
    # reflector lists
    for i in range(3):
        for k in ["x", "y", "radius"]:
            for v in [*BAD_NUMBERS, None, True]:
                add(f"reflectors[{i}].{k}={v!r}", _set(MAP_DOC, ("reflectors", i, k), v))
        for v in [1.5, "zero", None, NAN, True]:
            add(f"reflectors[{i}].id={v!r}", _set(MAP_DOC, ("reflectors", i, "id"), v))
        add(f"reflectors[{i}] without x", _drop(MAP_DOC, ("reflectors", i, "x")))
    for v in [0.0, -0.04]:
        add(f"reflectors[1].radius={v}", _set(MAP_DOC, ("reflectors", 1, "radius"), v))
    add("reflectors: duplicate id", _set(MAP_DOC, ("reflectors", 2, "id"), 0))
    add(
        "reflectors: duplicate position",
        _set(_set(MAP_DOC, ("reflectors", 2, "x"), 0.1), ("reflectors", 2, "y"), 0.1),
    )
    add("reflectors: mixed radii", _set(MAP_DOC, ("reflectors", 2, "radius"), 0.05))
    add("reflectors: extra key", _set(MAP_DOC, ("reflectors", 0, "colour"), "red"))
    for v in [5, "missing-reflectors.yaml", [1, 2, 3], [[0.1, 0.2]], True]:
        add(f"reflectors={v!r}", _set(MAP_DOC, ("reflectors",), v))
    for v in [
        {"positions": [[NAN, 0.0], [1.0, 1.0]], "radius": 0.04},
        {"positions": [[0.0, 0.0], [0.0, 0.0]], "radius": 0.04},
        {"positions": [[0.0, 0.0]], "radius": -0.04},
        {"positions": [[0.0, 0.0]], "radius": NAN},
        {"positions": [[0.0]], "radius": 0.04},
        {"positions": "here", "radius": 0.04},
        {"positions": [[0.0, 0.0]], "size": 0.04},
    ]:
        add(f"reflectors={v!r}", _set(MAP_DOC, ("reflectors",), v))
    return cases


# ============================================================================ 3. reflector maps


RM_DOC = {
    "frame_id": "map",
    "reflectors": [
        {"id": 0, "x": 1.25, "y": -0.4, "radius": 0.04},
        {"id": 1, "x": 3.0, "y": 2.1, "radius": 0.04},
        {"id": 2, "x": -1.0, "y": 0.5, "radius": 0.04},
    ],
}


def reflector_map_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    from mmpa.maps.reflector_map import load_reflector_map

    d = tmp / "rm"
    d.mkdir()
    load_reflector_map(_write(d / "good.yaml", RM_DOC))
    cases: list[Case] = []

    def add(label: str, doc: object) -> None:
        p = _write(d / f"rm{len(cases)}.yaml", doc)
        cases.append(Case("reflector maps", label, lambda p=p: load_reflector_map(p)))

    for i in range(3):
        for k in ["x", "y", "radius"]:
            for v in [*BAD_NUMBERS, None, True, "1.0"]:
                add(f"reflectors[{i}].{k}={v!r}", _set(RM_DOC, ("reflectors", i, k), v))
            add(f"reflectors[{i}] without {k}", _drop(RM_DOC, ("reflectors", i, k)))
        for v in [1.5, "zero", None, NAN, True, [0], {"id": 0}]:
            add(f"reflectors[{i}].id={v!r}", _set(RM_DOC, ("reflectors", i, "id"), v))
        for v in [0.0, -0.04, -INF]:
            add(f"reflectors[{i}].radius={v!r}", _set(RM_DOC, ("reflectors", i, "radius"), v))
        add(f"reflectors[{i}] extra key", _set(RM_DOC, ("reflectors", i, "z"), 0.0))
        add(f"reflectors[{i}] = a list", _set(RM_DOC, ("reflectors", i), [1.0, 2.0]))
    add("duplicate id", _set(RM_DOC, ("reflectors", 2, "id"), 1))
    add(
        "duplicate position",
        _set(_set(RM_DOC, ("reflectors", 2, "x"), 3.0), ("reflectors", 2, "y"), 2.1),
    )
    for v in [[], None, "a.yaml", 3, {"id": 0}]:
        add(f"reflectors={v!r}", _set(RM_DOC, ("reflectors",), v))
    for v in ["odom", None, 3, ""]:
        add(f"frame_id={v!r}", _set(RM_DOC, ("frame_id",), v))
    add("without reflectors", _drop(RM_DOC, ("reflectors",)))
    add("unknown top-level key", {**RM_DOC, "origin": [0, 0]})
    for v in [[], "text", 7, None]:
        add(f"document = {v!r}", v)
    for j in range(20):  # random entries: one field of one entry replaced at random
        i, k = int(rng.integers(0, 3)), str(rng.choice(["x", "y", "radius"]))
        v = float(rng.choice([NAN, INF, -INF])) * float(rng.uniform(0.5, 2.0))
        add(f"random #{j}: reflectors[{i}].{k}={v!r}", _set(RM_DOC, ("reflectors", i, k), v))
    return cases


# ============================================================================ 4. scenes


def scene_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    from mmpa.backends.twin.scene import default_scene_path, load_scene

    d = tmp / "scenes"
    d.mkdir()
    base = yaml.safe_load(default_scene_path().read_text())
    load_scene(_write(d / "good.yaml", base))
    cases: list[Case] = []

    def add(label: str, doc: object) -> None:
        p = _write(d / f"s{len(cases)}.yaml", doc)
        cases.append(Case("scenes", label, lambda p=p: load_scene(p)))

    leaves = list(_leaves(base))
    # NaN / inf / wrong type at a seeded sample of numeric leaves
    for path, _ in _pick(rng, leaves, 40):
        for v in _pick(rng, BAD_NUMBERS, 3):
            add(f"{_dotted(path)}={v!r}", _set(base, path, v))
    # sizes: zero and negative
    size_paths = [
        p
        for p, _ in leaves
        if any(
            isinstance(k, str) and any(s in k for s in ("size", "radius", "height", "thickness"))
            for k in p
        )
        and "position" not in str(p)
        and "offset" not in str(p)
        and "plate_height" not in str(p)  # >= 0 by design: 0 is "no plate"
    ]
    for path in _pick(rng, size_paths, 20):
        for v in (0.0, -0.5):
            add(f"{_dotted(path)}={v!r} (a size)", _set(base, path, v))
    # colours out of [0, 1]
    colour_paths = [p for p, _ in leaves if any("colo" in str(k) for k in p)]
    for path in _pick(rng, colour_paths, 10):
        for v in (1.5, -0.2, NAN):
            add(f"{_dotted(path)}={v!r} (a colour)", _set(base, path, v))
    # reflectors
    pos = base["reflectors"]["positions"]
    for v in [NAN, INF, "x"]:
        add(f"reflectors.positions[0][0]={v!r}", _set(base, ("reflectors", "positions", 0, 0), v))
    add("duplicate reflector", _set(base, ("reflectors", "positions", 1), list(pos[0])))
    add("two reflectors only", _set(base, ("reflectors", "positions"), pos[:2]))
    add("reflector position of 3 numbers", _set(base, ("reflectors", "positions", 0), [1, 2, 3]))
    for v in [0.0, -0.04, NAN]:
        add(f"reflectors.radius={v!r}", _set(base, ("reflectors", "radius"), v))
    # walls
    w0 = base["walls"][0]
    add("wall of zero length", _set(base, ("walls", 0, "end"), list(w0["start"])))
    for k in ["thickness", "height"]:
        for v in [0.0, -0.1, NAN]:
            add(f"walls[0].{k}={v!r}", _set(base, ("walls", 0, k), v))
    # sites
    site0 = next(iter(base["sites"]))
    for v in [[0, 0, 0, 0], [NAN, 0, 0, 1], [0, 0, 0, 5], [0, 0, 1]]:
        add(
            f"sites.{site0}.orientation_xyzw={v}",
            _set(base, ("sites", site0, "orientation_xyzw"), v),
        )
    add(f"sites.{site0}.workbench unknown", _set(base, ("sites", site0, "workbench"), "nope"))
    for v in [[NAN, 0, 0], [0, 0], "here"]:
        add(f"sites.{site0}.position={v!r}", _set(base, ("sites", site0, "position"), v))
    # whole-document damage
    for k in ["name", "walls", "reflectors", "sites"]:
        add(f"without {k}", _drop(base, (k,)))
    add("unknown top-level key", {**base, "gravity": 9.81})
    for v in [[], "text", 3, None]:
        add(f"document = {v!r}", v)
    if base.get("grasp_objects"):
        objs = base["grasp_objects"]
        add("duplicate grasp object", _set(base, ("grasp_objects",), [*objs, objs[0]]))
    for v in [[0.0, 20.0], [NAN, 20.0], [30.0, -1.0]]:
        add(f"floor_size={v}", _set(base, ("floor_size",), v))
    for v in ["seven", NAN, 1.5]:
        add(f"seed={v!r}", _set(base, ("seed",), v))
    return cases


# ============================================================================ 5. robot files


def robot_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    from mmpa.robot.description import RobotDescription
    from mmpa.robot.robot_file import load_robot, robot_to_yaml

    d = tmp / "robots"
    d.mkdir()
    base = yaml.safe_load(robot_to_yaml(RobotDescription()))
    load_robot(_write(d / "good.yaml", base))
    cases: list[Case] = []

    def add(label: str, doc: object, cal: str | None = None) -> None:
        sub = d / f"r{len(cases)}"
        sub.mkdir()
        if cal is not None:
            (sub / "calibration.conf").write_text(cal)
        p = _write(sub / "robot.yaml", doc)
        cases.append(Case("robot files", label, lambda p=p: load_robot(p)))

    leaves = list(_leaves(base))
    for path, _ in _pick(rng, leaves, 45):
        for v in _pick(rng, BAD_NUMBERS, 2):
            add(f"{_dotted(path)}={v!r}", _set(base, path, v))
    # limits and sizes that must be positive or ordered
    for path, v in [
        (("arm", "qd_max", 0), 0.0),
        (("arm", "qd_max", 1), -1.0),
        (("arm", "qdd_max", 2), 0.0),
        (("arm", "reach"), -0.85),
        (("arm", "reach"), 0.0),
        (("arm", "q_min", 0), 7.0),  # q_min > q_max
        (("base", "wheel_radius"), 0.0),
        (("base", "track_width"), -0.46),
        (("base", "mass"), -60.0),
        (("camera", "color", "width"), 0),
        (("camera", "color", "fx"), -615.0),
        (("camera", "depth", "height"), -480),
        (("camera", "rate"), 0.0),
        (("camera", "min_range"), 5.0),  # min above max
        (("lidar", "num_beams"), 0),
        (("lidar", "angle_increment"), 0.0),
        (("lidar", "range_min"), -0.05),
        (("lidar", "range_max"), 0.01),  # below range_min
        (("lidar", "rate"), -10.0),
        (("gripper", "stroke"), -0.085),
        (("gripper", "max_force"), 0.0),
        (("photosensor", "max_range"), -0.5),
        (("control_rate",), 0.0) if "control_rate" in base else (("base", "mass"), 0.0),
    ]:
        add(f"{_dotted(path)}={v!r}", _set(base, path, v))
    for path, v in [
        (("arm", "qd_max"), [3.14] * 5),
        (("arm", "home"), [0.0] * 7),
        (("arm", "dh", "a"), [0.0] * 3),
        (("camera", "T_flange_camera_vec"), [0.0] * 5),
        (("lidar", "T_base_link_laser_vec"), "front"),
        (("arm", "home"), [9.0, 0, 0, 0, 0, 0]),  # outside the joint limits
    ]:
        add(f"{_dotted(path)}={v!r}", _set(base, path, v))
    # shortcuts
    arm = {k: v for k, v in base["arm"].items() if k != "dh"}
    for v in ["ur99", 5, ["ur5e"]]:  # (null = not given: valid)
        add(f"arm.model={v!r}", {"arm": {**arm, "model": v}})
    add("unknown top-level key", {**base, "wings": 2})
    add("unknown arm key", _set(base, ("arm", "wingspan"), 2.0))
    for v in [[], "robot", 3]:
        add(f"document = {v!r}", v)
    add("arm = a list", _set(base, ("arm",), [1, 2]))
    add("arm.dh = text", _set(base, ("arm", "dh"), "standard"))
    # calibration.conf
    good_cal = "[mounting]\n" + "".join(
        f"{k} = [0, 0, 0, 0, 0, 0]\n" for k in ("delta_theta", "delta_a", "delta_d", "delta_alpha")
    )
    (d / "cal-good").mkdir()
    (d / "cal-good" / "c.conf").write_text(good_cal)
    load_robot(_write(d / "cal-good" / "robot.yaml", {"arm": {"calibration": "c.conf"}}))
    cal_doc = {"arm": {"calibration": "calibration.conf"}}
    bad_cals = {
        "calibration NaN delta": good_cal.replace("delta_a = [0, 0", "delta_a = [nan, 0"),
        "calibration inf delta": good_cal.replace("delta_d = [0, 0", "delta_d = [inf, 0"),
        "calibration 5 values": good_cal.replace(
            "delta_alpha = [0, 0, 0, 0, 0, 0]", "delta_alpha = [0, 0, 0, 0, 0]"
        ),
        "calibration text value": good_cal.replace("delta_theta = [0", "delta_theta = [zero"),
        "calibration without [mounting]": "[other]\nx = 1\n",
        "calibration without delta_d": "\n".join(
            ln for ln in good_cal.splitlines() if not ln.startswith("delta_d")
        ),
        "calibration not INI": "just some text\n",
        "calibration empty": "",
        "calibration huge delta 1e300": good_cal.replace("delta_a = [0, 0", "delta_a = [1e300, 0"),
    }
    for label, text in bad_cals.items():
        add(label, cal_doc, text)
    add("calibration file missing", {"arm": {"calibration": "missing.conf"}})
    return cases


# ============================================================================ 6. config overrides


def config_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    from mmpa.apps.demo import DemoConfig
    from mmpa.core.config import load_config

    base = DemoConfig().model_dump(mode="json")
    leaves = list(_leaves(base))
    cases: list[Case] = []

    def add(label: str, sets: list[str], path: Path | None = None) -> None:
        cases.append(
            Case("config overrides", label, lambda s=sets, p=path: load_config(DemoConfig, p, s))
        )

    texts = {NAN: ".nan", INF: ".inf", -INF: "-.inf", "abc": "abc", "[1, 2]": "[1, 2]"}
    for path, _ in _pick(rng, leaves, 45):
        for v in _pick(rng, list(texts), 2):
            key = _dotted(path)
            add(f"--set {key}={texts[v]}", [f"{key}={texts[v]}"])
    for s in [
        "errors.seed=-5",
        "errors.seed=1.5",
        "errors.seed=abc",
        "errors.profile=bogus",
        "errors.profile=.nan",
        "nosuchkey=1",
        "errors.nosuchfield=1",
        "errors.camera.nosuchfield=1",
        "=3",
        "seed",
        "errors.camera=3",
        "errors=[1, 2]",
        "errors.seed=*a",
        "errors.seed=[1, 2",
        "localization=bogus",
        "control_rate=-20",
        "control_rate=0",
        ".=1",
        "errors.camera.color_sigma=-1",
        "errors.lidar.range_sigma=-0.015",
        "errors.odometry.alpha1=-0.05",
        "controller.max_v=-0.4",
        "controller.pos_tol=-0.01",
        "controller.max_v=0",
    ]:
        add(f"--set {s}", [s])
    files = {
        "config list": "[1, 2]\n",
        "config alias bomb": _alias_bomb(6),
        "config unknown key": "wings: 2\n",
        "config NaN control_rate": "control_rate: .nan\n",
        "config errors as text": "errors: realistic\n",
    }
    for label, text in files.items():
        p = _write(tmp / "config" / f"{len(cases)}.yaml", text)
        add(label, [], p)
    return cases


# ============================================================================ 7. localizers


def _room(with_reflectors: bool):
    from mmpa.maps.occupancy import Box2D, rasterize

    walls = [
        Box2D((0.0, 3.0), (8.0, 0.1)),
        Box2D((0.0, -3.0), (8.0, 0.1)),
        Box2D((4.0, 0.0), (0.1, 6.0)),
        Box2D((-4.0, 0.0), (0.1, 6.0)),
        Box2D((1.5, 1.0), radius=0.3),
        Box2D((-2.0, -1.5), (1.2, 0.6)),
    ]
    L = np.array([[3.5, 2.5], [-3.5, 2.5], [3.5, -2.5], [-3.5, -2.5], [0.0, 2.7]])
    return rasterize(walls, (-4.5, -3.5, 4.5, 3.5), 0.05, L if with_reflectors else None, 0.04)


def localizer_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    from mmpa.localization.amcl import AMCL, AMCLConfig
    from mmpa.localization.localizer import METHODS, make_localizer
    from mmpa.robot.interfaces import LaserScan

    grid = _room(True)
    laser = np.array([0.2, 0.0, 0.0])
    truth = np.array([0.5, -0.5, 0.3])
    n = 360
    inc = 2 * np.pi / n
    ang = -np.pi + inc * np.arange(n)
    ranges = AMCL(grid, laser).raycast(truth[None, :], ang, 10.0)[0]
    # bright returns at the reflectors' bearings
    inten = np.full(n, 100.0)
    lx = truth[0] + laser[0] * np.cos(truth[2])
    ly = truth[1] + laser[0] * np.sin(truth[2])
    for x, y in grid.reflectors:
        b = np.arctan2(y - ly, x - lx) - truth[2]
        k = round(((b + np.pi) % (2 * np.pi)) / inc) % n
        inten[k] = 5000.0

    def scan(r: np.ndarray, i: np.ndarray | None = None, n_: int = n) -> LaserScan:
        inc_ = 2 * np.pi / max(n_, 1)
        return LaserScan(
            -np.pi,
            -np.pi + inc_ * (n_ - 1),
            inc_,
            0.0,
            0.1,
            0.05,
            10.0,
            r,
            inten[:n_] if i is None else i,
        )

    good = scan(ranges)
    amcl_cfg = AMCLConfig(max_particles=500, min_particles=100)

    def fresh(method: str):
        loc = make_localizer(method, grid, laser, np.random.default_rng(0), amcl=amcl_cfg)
        loc.initialize(truth + np.array([0.02, -0.02, 0.01]))
        return loc

    def finite_estimate(est: Any) -> None:
        pose = np.asarray(est.pose, float)
        cov = np.asarray(est.cov, float)
        if np.all(np.isfinite(pose)) and np.all(np.isfinite(cov)) and pose.shape == (3,):
            raise Handled(f"finite estimate {np.round(pose, 3).tolist()}")
        raise SilentWrong(f"estimate {pose.tolist()} cov finite={np.isfinite(cov).all()}")

    cases: list[Case] = []
    for m in METHODS:
        # NaN / inf odometry at each component
        for i in range(3):
            for v in (NAN, INF, -INF):
                odom = truth.copy()
                odom[i] = v
                cases.append(
                    Case(
                        "localizers",
                        f"{m}: update(odom[{i}]={v})",
                        lambda m=m, o=odom: fresh(m).update(o, good, force=True),
                    )
                )
        for odom, label in [
            (np.zeros(2), "odom of 2 numbers"),
            (np.array(["a", "b", "c"]), "odom of strings"),
        ]:
            cases.append(
                Case(
                    "localizers",
                    f"{m}: update({label})",
                    lambda m=m, o=odom: fresh(m).update(o, good, force=True),
                )
            )
        # NaN / inf / misshaped initial pose and covariance
        for i in range(3):
            for v in (NAN, INF):
                p0 = truth.copy()
                p0[i] = v
                cases.append(
                    Case(
                        "localizers",
                        f"{m}: initialize(pose[{i}]={v})",
                        lambda m=m, p=p0: make_localizer(
                            m, grid, laser, np.random.default_rng(0), amcl=amcl_cfg
                        ).initialize(p),
                    )
                )
        for p0, label in [(np.zeros(2), "pose of 2"), (np.zeros(4), "pose of 4")]:
            cases.append(
                Case(
                    "localizers",
                    f"{m}: initialize({label})",
                    lambda m=m, p=p0: make_localizer(
                        m, grid, laser, np.random.default_rng(0), amcl=amcl_cfg
                    ).initialize(p),
                )
            )
        for cov, label in [
            (np.full((3, 3), NAN), "cov NaN"),
            (-np.eye(3), "cov negative definite"),
            (np.eye(2), "cov 2x2"),
        ]:
            cases.append(
                Case(
                    "localizers",
                    f"{m}: initialize(truth, {label})",
                    lambda m=m, c=cov: make_localizer(
                        m, grid, laser, np.random.default_rng(0), amcl=amcl_cfg
                    ).initialize(truth, c),
                )
            )
        # scans: handled when the estimate stays finite (NaN beams are ignored by contract)
        r_nan = ranges.copy()
        r_nan[rng.choice(n, n // 4, replace=False)] = NAN
        scans = {
            "25 % NaN beams": scan(r_nan),
            "all beams NaN": scan(np.full(n, NAN)),
            "all beams inf": scan(np.full(n, INF)),
            "all beams -1": scan(np.full(n, -1.0)),
            "all beams 0": scan(np.zeros(n)),
            "intensities NaN": scan(ranges, np.full(n, NAN)),
            "a 1-beam scan": scan(ranges[:1], n_=1),
        }
        for label, sc in scans.items():
            cases.append(
                Case(
                    "localizers",
                    f"{m}: update({label})",
                    lambda m=m, s=sc: fresh(m).update(truth, s, force=True),
                    check=finite_estimate,
                )
            )
        cases.append(
            Case(
                "localizers",
                f"{m}: update(scan=None)",
                lambda m=m: fresh(m).update(truth, None, force=True),
            )
        )
        cases.append(
            Case(
                "localizers",
                f"{m}: pose_at(NaN odom)",
                lambda m=m: fresh(m).pose_at(np.array([NAN, 0.0, 0.0])),
            )
        )
    # the scan itself and the map
    for label, fn in [
        ("LaserScan with 0 beams", lambda: scan(np.zeros(0), np.zeros(0), n_=0)),
        (
            "LaserScan angle_increment 0",
            lambda: LaserScan(0.0, 1.0, 0.0, 0, 0.1, 0.05, 10.0, np.zeros(3), np.zeros(3)),
        ),
        (
            "LaserScan angle_increment NaN",
            lambda: LaserScan(0.0, 1.0, NAN, 0, 0.1, 0.05, 10.0, np.zeros(3), np.zeros(3)),
        ),
        (
            "LaserScan range_max NaN",
            lambda: LaserScan(0.0, 1.0, 0.5, 0, 0.1, 0.05, NAN, np.zeros(3), np.zeros(3)),
        ),
        (
            "LaserScan ranges list",
            lambda: LaserScan(0.0, 1.0, 0.5, 0, 0.1, 0.05, 10.0, [1.0, 1.0, 1.0], np.zeros(3)),
        ),
        ("make_localizer unknown method", lambda: make_localizer("magic", grid, laser)),
        (
            "make_localizer laser_pose NaN",
            lambda: make_localizer("amcl", grid, np.array([NAN, 0, 0])),
        ),
        (
            "enhanced on a map without reflectors",
            lambda: make_localizer("enhanced", _room(False), laser),
        ),
    ]:
        cases.append(Case("localizers", label, fn))
    return cases


# ============================================================================ 8. joints (twin arm)


def joint_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    from mmpa.backends.twin.world import SimWorld
    from mmpa.planning import retime
    from mmpa.robot.description import ArmDescription
    from mmpa.robot.limits import JointLimits, check_path

    arm_d = ArmDescription()
    lim = JointLimits.from_description(arm_d)
    home = np.array(arm_d.home)
    world = SimWorld(site="0")
    arm = world.arm
    arm.move_joints(home)

    def unmoved() -> None:
        """After a refusal the arm must not have moved (it was at home)."""
        world.step(0.05)
        if np.abs(arm.joint_positions() - home).max() > 2e-3:
            got = arm.joint_positions()
            arm.move_joints(home)
            raise SilentWrong(f"the arm moved to {np.round(got, 3).tolist()}")

    def rehome() -> None:
        if world._stream is not None or np.abs(arm.joint_positions() - home).max() > 2e-3:
            with contextlib.suppress(Exception):
                arm.move_joints(home)

    cases: list[Case] = []
    t = np.arange(10) * 0.02
    q = np.tile(home, (10, 1))

    def path_with(i: int, j: int, v: float) -> np.ndarray:
        out = q.copy()
        out[i, j] = v
        return out

    # follow: NaN / inf anywhere, out of limits, jumps, bad times
    for k in range(12):
        i, j = int(rng.integers(0, 10)), int(rng.integers(0, 6))
        v = [NAN, INF, -INF][k % 3]
        cases.append(
            Case(
                "joints",
                f"follow(q[{i},{j}]={v})",
                lambda p=path_with(i, j, v): arm.follow(t, p),  # noqa: B008
                after=rehome,
            )
        )
    for k in range(8):
        i, j = int(rng.integers(0, 10)), int(rng.integers(0, 6))
        v = float(lim.q_max[j] + rng.uniform(0.1, 3.0)) * (1 if k % 2 else -1)
        cases.append(
            Case(
                "joints",
                f"follow(q[{i},{j}]={v:.3f}, outside the limits)",
                lambda p=path_with(i, j, v): arm.follow(t, p),  # noqa: B008
                after=rehome,
            )
        )
    for _ in range(6):
        j = int(rng.integers(0, 6))
        jump = q.copy()
        jump[5:, j] += float(rng.uniform(0.5, 2.0))
        cases.append(
            Case(
                "joints",
                f"follow(joint {j + 1} jumps {jump[5, j] - home[j]:.2f} rad in 20 ms)",
                lambda p=jump: arm.follow(t, p),
                after=rehome,
            )
        )
    bad_times = {
        "t[3]=NaN": np.where(np.arange(10) == 3, NAN, t),
        "t[9]=inf": np.where(np.arange(10) == 9, INF, t),
        "t decreasing": t[::-1].copy(),
        "t all equal": np.zeros(10),
        "t with a repeat": np.where(np.arange(10) == 4, t[3], t),
        "t negative steps": -t,
    }
    for label, tt in bad_times.items():
        cases.append(
            Case("joints", f"follow({label})", lambda tt=tt: arm.follow(tt, q), after=rehome)
        )
    for label, (tt, qq) in {
        "empty path": (np.zeros(0), np.zeros((0, 6))),
        "q of 5 joints": (t, q[:, :5]),
        "times of 9 for 10 samples": (t[:9], q),
        "q as text": (t, np.full((10, 6), "x")),
    }.items():
        cases.append(
            Case(
                "joints", f"follow({label})", lambda tt=tt, qq=qq: arm.follow(tt, qq), after=rehome
            )
        )
    for hz in (0.0, -250.0, NAN, INF):
        cases.append(
            Case(
                "joints",
                f"follow(record_hz={hz})",
                lambda hz=hz: arm.follow(t, q, record_hz=hz),
                after=rehome,
            )
        )
    # command / move_joints
    targets: dict[str, Any] = {}
    for j in range(6):
        targets[f"q[{j}]=NaN"] = np.where(np.arange(6) == j, NAN, home)
        targets[f"q[{j}]={lim.q_max[j] + 0.5:.2f} (above q_max)"] = np.where(
            np.arange(6) == j, lim.q_max[j] + 0.5, home
        )
    targets.update(
        {
            "all inf": np.full(6, INF),
            "5 joints": home[:5],
            "7 joints": np.zeros(7),
            "None": None,
            "text": "home",
        }
    )
    for label, tq in targets.items():
        cases.append(
            Case("joints", f"command({label})", lambda tq=tq: arm.command(tq), after=rehome)
        )
        cases.append(
            Case("joints", f"move_joints({label})", lambda tq=tq: arm.move_joints(tq), after=rehome)
        )
    for dur in (NAN, -1.0, INF):
        cases.append(
            Case(
                "joints",
                f"move_joints(home + 0.1, duration={dur})",
                lambda dur=dur: arm.move_joints(home + 0.1, duration=dur),
                check=lambda _r: unmoved(),
                after=rehome,
            )
        )
    # path checks and retiming (what the missions call before moving)
    for _ in range(6):
        i, j = int(rng.integers(0, 10)), int(rng.integers(0, 6))
        cases.append(
            Case(
                "joints",
                f"check_path(q[{i},{j}]=NaN)",
                lambda p=path_with(i, j, NAN): check_path(t, p, lim),  # noqa: B008
            )
        )
        cases.append(
            Case(
                "joints",
                f"retime(q[{i},{j}]=NaN)",
                lambda p=path_with(i, j, NAN): retime(t, p, arm_d),  # noqa: B008
            )
        )
    for label, tt in bad_times.items():
        cases.append(Case("joints", f"retime({label})", lambda tt=tt: retime(tt, q, arm_d)))
    return cases


# ============================================================================ 9. registration


def registration_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    from mmpa.registration import RegistrationConfig, register
    from mmpa.robot.interfaces import PointCloud

    cfg = RegistrationConfig()
    # a valid textured surface (a bumpy patch), ~2000 points
    u, v = np.meshgrid(np.linspace(-0.2, 0.2, 45), np.linspace(-0.2, 0.2, 45))
    z = 0.6 + 0.03 * np.sin(12 * u) * np.cos(9 * v)
    pts = np.column_stack([u.ravel(), v.ravel(), z.ravel()])
    cols = np.clip(
        0.5
        + 0.4
        * np.column_stack(
            [np.sin(20 * u.ravel()), np.cos(15 * v.ravel()), np.sin(7 * (u + v).ravel())]
        ),
        0,
        1,
    )
    good = PointCloud(pts, cols)

    def refused(reg: Any) -> None:
        if not reg.ok and reg.reason:
            raise Handled(f"ok=False: {reg.reason}")
        raise SilentWrong(f"ok=True, T translation {np.round(reg.T[:3, 3], 4).tolist()}")

    clouds: dict[str, Callable[[], Any]] = {
        "empty cloud": lambda: PointCloud(np.zeros((0, 3)), np.zeros((0, 3))),
        "one point": lambda: PointCloud(pts[:1], cols[:1]),
        "5 points": lambda: PointCloud(pts[:5], cols[:5]),
        "all NaN": lambda: PointCloud(np.full_like(pts, NAN), cols),
        "all inf": lambda: PointCloud(np.full_like(pts, INF), cols),
        "one point identical x 2025": lambda: PointCloud(np.tile(pts[:1], (len(pts), 1)), cols),
        "collinear points": lambda: PointCloud(
            np.column_stack([u.ravel(), 0 * u.ravel(), 0.6 + 0 * u.ravel()]), cols
        ),
        "a flat plane": lambda: PointCloud(
            np.column_stack([u.ravel(), v.ravel(), 0.6 + 0 * u.ravel()]), cols
        ),
        "coordinates 1e30": lambda: PointCloud(pts * 1e30, cols),
        "coordinates 1e-9 (a speck)": lambda: PointCloud(pts * 1e-9, cols),
        "colors NaN": lambda: PointCloud(pts, np.full_like(cols, NAN)),
        "colors 0..255 (not 0..1)": lambda: PointCloud(pts, cols * 255),
        "points (N, 2)": lambda: PointCloud(pts[:, :2], None),
        "points as text": lambda: PointCloud(np.full((10, 3), "x"), None),
        "a list of lists": lambda: [[0.0, 0.0, 0.0]] * 10,
        "None": lambda: None,
    }
    for _ in range(6):  # seeded: random fraction of NaN points (filtered by contract)
        frac = float(rng.uniform(0.05, 0.5))
        bad = pts.copy()
        bad[rng.random(len(pts)) < frac] = NAN
        clouds[f"{frac:.0%} NaN points"] = lambda b=bad: PointCloud(b, cols)
    cases: list[Case] = []
    nan_ok = {"% NaN points"}  # NaN points are filtered by default: a result may be fine

    def nan_check(reg: Any) -> None:
        if not reg.ok:
            raise Handled(f"ok=False: {reg.reason}")
        err = np.abs(reg.T - np.eye(4)).max()
        if err < 0.01:
            raise Handled(f"registered, |T - I| = {err:.1e}")
        raise SilentWrong(f"ok=True but |T - I| = {err:.3f} (the clouds are the same)")

    for label, make in clouds.items():
        chk = nan_check if any(s in label for s in nan_ok) else refused
        for side in ("source", "target"):

            def fn(make=make, side=side):
                c = make()
                return (
                    register(c, good, cfg, init=np.eye(4))
                    if side == "source"
                    else register(good, c, cfg, init=np.eye(4))
                )

            cases.append(Case("registration", f"register({side}={label}, init=I)", fn, check=chk))
    for label, init in {
        "init NaN": np.full((4, 4), NAN),
        "init 3x3": np.eye(3),
        "init scaled x2": np.diag([2.0, 2.0, 2.0, 1.0]),
        "init a reflection": np.diag([1.0, 1.0, -1.0, 1.0]),
        "init inf translation": np.array(
            [[1, 0, 0, INF], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]
        ),
    }.items():
        cases.append(
            Case(
                "registration",
                f"register(good, good, {label})",
                lambda init=init: register(good, good, cfg, init=init),
                check=refused,
            )
        )
    from mmpa.core.config import load_config

    for label, sets in {
        "voxel 0": ["coarse_voxel=0"],
        "voxel NaN": ["coarse_voxel=.nan"],
        "min_points -1": ["min_points=-1"],
        "nan_policy bogus": ["nan_policy=bogus"],
        "max_depth < min_depth": ["min_depth=2.0", "max_depth=1.0"],
    }.items():
        cases.append(
            Case(
                "registration",
                f"load_config(RegistrationConfig, --set {' '.join(sets)}) ({label})",
                lambda sets=sets: load_config(RegistrationConfig, None, sets),
            )
        )
    return cases


# ============================================================================ 10. task bundles


def bundle_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    from mmpa.tasks import read_bundle, write_bundle

    sys.path.insert(0, str(REPO / "tests"))
    from test_tasks import make_task

    d = tmp / "bundles"
    d.mkdir()
    master = write_bundle(make_task("valve", n_points=300, n_waypoints=20), d / "master")
    saved = read_bundle(master)
    doc = yaml.safe_load((master / "task.yaml").read_text())
    cases: list[Case] = []

    def same_as_saved(task: Any) -> None:
        try:
            _assert_same(saved, task)
        except AssertionError as e:
            raise SilentWrong(f"read back a different task: {e}") from None
        raise Handled("read back bit-identical")

    def copy_bundle() -> Path:
        b = d / f"b{len(cases)}"
        shutil.copytree(master, b)
        return b

    def add(label: str, b: Path) -> None:
        cases.append(Case("bundles", label, lambda b=b: read_bundle(b), check=same_as_saved))

    # task.yaml fields
    yleaves = [(p, v) for p, v in _leaves(doc)]
    for path, _ in _pick(rng, yleaves, 25):
        for v in _pick(rng, [*BAD_NUMBERS, None, True], 2):
            b = copy_bundle()
            _write(b / "task.yaml", _set(doc, path, v))
            add(f"task.yaml {_dotted(path)}={v!r}", b)
    for k in _pick(rng, list(doc), 10):
        b = copy_bundle()
        _write(b / "task.yaml", _drop(doc, (k,)))
        add(f"task.yaml without {k}", b)
    for k, v in [
        ("name", "../escape"),
        ("name", ""),
        ("name", 3),
        ("format_version", 99),
        ("format_version", "2"),
        ("created", "yesterday"),
        ("site", None),
        ("T_map_base_park", [[1, 0], [0, 1]]),
        ("q_sample", [0.0] * 5),
        ("meta", [1, 2]),
        ("header_sha256", "0" * 64),
    ]:
        b = copy_bundle()
        _write(b / "task.yaml", _set(doc, (k,), v))
        add(f"task.yaml {k}={v!r}", b)
    b = copy_bundle()
    (b / "task.yaml").write_text(_alias_bomb(8))
    add("task.yaml alias bomb", b)
    # data files: random byte flips, truncations, appended bytes, missing files
    for name in ("cloud.ply", "path.csv", "task.yaml"):
        raw = (master / name).read_bytes()
        for _ in range(8):
            b = copy_bundle()
            buf = bytearray(raw)
            off = int(rng.integers(0, len(buf)))
            buf[off] ^= int(rng.integers(1, 256))
            (b / name).write_bytes(bytes(buf))
            add(f"{name}: byte {off} flipped", b)
        for _ in range(4):
            b = copy_bundle()
            cut = int(rng.integers(0, len(raw)))
            (b / name).write_bytes(raw[:cut])
            add(f"{name}: truncated at byte {cut}", b)
        b = copy_bundle()
        (b / name).write_bytes(raw + b"\x00extra")
        add(f"{name}: bytes appended", b)
        b = copy_bundle()
        (b / name).unlink()
        add(f"{name}: missing", b)
        b = copy_bundle()
        (b / name).unlink()
        (b / name).mkdir()
        add(f"{name}: a directory", b)
        b = copy_bundle()
        (d / f"outside-{len(cases)}").write_bytes(raw)
        (b / name).unlink()
        (b / name).symlink_to(d / f"outside-{len(cases)}")
        add(f"{name}: a symbolic link out of the bundle", b)
        b = copy_bundle()
        os.truncate(b / name, 3 << 30)
        add(f"{name}: 3 GiB (sparse)", b)
    cases.append(Case("bundles", "bundle folder missing", lambda: read_bundle(d / "nope")))
    (d / "afile").write_text("x")
    cases.append(Case("bundles", "bundle path is a file", lambda: read_bundle(d / "afile")))
    cases.append(
        Case(
            "bundles",
            "write_bundle into a path under a file",
            lambda: write_bundle(saved, d / "afile" / "b"),
        )
    )
    cases.append(
        Case("bundles", "write_bundle over an existing bundle", lambda: write_bundle(saved, master))
    )
    return cases


def _assert_same(a: Any, b: Any) -> None:
    for f in ("name", "site", "robot_id", "created", "description", "meta", "format_version"):
        assert getattr(a, f) == getattr(b, f), f
    for f in ("T_map_base_park", "q_sample", "T_arm_base_camera"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    for f in ("t", "q", "T_arm_base_tool"):
        assert np.array_equal(getattr(a.path, f), getattr(b.path, f)), f"path.{f}"
    assert a.path.rate_hz == b.path.rate_hz, "rate_hz"
    if a.path.gripper is None:
        assert b.path.gripper is None, "gripper"
    else:
        assert b.path.gripper is not None and np.array_equal(a.path.gripper, b.path.gripper), (
            "gripper"
        )
    assert np.array_equal(a.cloud.points, b.cloud.points), "cloud.points"
    assert a.cloud.frame == b.cloud.frame, "cloud.frame"
    if a.cloud.colors is None:
        assert b.cloud.colors is None, "cloud.colors"
    else:
        assert b.cloud.colors is not None and np.array_equal(a.cloud.colors, b.cloud.colors), (
            "cloud.colors"
        )


# ============================================================================ 11. task store


def _integrity(p: Path) -> str:
    try:
        con = sqlite3.connect(f"file:{p}?mode=ro", uri=True)
        try:
            return str(con.execute("PRAGMA integrity_check").fetchone()[0])
        finally:
            con.close()
    except sqlite3.Error as e:
        return f"sqlite3: {e}"


def _poke(p: Path, off: int, data: bytes) -> None:
    raw = bytearray(p.read_bytes())
    raw[off : off + len(data)] = data
    p.write_bytes(bytes(raw))


def store_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    from mmpa.tasks import TaskStore, write_bundle

    sys.path.insert(0, str(REPO / "tests"))
    from test_tasks import make_task

    d = tmp / "store"
    d.mkdir()
    tasks = {
        "valve": make_task("valve", 0, n_points=200, n_waypoints=15),
        "cup": make_task("cup", 1, n_points=200, n_waypoints=15),
    }
    master = d / "master.db"
    with TaskStore(master) as s:
        for t in tasks.values():
            s.save(t)
    bundle = write_bundle(tasks["valve"], d / "valve-bundle")
    cases: list[Case] = []

    def copy_db() -> Path:
        p = d / f"s{len(cases)}.db"
        shutil.copy(master, p)
        return p

    def intact(p: Path, names: tuple[str, ...] = ("valve", "cup")) -> None:
        """``names`` must still load bit-identical and the file pass integrity_check."""
        ok = _integrity(p)
        if ok != "ok":
            raise DataLost(f"integrity_check: {ok}")
        try:
            with TaskStore(p, timeout=1.0) as s:
                for n in names:
                    _assert_same(tasks[n], s.load(n))
        except Exception as e:
            raise DataLost(
                f"a committed task is lost or changed: {type(e).__name__}: {e}"
            ) from None

    def unchanged(p: Path, before: str) -> Callable[[], None]:
        def check() -> None:
            if _digest(p) != before:
                raise DataLost("a read-only operation changed the database file")

        return check

    def reads(p: Path) -> Callable[[], Any]:
        def fn() -> Any:
            with TaskStore(p, timeout=1.0) as s:
                infos = s.list()
                loaded = {n: s.load(n) for n in ("valve", "cup")}
            return infos, loaded

        return fn

    def reads_ok(res: Any) -> None:
        infos, loaded = res
        for n, t in loaded.items():
            try:
                _assert_same(tasks[n], t)
            except AssertionError as e:
                raise SilentWrong(f"task {n!r} loaded with a different {e}") from None
        for info in infos:
            t = tasks[info.name]
            if info.n_points != len(t.cloud) or info.n_waypoints != len(t.path.t):
                raise SilentWrong(f"list() shows {info}")
        raise Handled("read back bit-identical")

    def add_corrupt(label: str, corrupt: Callable[[Path], None], fresh: bool = False) -> None:
        p = copy_db()
        corrupt(p)
        # a zero-length file is an empty SQLite database: mmpa creates its schema there
        after = None if fresh else unchanged(p, _digest(p))
        cases.append(Case("task store", label, reads(p), check=reads_ok, after=after))

    def sql(*stmts: str) -> Callable[[Path], None]:
        def f(p: Path) -> None:
            con = sqlite3.connect(p)
            for s_ in stmts:
                con.execute(s_)
            con.commit()
            con.close()

        return f

    # random bytes at random offsets (the fault destroys data; mmpa must not make it worse)
    size = master.stat().st_size
    for _ in range(30):
        off = int(rng.integers(0, size))
        n = int(rng.integers(1, 64))
        junk = bytes(rng.integers(0, 256, n, dtype=np.uint8))

        def smash(p: Path, off=off, junk=junk) -> None:
            raw = bytearray(p.read_bytes())
            raw[off : off + len(junk)] = junk
            p.write_bytes(bytes(raw[: len(p.read_bytes())]))

        add_corrupt(f"{len(junk)} random bytes at offset {off}", smash)
    for cut in sorted(int(x) for x in rng.integers(0, size, 5)):
        add_corrupt(
            f"file truncated at byte {cut}", lambda p, c=cut: p.write_bytes(p.read_bytes()[:c])
        )
    # found by tests/test_store_fuzz.py: invalid UTF-8 in a table name of the schema
    raw_master = master.read_bytes()
    for table in ("paths", "clouds"):
        at = raw_master.index(f"table{table}{table}".encode()) + len("table")
        add_corrupt(
            f"byte 0x80 over the schema's table name {table!r} (offset {at})",
            lambda p, at=at: _poke(p, at, b"\x80"),
        )
    add_corrupt("zero-length file", lambda p: p.write_bytes(b""), fresh=True)
    add_corrupt("text file", lambda p: p.write_text("not a database\n"))
    add_corrupt("header zeroed", lambda p: p.write_bytes(b"\0" * 100 + p.read_bytes()[100:]))
    # dropped tables / columns, and values of the wrong type in every column
    for t_ in ("tasks", "clouds", "paths", "schema_version"):
        add_corrupt(f"DROP TABLE {t_}", sql(f"DROP TABLE {t_}"))
    con = sqlite3.connect(master)
    cols = {
        t_: [r[1] for r in con.execute(f"PRAGMA table_info({t_})")]
        for t_ in ("tasks", "clouds", "paths")
    }
    con.close()
    for c in cols["tasks"]:
        if c != "name":
            add_corrupt(f"DROP COLUMN tasks.{c}", sql(f"ALTER TABLE tasks DROP COLUMN {c}"))
    bad_values = [
        "'abc'",
        "x'00ff'",
        "-1",
        "1e308",
        "0.5",
        "'[1, 2'",
        "'NaN'",
        "9223372036854775807",
    ]
    for t_, cs in cols.items():
        for c in cs:
            if c in ("name", "task"):
                continue
            for v in _pick(rng, bad_values, 3):
                where = "name = 'cup'" if t_ == "tasks" else "task = 'cup'"
                add_corrupt(
                    f"UPDATE {t_} SET {c} = {v} (task cup)",
                    sql(f"UPDATE {t_} SET {c} = {v} WHERE {where}"),
                )
    add_corrupt("DELETE the cloud row of cup", sql("DELETE FROM clouds WHERE task = 'cup'"))
    add_corrupt("schema_version 99", sql("INSERT INTO schema_version VALUES (99, 'x', 'y')"))
    for v in (-1, 0):
        add_corrupt(
            f"schema_version.version = {v}", sql(f"UPDATE schema_version SET version = {v}")
        )

    def names_are_text(names: Any) -> None:
        if all(isinstance(n, str) for n in names):
            raise Handled(f"names {names}")
        raise SilentWrong(f"names() returned {names!r}")

    for v in ("NULL", "x'01'"):
        p = copy_db()
        sql(f"UPDATE tasks SET name = {v} WHERE name = 'valve'")(p)

        def names(p: Path = p) -> Any:
            with TaskStore(p, timeout=1.0) as s:
                return s.names()

        cases.append(
            Case(
                "task store",
                f"UPDATE tasks SET name = {v} (task valve), then names()",
                names,
                check=names_are_text,
                after=unchanged(p, _digest(p)),
            )
        )
    add_corrupt(
        "rename valve to cup2 in tasks only",
        sql("PRAGMA foreign_keys = OFF", "UPDATE tasks SET name = 'cup2' WHERE name = 'valve'"),
    )

    # operations that must refuse and keep every committed task (data lost is mmpa's fault)
    def op(label: str, fn: Callable[[Path], Any], keep: tuple[str, ...] = ("valve", "cup")) -> None:
        p = copy_db()
        cases.append(
            Case("task store", label, lambda p=p: fn(p), after=lambda p=p: intact(p, keep))
        )

    def save(p: Path, task: Any, overwrite: bool = False) -> None:
        with TaskStore(p, timeout=1.0) as s:
            s.save(task, overwrite=overwrite)

    op(
        "save a task under a taken name",
        lambda p: save(p, make_task("valve", 5, n_points=50, n_waypoints=5)),
    )
    op("save a non-task (a dict)", lambda p: save(p, {"name": "x"}))
    op("save None", lambda p: save(p, None))
    for label, mutate in [
        ("import a bundle with a flipped cloud byte over valve (overwrite)", "cloud.ply"),
        ("import a bundle with a flipped path byte over valve (overwrite)", "path.csv"),
        ("import a bundle with an edited task.yaml over valve (overwrite)", "task.yaml"),
    ]:
        b = d / f"bad-{mutate}"
        shutil.copytree(bundle, b)
        raw = bytearray((b / mutate).read_bytes())
        raw[len(raw) // 2] ^= 0x55
        (b / mutate).write_bytes(bytes(raw))

        def imp(p: Path, b=b) -> None:
            with TaskStore(p, timeout=1.0) as s:
                s.import_bundle(b, overwrite=True)

        op(label, imp)

    def imp_missing(p: Path) -> None:
        with TaskStore(p, timeout=1.0) as s:
            s.import_bundle(d / "no-bundle", overwrite=True)

    op("import a missing bundle (overwrite)", imp_missing)

    def delete_unknown(p: Path) -> None:
        with TaskStore(p, timeout=1.0) as s:
            s.delete("nope")

    op("delete an unknown task", delete_unknown)
    for name in ["", "../x", None, 3]:

        def load_name(p: Path, name=name) -> Any:
            with TaskStore(p, timeout=1.0) as s:
                return s.load(name)

        op(f"load({name!r})", load_name)
    (d / "blocker").write_text("x")

    def export_under_file(p: Path) -> Any:
        with TaskStore(p, timeout=1.0) as s:
            return s.export("valve", d / "blocker" / "out")

    op("export into a folder under a file", export_under_file)

    def locked_save(p: Path) -> None:
        other = sqlite3.connect(p, isolation_level=None)
        other.execute("BEGIN EXCLUSIVE")
        try:
            save(p, make_task("new", 3, n_points=50, n_waypoints=5))
        finally:
            other.close()

    op("save while another process holds an exclusive lock", locked_save)

    def readonly_save(p: Path) -> None:
        os.chmod(p, 0o444)
        try:
            save(p, make_task("new", 3, n_points=50, n_waypoints=5))
        finally:
            os.chmod(p, 0o644)

    if os.geteuid() != 0:
        op("save into a read-only database file", readonly_save)

    def crash_mid_save(p: Path) -> None:
        """The process dies (SystemExit) while the overwrite's rows are half written."""
        import mmpa.tasks.store as store_mod

        real = store_mod.path_blobs

        def boom(*a: Any, **k: Any) -> Any:
            raise KeyboardInterrupt("simulated interrupt while saving")

        with TaskStore(p, timeout=1.0) as s:
            store_mod.path_blobs = boom
            try:
                s.save(make_task("valve", 9, n_points=50, n_waypoints=5), overwrite=True)
            finally:
                store_mod.path_blobs = real

    p_int = copy_db()

    def crash_case(p: Path = p_int) -> None:
        try:
            crash_mid_save(p)
        except KeyboardInterrupt as e:
            raise _Interrupted(str(e)) from None

    cases.append(
        Case(
            "task store",
            "KeyboardInterrupt during save(overwrite=True) of valve",
            crash_case,
            after=lambda: intact(p_int),
        )
    )
    # store paths
    (d / "adir.db").mkdir()
    cases.append(Case("task store", "store path is a directory", lambda: TaskStore(d / "adir.db")))
    cases.append(
        Case("task store", "store path under a file", lambda: TaskStore(d / "blocker" / "t.db"))
    )
    loop = d / "loop.db"
    loop.symlink_to(loop)
    cases.append(Case("task store", "store path is a symlink loop", lambda: TaskStore(loop)))
    huge = d / "huge.db"
    huge.write_bytes(b"")
    os.truncate(huge, 3 << 30)
    cases.append(
        Case("task store", "store file: 3 GiB of zeros (sparse)", lambda: TaskStore(huge).list())
    )
    for v in (-1.0, NAN, INF, "3"):
        cases.append(
            Case(
                "task store",
                f"TaskStore(timeout={v!r})",
                lambda v=v: TaskStore(copy_db(), timeout=v),
            )
        )
    return cases


# ============================================================================ 12. CLI


def cli_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    from typer.testing import CliRunner

    from mmpa.cli.main import app

    runner = CliRunner()
    d = tmp / "cli"
    d.mkdir()
    (d / "afile").write_text("x")
    (d / "bomb.yaml").write_text(_alias_bomb(8))
    (d / "garbage.db").write_bytes(bytes(range(256)) * 8)
    env = {
        "MMPA_TASKS_DB": str(d / "tasks.db"),
        "MUJOCO_GL": "osmesa",
        "PYOPENGL_PLATFORM": "osmesa",
    }
    blocker = d / "afile"
    in_process: list[list[str]] = [
        ["demo", "--seed", "-1"],
        ["demo", "--set", "errors.seed=-5"],
        ["demo", "--set", "errors.seed=.nan"],
        ["demo", "--set", "nosuchkey=1"],
        ["demo", "--set", "errors.profile=bogus"],
        ["demo", "--config", str(d / "bomb.yaml")],
        ["demo", "--config", str(d / "missing.yaml")],
        ["demo", "--profile", "bogus"],
        ["navigate", "--to", "1", "--timeout", "nan"],
        ["navigate", "--to", "1", "--timeout", "-5"],
        ["navigate", "--to", "1", "--timeout", "inf"],
        ["navigate", "--to", "99"],
        ["navigate", "--to", "1", "--method", "magic"],
        ["navigate", "--to", "1", "--reflectors", str(d / "bomb.yaml")],
        ["navigate", "--to", "1", "--out", str(blocker / "x")],
        ["map", "export", "--resolution", "nan"],
        ["map", "export", "--resolution", "-0.05"],
        ["map", "export", "--resolution", "1e9"],
        ["map", "export", "--out", str(blocker / "m" / "map.yaml")],
        ["map", "export", "--profile", "bogus"],
        ["run", "t", "--trial", "-1"],
        ["run", "nosuchtask"],
        ["run", "nosuchtask", "--db", str(d / "garbage.db")],
        ["teach", "bad/name"],
        ["tasks", "list", "--db", str(d / "garbage.db")],
        ["tasks", "list", "--db", str(blocker / "t.db")],
        ["tasks", "show", "nope"],
        ["tasks", "show", "nope", "--db", str(d)],
        ["tasks", "import", str(d / "missing-bundle")],
        ["tasks", "import", str(blocker)],
        ["tasks", "export", "nope", str(d / "out")],
        ["tasks", "delete", "nope", "--yes"],
        ["localize", str(d / "missing.mcap")],
        ["localize", str(blocker)],
        [
            "register",
            "--color1",
            str(d / "no.png"),
            "--depth1",
            str(d / "no.png"),
            "--color2",
            str(d / "no.png"),
            "--depth2",
            str(d / "no.png"),
            "--intrinsics",
            str(blocker),
        ],
        ["register", "--bag", str(d / "missing.mcap"), "--from", "nan", "--to", "1"],
        [
            "register",
            "--depth-scale",
            "-1",
            "--bag",
            str(d / "missing.mcap"),
            "--from",
            "0",
            "--to",
            "1",
        ],
        ["sweep", str(d / "missing-sweep.yaml")],
        ["sweep", str(d / "bomb.yaml")],
        ["experiment", "nosuch"],
        ["experiment", "ipe", "--seed", "-2"],
        ["calibrate", "reflectors", "--spacing", "nan"],
        ["calibrate", "reflectors", "--route", ""],
        ["--robot", str(d / "bomb.yaml"), "robot", "show"],
        ["--robot", str(d / "missing.yaml"), "robot", "show"],
        ["--log-level", "loud", "version"],
        ["sim", "snapshot", "--site", "99", "--out", str(d / "snap")],
        ["sim", "snapshot", "--out", str(blocker / "snap")],
    ]
    cases: list[Case] = []
    for args in in_process:

        def fn(args=args) -> Any:
            cwd = os.getcwd()
            os.chdir(d)
            try:
                return runner.invoke(app, args, env=env)
            finally:
                os.chdir(cwd)

        cases.append(Case("cli", "mmpa " + " ".join(args).replace(str(d), "$TMP"), fn, cli=True))
    # a few through the console script (a subprocess): what a user sees, tracebacks included
    subproc = [
        ["demo", "--seed", "-1"],
        ["map", "export", "--out", str(blocker / "m" / "map.yaml")],
        ["tasks", "list", "--db", str(d / "garbage.db")],
        ["tasks", "show", "nope", "--db", str(d)],
        ["--robot", str(d / "bomb.yaml"), "robot", "show"],
        ["navigate", "--to", "1", "--timeout", "nan"],
        ["localize", str(blocker)],
        ["sweep", str(d / "bomb.yaml")],
        ["tasks", "import", str(blocker)],
        ["register", "--bag", str(d / "missing.mcap"), "--from", "0", "--to", "1"],
    ]
    exe = str(Path(sys.executable).with_name("mmpa"))
    for args in subproc:

        def sp(args=args) -> Any:
            return subprocess.run(
                [exe, *args],
                cwd=d,
                env={**os.environ, **env},
                capture_output=True,
                text=True,
                timeout=CLI_LIMIT_S,
            )

        cases.append(Case("cli", "$ mmpa " + " ".join(args).replace(str(d), "$TMP"), sp, cli=True))
    return cases


# ============================================================================ 13. real data


def _rd_bag(path: Path, static: list[tuple[str, str, np.ndarray]], frames: list[str]) -> Path:
    """A small bag as a real robot records it: /map, /initialpose, /odom, one scan per frame
    in ``frames``, and ``static`` transforms (parent, child, 4x4) on /tf_static."""
    from mmpa.backends.bag import BagWriter
    from mmpa.backends.bag import messages as rm
    from mmpa.maps.occupancy import OccupancyGrid
    from mmpa.robot.interfaces import LaserScan, Odometry

    data = np.zeros((60, 60), np.int8)
    data[[0, -1], :] = data[:, [0, -1]] = 100
    n, a0 = 61, -np.pi / 2
    inc = np.pi / (n - 1)
    with BagWriter(path) as bag:
        bag.write("/map", rm.occupancy_grid(OccupancyGrid(data, 0.05), 0.0))
        if static:
            tfs = [rm.transform_stamped(0.0, a, b, T) for a, b, T in static]
            bag.write("/tf_static", rm.tf_message(tfs), 0.0)
        bag.write("/initialpose", rm.pose_cov_stamped(0.0, "map", [1.5, 1.5, 0.0], None))
        for t in (0.0, 0.1, 0.2, 0.3):
            bag.write(
                "/odom", rm.odometry(Odometry(np.zeros(3), np.zeros(2), t, "odom", "base_link"))
            )
        for i, f in enumerate(frames):
            sc = LaserScan(
                a0,
                a0 + inc * (n - 1),
                inc,
                0.0,
                0.1,
                0.05,
                10.0,
                np.full(n, 1.2),
                np.zeros(n),
                0.05 + 0.1 * i,
                f,
            )
            bag.write("/scan", rm.laser_scan(sc))
    return path


class _FakeArm:
    """An ``Arm`` that records its calls (TMMA cases: did anything move?)."""

    def __init__(self, q: np.ndarray) -> None:
        self.q, self.calls = np.asarray(q, float).copy(), []

    def joint_positions(self) -> np.ndarray:
        return self.q.copy()

    def move_joints(self, q: Any, duration: float | None = None) -> None:
        self.calls.append("move_joints")
        self.q = np.asarray(q, float).copy()

    def follow(self, t: Any, q: Any, record_hz: float | None = None) -> None:
        self.calls.append("follow")
        self.q = np.asarray(q, float)[-1].copy()


def real_data_cases(tmp: Path, rng: np.random.Generator) -> list[Case]:
    """Issue 32: a twin value standing in for a real one, values wrapped by a cast, a damaged
    task listed as fine, a TMMA replay of joints that are not the taught tool path, a path
    slowed down without a word (docs/silent_defaults.md)."""
    import logging

    from typer.testing import CliRunner

    from mmpa.apps.localize import LocalizeConfig, run_localize
    from mmpa.backends.bag import messages as rm
    from mmpa.backends.twin.scene import load_scene, parse_scene
    from mmpa.cli.main import app
    from mmpa.core.geometry import make_T
    from mmpa.maps.occupancy import OccupancyGrid
    from mmpa.missions.teach_repeat import replay_tmma
    from mmpa.robot.description import CameraIntrinsics, RobotDescription
    from mmpa.robot.interfaces import PointCloud
    from mmpa.robot.kinematics import fk
    from mmpa.tasks import Task, TaskStore, ToolPath

    d = tmp / "real"
    d.mkdir()
    runner = CliRunner()
    cases: list[Case] = []
    rear = make_T(np.diag([-1.0, -1.0, 1.0]), [-0.2, 0.02, 0.3])  # 0.5 m, pi from the twin's
    # ---- the lidar mount
    bags = {
        "no /tf_static": ([], ["laser"]),
        "/tf_static for another frame (base_link -> camera_link)": (
            [("base_link", "camera_link", rear)],
            ["base_laser_link"],
        ),
        "/tf_static base_link -> laser, scans in base_laser_link": (
            [("base_link", "laser", rear)],
            ["base_laser_link"],
        ),
        "scans from two frames": (
            [("base_link", "front", rear), ("base_link", "rear", rear)],
            ["front", "rear"],
        ),
        "a scan without frame_id": ([("base_link", "laser", rear)], [""]),
    }
    for i, (label, (static, frames)) in enumerate(bags.items()):
        b = _rd_bag(d / f"b{i}.mcap", static, frames)
        out = d / f"loc{i}"
        cases.append(
            Case(
                "real data",
                f"localize: {label}",
                lambda b=b, out=out: run_localize(b, out, cfg=LocalizeConfig(method="amcl")),
            )
        )
    for label, static in {
        "mount only under base_laser_link (a chain via a plate)": [
            ("base_link", "plate", make_T(np.eye(3), [-0.15, 0.02, 0.3])),
            ("plate", "base_laser_link", make_T(np.diag([-1.0, -1.0, 1.0]), [-0.05, 0, 0])),
        ],
        "mount recorded laser -> base_link (inverse)": [
            ("/base_laser_link", "/base_link", np.linalg.inv(rear))
        ],
    }.items():
        b = _rd_bag(d / f"b{len(cases)}.mcap", static, ["base_laser_link"])
        out = d / f"loc{len(cases)}"

        def check(s: Any) -> None:
            got = np.asarray(s["laser_pose"])
            if s.get("laser_pose_source") != "tf_static" or not np.allclose(got[:2], [-0.2, 0.02]):
                raise SilentWrong(f"mount {got.tolist()} from {s.get('laser_pose_source')!r}")
            raise Handled(f"the bag's mount {got.round(4).tolist()}, laser_pose_source tf_static")

        cases.append(
            Case(
                "real data",
                f"localize: {label}",
                lambda b=b, out=out: run_localize(b, out, cfg=LocalizeConfig(method="amcl")),
                check,
            )
        )
    b = _rd_bag(d / "cli.mcap", [], ["base_laser_link"])
    cases.append(
        Case(
            "real data",
            "mmpa localize --bag (no mount anywhere)",
            lambda: runner.invoke(app, ["localize", "--bag", str(b), "--out", str(d / "c")]),
            cli=True,
        )
    )
    # ---- map cells
    for label, data in {
        "200 (int64)": np.full((2, 2), 200),
        "101 (int8)": np.full((2, 2), 101, np.int8),
        "-2": np.array([[0, -2]]),
        "50.7": np.array([[0.0, 50.7]]),
        "NaN": np.array([[np.nan]]),
        "inf": np.array([[np.inf]]),
        "255 (uint8, raw unknown)": np.array([[255]], np.uint8),
        "-128 (int8)": np.array([[-128]], np.int8),
        "strings": np.array([["a"]]),
        "random int16 beyond 100": rng.integers(101, 30000, (3, 3)).astype(np.int16),
    }.items():
        cases.append(
            Case(
                "real data",
                f"OccupancyGrid cells {label}",
                lambda data=data: OccupancyGrid(data, 0.05).data,
            )
        )
    # ---- scene seed
    doc = load_scene().model_dump(mode="json")
    for v in (-1, -(2**40), True, 1.5, "7", None):
        bad = {**doc, "seed": v}
        cases.append(
            Case("real data", f"scene seed {v!r}", lambda bad=bad: parse_scene(bad, "s.yaml"))
        )
    neg = _write(d / "neg_seed.yaml", {**doc, "seed": -1})
    cases.append(
        Case(
            "real data",
            "mmpa sim snapshot --set scene=<seed -1>",
            lambda: runner.invoke(
                app, ["sim", "snapshot", "--set", f"scene={neg}", "--out", str(d / "snap")]
            ),
            cli=True,
        )
    )
    # ---- the task store: a damaged task in the listing
    sys.path.insert(0, str(REPO / "tests"))
    from test_tasks import make_task

    master = d / "master.db"
    with TaskStore(master) as st:
        st.save(make_task("valve", 0, n_points=200, n_waypoints=15))
        st.save(make_task("cup", 1, n_points=200, n_waypoints=15))
    for sql in (
        "DELETE FROM clouds WHERE task = 'valve'",
        "DELETE FROM paths WHERE task = 'valve'",
        "UPDATE clouds SET ply = substr(ply, 1, length(ply) - 1) WHERE task = 'valve'",
        "UPDATE clouds SET ply = substr(ply, 1, length(ply) / 2) WHERE task = 'valve'",
        "UPDATE clouds SET ply = CAST(ply || x'00' AS BLOB) WHERE task = 'valve'",
        "UPDATE clouds SET ply = ply || x'00' WHERE task = 'valve'",  # || gives text
        "UPDATE clouds SET ply = CAST(ply AS TEXT) WHERE task = 'valve'",
        "UPDATE paths SET q = substr(q, 1, length(q) - 48) WHERE task = 'valve'",
        "UPDATE paths SET gripper = x'00' WHERE task = 'valve'",
        "UPDATE paths SET T_arm_base_tool = 1 WHERE task = 'valve'",
    ):
        db = d / f"t{len(cases)}.db"
        shutil.copy(master, db)
        con = sqlite3.connect(db)
        con.execute(sql)
        con.commit()
        con.close()
        cases.append(
            Case("real data", f"tasks list after: {sql}", lambda db=db: TaskStore(db).list())
        )
        cases.append(
            Case(
                "real data",
                f"mmpa tasks list after: {sql}",
                lambda db=db: runner.invoke(app, ["tasks", "list", "--db", str(db)]),
                cli=True,
            )
        )
    # ---- TMMA: joints vs tool path, and slowing down
    rob = RobotDescription()
    tcp = rob.gripper.T_flange_tcp
    home = np.array(rob.arm.home)
    q = np.tile(home, (20, 1))
    q[10:, 0] += 1.5

    def task(qq: np.ndarray, T: np.ndarray) -> Task:
        cloud = PointCloud(np.zeros((10, 3)), None)
        return Task(
            "t",
            "0",
            np.eye(4),
            qq[0],
            np.eye(4),
            cloud,
            ToolPath(np.arange(len(qq)) * 0.02, qq, T, 50.0),
        )

    def tmma(tk: Task, tool: np.ndarray) -> Any:
        arm = _FakeArm(tk.path.q[0])
        try:
            return replay_tmma(tk, RobotDevices(rob, arm=arm), T_flange_tool=tool)
        except MMPAError:
            if arm.calls:
                raise SilentWrong(f"refused after the arm moved: {arm.calls}") from None
            raise

    still = np.tile(home, (20, 1))
    for label, tk, tool in (
        ("joint 1 jumps 1.5 rad, tool path does not", task(q, fk(rob.arm.dh, still, tcp)), tcp),
        ("tool path of the flange, replayed with the TCP", task(q, fk(rob.arm.dh, q)), tcp),
        (
            "joint 6 off by 0.2 rad all along",
            task(still + np.r_[0, 0, 0, 0, 0, 0.2], fk(rob.arm.dh, still, tcp)),
            tcp,
        ),
        (
            "tool path of random joints",
            task(still, fk(rob.arm.dh, still + rng.normal(0, 0.3, (20, 6)), tcp)),
            tcp,
        ),
    ):
        cases.append(Case("real data", f"TMMA: {label}", lambda tk=tk, tool=tool: tmma(tk, tool)))

    def slowed() -> Any:
        rec: list[str] = []
        h = logging.Handler()
        h.emit = lambda r: rec.append(r.getMessage())  # type: ignore[method-assign]
        log = logging.getLogger("mmpa")
        log.addHandler(h)
        old = log.level
        log.setLevel(logging.WARNING)
        try:
            path, _ = tmma(task(q, fk(rob.arm.dh, q, tcp)), tcp)
        finally:
            log.removeHandler(h)
            log.setLevel(old)
        return path, rec

    def check_slowed(res: Any) -> None:
        path, rec = res
        said = [m for m in rec if "slowed" in m]
        if path.time_scale > 1 and said:
            raise Handled(f"time_scale {path.time_scale:.2f}, warned: {said[0][:90]}")
        raise SilentWrong(f"time_scale {path.time_scale:.2f}, warnings {rec}")

    cases.append(
        Case("real data", "TMMA: joint 1 taught 1.5 rad in 20 ms (too fast)", slowed, check_slowed)
    )
    # ---- camera info
    k = CameraIntrinsics(fx=600.0, fy=600.0, cx=320.0, cy=240.0)
    msg = rm.camera_info(k, 0.0, "cam")
    for label, change in {
        "K all zero (uncalibrated driver)": {"k": np.zeros(9)},
        "fx NaN": {"k": np.r_[np.nan, 0, 320, 0, 600, 240, 0, 0, 1.0]},
        "fy negative": {"k": np.r_[600, 0, 320, 0, -600, 240, 0, 0, 1.0]},
        "width 0": {"width": 0},
    }.items():
        bad_msg = dataclasses.replace(msg, **change)
        cases.append(
            Case("real data", f"camera info: {label}", lambda m=bad_msg: rm.from_camera_info(m))
        )
    return cases


# ============================================================================ running


class _Interrupted(Exception):  # noqa: N818
    """A KeyboardInterrupt simulated inside a case (the case is judged by its ``after``)."""


CLASSES: dict[str, Callable[[Path, np.random.Generator], list[Case]]] = {
    "yaml": yaml_cases,
    "maps": map_cases,
    "reflector maps": reflector_map_cases,
    "scenes": scene_cases,
    "robot files": robot_cases,
    "config overrides": config_cases,
    "localizers": localizer_cases,
    "joints": joint_cases,
    "registration": registration_cases,
    "bundles": bundle_cases,
    "task store": store_cases,
    "cli": cli_cases,
    "real data": real_data_cases,
}


def _short(x: object, n: int = 300) -> str:
    s = " ".join(str(x).split())
    return s if len(s) <= n else s[: n - 3] + "..."


def _message(out: str) -> str:
    """The line of a CLI's output that says what was wrong."""
    lines = [ln.strip(" │╭╰─") for ln in out.strip().splitlines() if ln.strip(" │╭╰─")]
    for ln in lines:
        if any(k in ln.lower() for k in ("error", "invalid", "must", "missing")):
            return _short(ln)
    return _short(lines[-1]) if lines else ""


def _judge_cli(res: Any) -> tuple[str, str]:
    if isinstance(res, subprocess.CompletedProcess):
        out = (res.stdout or "") + (res.stderr or "")
        if "Traceback" in out:
            return "traceback", f"exit {res.returncode}: {_short(out[-600:])}"
        if res.returncode == 0:
            return "silent wrong", f"exit 0: {_short(out)}"
        return "clear", f"exit {res.returncode}: {_message(out)}"
    out = res.output or ""
    exc = res.exception
    if "Traceback" in out:
        return "traceback", f"exit {res.exit_code}: {_short(out[-600:])}"
    if exc is not None and not isinstance(exc, (SystemExit, MMPAError, OSError)):
        tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)[-3:])
        return "traceback", f"{type(exc).__name__}: {_short(exc)} | {_short(tb, 400)}"
    if res.exit_code == 0:
        return "silent wrong", f"exit 0: {_short(out)}"
    msg = _message(out) if out.strip() else f"{type(exc).__name__}: {_short(exc)}"
    return "clear", f"exit {res.exit_code}: {msg}"


def run_case(case: Case) -> dict[str, Any]:
    limit = CLI_LIMIT_S + 10 if case.cli else CASE_LIMIT_S

    def on_alarm(signum: int, frame: Any) -> None:
        raise _Hang()

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, limit)
    t0 = time.perf_counter()
    outcome, detail = "", ""
    try:
        try:
            res = case.fn()
        except subprocess.TimeoutExpired:
            outcome, detail = "hang", f"no exit within {CLI_LIMIT_S:g} s"
        except MMPAError as e:
            outcome, detail = "clear", f"{type(e).__name__}: {_short(e)}"
        except _Interrupted as e:
            outcome, detail = "clear", f"interrupted ({e}); judged by the store afterwards"
        except _Hang:
            raise
        except Exception as e:
            tb = traceback.extract_tb(e.__traceback__)
            where = f"{Path(tb[-1].filename).name}:{tb[-1].lineno} {tb[-1].name}" if tb else ""
            outcome, detail = (
                "traceback",
                f"{type(e).__module__}.{type(e).__name__}: {_short(e)} [at {where}]",
            )
        else:
            if case.cli:
                outcome, detail = _judge_cli(res)
            elif case.check is None:
                outcome, detail = "silent wrong", f"accepted, returned {_short(repr(res), 160)}"
            else:
                try:
                    case.check(res)
                    outcome, detail = "silent wrong", f"accepted, returned {_short(repr(res), 160)}"
                except Handled as h:
                    outcome, detail = "handled", str(h)
                except SilentWrong as w:
                    outcome, detail = "silent wrong", str(w)
        if case.after is not None:
            try:
                case.after()
            except DataLost as e:
                outcome, detail = "data lost", f"{e} (operation: {outcome}: {detail})"
            except SilentWrong as e:
                outcome, detail = "silent wrong", str(e)
    except _Hang:
        outcome, detail = "hang", f"still running after {limit:g} s"
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    return {
        "class": case.cls,
        "case": case.name,
        "outcome": outcome,
        "detail": detail,
        "seconds": round(time.perf_counter() - t0, 3),
    }


def _worker(cls: str, seed: int, tmp: str, conn: Any) -> None:
    """Build and run one class's cases in this (forked) process, reporting each result."""
    os.environ["MMPA_TASKS_DB"] = str(Path(tmp) / "default-tasks.db")  # never the user's store
    rng = np.random.default_rng([seed, list(CLASSES).index(cls)])
    try:
        cases = CLASSES[cls](Path(tmp), rng)
    except Exception:
        conn.send(("error", traceback.format_exc()))
        return
    conn.send(("plan", [c.name for c in cases]))
    for c in cases:
        conn.send(("result", run_case(c)))
    conn.send(("done", None))


def run_class(cls: str, seed: int) -> list[dict[str, Any]]:
    ctx = mp.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)
    with tempfile.TemporaryDirectory(prefix=f"audit-{cls.replace(' ', '-')}-") as tmp:
        proc = ctx.Process(target=_worker, args=(cls, seed, tmp, child), daemon=True)
        proc.start()
        child.close()
        plan: list[str] = []
        results: list[dict[str, Any]] = []
        watchdog = CLI_LIMIT_S + 60 if cls == "cli" else CASE_LIMIT_S + 60
        build_limit = 300.0
        while True:
            if not parent.poll(build_limit if not plan else watchdog):
                proc.kill()
                i = len(results)
                if plan and i < len(plan):
                    results.append(
                        {
                            "class": cls,
                            "case": plan[i],
                            "outcome": "hang",
                            "detail": "the worker stopped answering; killed",
                            "seconds": watchdog,
                        }
                    )
                    for name in plan[i + 1 :]:
                        results.append(
                            {
                                "class": cls,
                                "case": name,
                                "outcome": "not run",
                                "detail": "after a hang",
                                "seconds": 0.0,
                            }
                        )
                break
            try:
                kind, payload = parent.recv()
            except EOFError:  # the worker died (a crash in C code is a traceback to a user)
                i = len(results)
                code = proc.exitcode
                if plan and i < len(plan):
                    results.append(
                        {
                            "class": cls,
                            "case": plan[i],
                            "outcome": "traceback",
                            "detail": f"the process died (exit code {code})",
                            "seconds": 0.0,
                        }
                    )
                    for name in plan[i + 1 :]:
                        results.append(
                            {
                                "class": cls,
                                "case": name,
                                "outcome": "not run",
                                "detail": "after a crash",
                                "seconds": 0.0,
                            }
                        )
                break
            if kind == "error":
                raise RuntimeError(f"building the {cls} cases failed:\n{payload}")
            if kind == "plan":
                plan = payload
            elif kind == "result":
                results.append(payload)
            else:
                break
        proc.join(5)
    return results


def table(results: list[dict[str, Any]]) -> str:
    cols = ("tried", *OUTCOMES)
    rows = []
    for cls in [*dict.fromkeys(r["class"] for r in results), "total"]:
        rs = results if cls == "total" else [r for r in results if r["class"] == cls]
        counts = [len(rs)] + [sum(r["outcome"] == o for r in rs) for o in OUTCOMES]
        rows.append((cls, *counts))
    w = max(len(r[0]) for r in rows)
    head = f"| {'class':<{w}} | " + " | ".join(f"{c:>12}" for c in cols) + " |"
    sep = "|" + "-" * (w + 2) + "|" + "|".join("-" * 14 for _ in cols) + "|"
    lines = [head, sep]
    for r in rows:
        lines.append(f"| {r[0]:<{w}} | " + " | ".join(f"{c:>12}" for c in r[1:]) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, help="write every case's result as JSON here")
    ap.add_argument("--only", help="comma-separated classes: " + ", ".join(CLASSES))
    ap.add_argument("--seed", type=int, default=22)
    args = ap.parse_args(argv)
    classes = list(CLASSES) if not args.only else [c.strip() for c in args.only.split(",")]
    unknown = [c for c in classes if c not in CLASSES]
    if unknown:
        ap.error(f"unknown class(es) {unknown}; valid: {', '.join(CLASSES)}")
    t0 = time.perf_counter()
    results: list[dict[str, Any]] = []
    for cls in classes:
        t1 = time.perf_counter()
        rs = run_class(cls, args.seed)
        results.extend(rs)
        print(f"{cls}: {len(rs)} cases in {time.perf_counter() - t1:.1f} s", flush=True)
    print()
    print(table(results))
    bad = [r for r in results if r["outcome"] not in ("clear", "handled")]
    print(f"\n{len(bad)} case(s) not refused clearly:")
    for r in bad:
        print(f"- [{r['class']}] {r['outcome']}: {r['case']}\n    -> {r['detail']}")
    print(f"\nwall time {time.perf_counter() - t0:.1f} s (seed {args.seed})")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(
            json.dumps({"seed": args.seed, "table": table(results), "results": results}, indent=1)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
