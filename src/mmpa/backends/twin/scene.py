"""The scene file: one YAML document describes the simulated world.

The MuJoCo model is generated from it and from the robot description (``mmpa.backends.twin.mjcf``);
nobody edits XML by hand. Positions are metres in the ``map`` frame; angles in the file are
degrees (fields end in ``_deg``) because people write this file. Desk items are placed in
their desk's top-surface frame (x along the desk length, y along its depth, z up).

A malformed file fails with :class:`mmpa.core.errors.ConfigError` naming the field, before anything
reaches MuJoCo: every number must be finite, sizes positive, colours in [0, 1], reflectors
apart (their cylinders may not overlap). The YAML is read through :mod:`mmpa.core.yamlio` (no
aliases, bounded size).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from mmpa.core.errors import ConfigError, UnknownNameError
from mmpa.core.geometry import Array, quat_xyzw_to_R, wrap_angle
from mmpa.core.yamlio import load_yaml

__all__ = [
    "FIXED_KINDS",
    "DeskItem",
    "FiducialArtifact",
    "GraspObject",
    "Reflectors",
    "SceneConfig",
    "SiteConfig",
    "SpeedBump",
    "Wall",
    "Workbench",
    "default_scene_path",
    "load_scene",
]

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]


class _Model(BaseModel):
    # allow_inf_nan=False: a NaN or infinite number anywhere in the scene is refused here;
    # MuJoCo would accept it and fail later (or silently place a body at NaN)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _positive(v: tuple[float, ...] | None, what: str = "size") -> tuple[float, ...] | None:
    """Every entry of a size > 0 (m)."""
    if v is not None and any(x <= 0 for x in v):
        raise ValueError(f"every {what} entry must be > 0 m, got {tuple(v)}")
    return v


def _colour(v: tuple[float, ...] | None) -> tuple[float, ...] | None:
    """An RGB colour with each channel in [0, 1]."""
    if v is not None and any(not 0.0 <= x <= 1.0 for x in v):
        raise ValueError(f"colour channels must be in [0, 1], got {tuple(v)}")
    return v


class Wall(_Model):
    """A straight wall segment from ``start`` to ``end`` (map x, y)."""

    start: Vec2
    end: Vec2
    thickness: float = Field(0.1, gt=0)
    height: float = Field(1.5, gt=0)

    @model_validator(mode="after")
    def _length(self) -> Wall:
        if np.hypot(self.end[0] - self.start[0], self.end[1] - self.start[1]) < 1e-3:
            raise ValueError("wall start and end coincide")
        return self


class Reflectors(_Model):
    """Laser reflectors: vertical cylinders wrapped in retroreflective tape (paper 001)."""

    radius: float = Field(0.04, gt=0)
    height: float = Field(1.2, gt=0)
    positions: list[Vec2]

    @field_validator("positions")
    @classmethod
    def _at_least_three(cls, v: list[Vec2]) -> list[Vec2]:
        if len(v) < 3:
            raise ValueError(f"need at least 3 reflectors for trilateration, got {len(v)}")
        return v

    @model_validator(mode="after")
    def _apart(self) -> Reflectors:
        p = np.asarray(self.positions, dtype=float)
        d = np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1])
        i, j = np.nonzero(np.triu(d < 2 * self.radius, k=1))
        if len(i):
            a, b = int(i[0]), int(j[0])
            what = "the same position as" if d[a, b] < 1e-6 else "overlapping"
            raise ValueError(
                f"reflector {b} at {self.positions[b]} is {what} reflector {a} at "
                f"{self.positions[a]} (centres {d[a, b]:.4g} m apart; cylinders of radius "
                f"{self.radius} m need >= {2 * self.radius:.4g} m)"
            )
        return self


class SiteConfig(_Model):
    """A work site: the base_link park pose (paper 000 §4.2 gives position + quaternion)."""

    position: Vec3
    orientation_xyzw: tuple[float, float, float, float]
    speed_bump: bool = False
    workbench: str | None = None
    description: str = ""

    @field_validator("orientation_xyzw")
    @classmethod
    def _unit(cls, q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
        n = float(np.linalg.norm(q))
        if not 0.9 < n < 1.1:
            raise ValueError(f"orientation quaternion must be unit length, |q| = {n:.3f}")
        return tuple(float(x) / n for x in q)  # type: ignore[return-value]

    @property
    def yaw(self) -> float:
        """Heading (rad) of the park pose."""
        R = quat_xyzw_to_R(self.orientation_xyzw)
        return float(np.arctan2(R[1, 0], R[0, 0]))

    @property
    def pose2d(self) -> Array:
        """``[x, y, yaw]`` of the park pose."""
        return np.array([self.position[0], self.position[1], self.yaw])


class SpeedBump(_Model):
    """A triangular-prism speed bump (paper 000 Fig. 6d: 1000 x 350 x 50 mm).

    ``center`` and ``yaw_deg`` place its ridge line; ``length`` runs along the ridge.
    """

    center: Vec2
    yaw_deg: float = 0.0
    length: float = Field(1.0, gt=0)
    width: float = Field(0.35, gt=0)
    height: float = Field(0.05, gt=0)


ItemKind = Literal[
    "valve_container",
    "cup",
    "bottle",
    "small_bottle",
    "logo_tape",
    "letter_tape",
    "backboard",
    "reagent_bottle",
    "dropper",
    "waste_container",
    "test_tube_stand",
    "box",
    "dot",
    "poster",
]


#: kinds that never move between teaching and repeating: the backboard and the task's target
FIXED_KINDS = frozenset({"backboard", "dot"})

#: (fewest, most) entries of a desk item's ``size`` that ``mmpa.backends.twin.mjcf`` reads
_DESK_ITEM_SIZE_LEN: dict[str, tuple[int, int | None]] = {
    "backboard": (3, 3),
    "box": (3, 3),
    "poster": (2, None),
    "logo_tape": (2, None),
    "letter_tape": (2, None),
    "valve_container": (2, None),
    "cup": (2, None),
    "bottle": (2, 2),
    "small_bottle": (2, 2),
    "reagent_bottle": (2, 2),
}


class DeskItem(_Model):
    """Something on a desk, in the desk-top frame.

    ``free``: a physics free body (it can be pushed, grasped, knocked over).
    ``loose``: a thing a person moves while using the bench (cups, bottles, droppers), as
    opposed to a fixture (containers plumbed in, stands, backboards, tapes stuck on the top,
    the task's target). Loose items are their own bodies in the model, so the scene change
    between teaching and repeating (:mod:`mmpa.backends.twin.scene_change`, error model v2) can
    nudge
    them; a loose item need not be ``free``. Backboards and ``dot`` targets cannot be loose.
    """

    kind: ItemKind
    name: str | None = None
    xy: Vec2
    yaw_deg: float = 0.0
    size: tuple[float, ...] | None = None  # kind-specific; defaults in mjcf
    color: tuple[float, float, float] | None = None  # RGB in [0, 1]; None: seeded random
    free: bool = False
    loose: bool = False
    text: str | None = None  # for letter tapes; None: seeded random letters

    @field_validator("size")
    @classmethod
    def _size_positive(cls, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
        return _positive(v)

    @field_validator("color")
    @classmethod
    def _color_range(cls, v: Vec3 | None) -> Vec3 | None:
        return _colour(v)  # type: ignore[return-value]

    @model_validator(mode="after")
    def _fixed_kinds_stay(self) -> DeskItem:
        if self.loose and self.kind in FIXED_KINDS:
            raise ValueError(f"a {self.kind} never moves: it cannot be loose")
        need = _DESK_ITEM_SIZE_LEN.get(self.kind, (1, None))
        if self.size is not None and not (
            need[0] <= len(self.size) and (need[1] is None or len(self.size) <= need[1])
        ):
            n = f"{need[0]}" if need[0] == need[1] else f"{need[0]} or more"
            raise ValueError(f"a {self.kind} size has {n} entries, got {len(self.size)}")
        return self


class Workbench(_Model):
    """A desk in front of a work site with the items of paper 000's Site 1 / Site 2."""

    name: str
    center: Vec2
    yaw_deg: float = 0.0
    size: Vec3 = (1.2, 0.6, 0.72)  # length, depth, height
    top_color: Vec3 | None = None  # RGB in [0, 1] for a plain top; None: wood texture
    items: list[DeskItem] = Field(default_factory=list)

    @field_validator("size")
    @classmethod
    def _size_positive(cls, v: Vec3) -> Vec3:
        return _positive(v)  # type: ignore[return-value]

    @field_validator("top_color")
    @classmethod
    def _color_range(cls, v: Vec3 | None) -> Vec3 | None:
        return _colour(v)  # type: ignore[return-value]

    def item_name(self, j: int) -> str:
        """The model name of item ``j``: its ``name``, else ``<bench>_<kind>_<j>``."""
        item = self.items[j]
        return item.name or f"{self.name}_{item.kind}_{j}"

    @model_validator(mode="after")
    def _items_on_desk(self) -> Workbench:
        lx, ly = self.size[0] / 2, self.size[1] / 2
        for i, it in enumerate(self.items):
            if abs(it.xy[0]) > lx or abs(it.xy[1]) > ly:
                raise ValueError(
                    f"item {i} ({it.kind}) at {it.xy} lies off the {self.size[0]} x "
                    f"{self.size[1]} m desk top"
                )
        return self


class GraspObject(_Model):
    """A graspable free body (paper 001 Fig. 11 objects).

    ``size``: cube (half edge,), ball (radius,), bottle/cup/stick (radius, half height).
    ``lying``: a cylinder lying on its side (axis horizontal, along the body x axis).
    ``glossy``: specular plastic/glass look instead of matte. ``label``/``cap``: an extra
    colored band around the middle / a cap on top of a cylinder (looks only, no collision).
    """

    name: str
    kind: Literal["cube", "ball", "bottle", "cup", "stick"]
    position: Vec3
    size: tuple[float, ...]
    color: tuple[float, float, float]
    mass: float = Field(0.1, gt=0)
    lying: bool = False
    glossy: bool = False
    label: tuple[float, float, float] | None = None
    cap: tuple[float, float, float] | None = None

    @field_validator("color", "label", "cap")
    @classmethod
    def _color_range(cls, v: Vec3 | None) -> Vec3 | None:
        return _colour(v)  # type: ignore[return-value]

    @field_validator("size")
    @classmethod
    def _size_positive(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        return _positive(v)  # type: ignore[return-value]

    @model_validator(mode="after")
    def _size_fits_kind(self) -> GraspObject:
        need = 1 if self.kind in ("cube", "ball") else 2
        if len(self.size) != need:
            what = "(half edge,)" if self.kind == "cube" else "(radius,)"
            if need == 2:
                what = "(radius, half height)"
            raise ValueError(f"a {self.kind} size is {what}, got {len(self.size)} entries")
        return self


class FiducialArtifact(_Model):
    """Paper 002 calibration artifact: retroreflectors at the bottom of collimator tubes.

    ``fiducials`` are the (x, y) of Table 1 in the artifact frame, which sits at ``origin``
    (map x, y) with heading ``yaw_deg`` (the frame the base starts its pass in).
    """

    origin: Vec2
    yaw_deg: float = 0.0
    plate_height: float = Field(0.10, ge=0)
    tube_inner_diameter: float = Field(0.0127, gt=0)
    tube_height: float = Field(0.0667, gt=0)
    tube_wall: float = Field(0.002, gt=0)
    fiducials: list[Vec2]


class SceneConfig(_Model):
    """The whole world."""

    name: str
    seed: int = Field(0, ge=0, strict=True)  # procedural textures, item colours (numpy: >= 0)
    floor_size: Vec2 = (30.0, 20.0)
    floor_center: Vec2 = (0.0, 0.0)
    walls: list[Wall]
    reflectors: Reflectors

    @field_validator("floor_size")
    @classmethod
    def _floor_positive(cls, v: Vec2) -> Vec2:
        return _positive(v)  # type: ignore[return-value]

    sites: dict[str, SiteConfig]
    speed_bump: SpeedBump | None = None
    workbenches: list[Workbench] = Field(default_factory=list)
    grasp_desk: Workbench | None = None
    grasp_objects: list[GraspObject] = Field(default_factory=list)
    fiducial_artifact: FiducialArtifact | None = None

    @model_validator(mode="after")
    def _references(self) -> SceneConfig:
        benches = {w.name for w in self.workbenches}
        for name, site in self.sites.items():
            if site.workbench is not None and site.workbench not in benches:
                raise ValueError(
                    f"site {name!r} names workbench {site.workbench!r}; defined: {sorted(benches)}"
                )
            if site.speed_bump and self.speed_bump is None:
                raise ValueError(f"site {name!r} wants a speed bump but none is defined")
        names = [o.name for o in self.grasp_objects]
        if len(set(names)) != len(names):
            raise ValueError("grasp object names must be unique")
        return self

    def site(self, name: str | int) -> SiteConfig:
        """The site called ``name``; unknown names list the valid ones."""
        key = str(name)
        if key not in self.sites:
            raise UnknownNameError("site", key, list(self.sites))
        return self.sites[key]

    def workbench(self, name: str) -> Workbench:
        for w in self.workbenches:
            if w.name == name:
                return w
        raise UnknownNameError("workbench", name, [w.name for w in self.workbenches])

    def reflector_positions(self) -> Array:
        """(N, 2) reflector centers as built (TRUE positions)."""
        return np.array(self.reflectors.positions, dtype=float)

    def speed_bump_yaw(self) -> float:
        return float(wrap_angle(np.deg2rad(self.speed_bump.yaw_deg))) if self.speed_bump else 0.0


def _field_path(loc: tuple[int | str, ...]) -> str:
    return ".".join(str(p) for p in loc) or "<root>"


def parse_scene(data: object, source: str = "<scene>") -> SceneConfig:
    """Validate a parsed YAML document; errors name the offending field."""
    if not isinstance(data, dict):
        raise ConfigError(
            f"{source}: a scene file must be a YAML mapping, got {type(data).__name__}"
        )
    try:
        return SceneConfig.model_validate(data)
    except ValidationError as e:
        lines = [f"  {_field_path(err['loc'])}: {err['msg']}" for err in e.errors()]
        raise ConfigError(f"{source}: invalid scene\n" + "\n".join(lines)) from None


def load_scene(path: str | Path | None = None) -> SceneConfig:
    """Load a scene YAML (default: the built-in world)."""
    path = Path(path) if path is not None else default_scene_path()
    return parse_scene(load_yaml(path, what="scene file"), str(path))


def default_scene_path() -> Path:
    """The built-in world shipped with mmpa."""
    return Path(str(resources.files("mmpa.backends.twin") / "worlds" / "default.yaml"))
