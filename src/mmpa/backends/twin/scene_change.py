"""Scene change between teaching and repeating (DESIGN.md "Error model v2").

A bench in use is touched: between the teaching session and a repeat session someone moves a
cup or a bottle. With probability ``p`` per repeat session and per bench, ``n`` of the bench's
loose items (:attr:`~mmpa.backends.twin.scene.DeskItem.loose`), ``n`` uniform on
``{1, ..., min(max_objects, #loose)}`` and the items chosen uniformly without replacement, are
nudged in the map plane about their own vertical axis:

    dx, dy ~ N(0, trans_sigma^2)  (m),   dyaw ~ N(0, rot_sigma_deg^2)  (deg, returned in rad)

    p_new = p_taught + (dx, dy, 0),   R_new = R_z(dyaw) R_taught

(``realistic``: p = 0.3, n <= 3, 2 mm, 1 deg; ``harsh``: 0.5, 5 mm, 2 deg; ``reference`` and
``ideal``: p = 0). Fixtures, backboards and the task's target (``dot``) are never loose, so
they never move. The taught pose of an item is its pose in the scene file
(:func:`~mmpa.backends.twin.mjcf.desk_item_pose`).

The change lives in the MODEL, so it survives :meth:`SimWorld.reset` (``mj_resetData``
restores ``qpos`` to ``model.qpos0``): a free loose item (a cup) gets its free joint's
``model.qpos0`` (and ``data.qpos``, at rest), a static loose item (its own body, a child of
the world body; see :mod:`mmpa.backends.twin.mjcf`) its ``model.body_pos`` / ``model.body_quat``.
Every draw comes from ``ErrorModel.session_rng("scene_change", session)``: a session's change
does not depend on what ran before it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from mmpa.backends.twin.error_model import SceneChange
from mmpa.backends.twin.mjcf import desk_item_pose
from mmpa.backends.twin.scene import SceneConfig
from mmpa.core.errors import InvalidInputError, SimulationError
from mmpa.core.geometry import Array, rot_z

if TYPE_CHECKING:
    from mmpa.backends.twin.world import SimWorld

__all__ = [
    "LooseItem",
    "apply_scene_change",
    "draw_scene_change",
    "loose_items",
    "nudged_pose",
]

Nudge = tuple[float, float, float]


@dataclass(frozen=True)
class LooseItem:
    """A loose desk item: its model name, bench, and taught pose ``T_map_item`` (4x4, m)."""

    name: str
    bench: str
    T_map: Array


def loose_items(scene: SceneConfig) -> dict[str, list[LooseItem]]:
    """The loose items of every bench (site workbenches, then the grasp desk), by bench name,
    in scene order; benches without loose items are left out."""
    out: dict[str, list[LooseItem]] = {}
    for bench in [*scene.workbenches, *([scene.grasp_desk] if scene.grasp_desk else [])]:
        items = [
            LooseItem(bench.item_name(j), bench.name, desk_item_pose(bench, it))
            for j, it in enumerate(bench.items)
            if it.loose
        ]
        if items:
            out[bench.name] = items
    return out


def draw_scene_change(
    names: Sequence[str], rng: np.random.Generator, cfg: SceneChange
) -> dict[str, Nudge]:
    """One bench's change for one repeat session: with probability ``cfg.probability``,
    ``n ~ U{1, ..., min(cfg.max_objects, len(names))}`` of ``names`` (uniform, without
    replacement) each get ``(dx, dy, dyaw)`` with ``dx, dy ~ N(0, cfg.trans_sigma)`` (m) and
    ``dyaw ~ N(0, cfg.rot_sigma_deg)`` (converted to rad); otherwise nothing moves.

    Pure: the result depends only on the arguments. It always consumes the same draws from
    ``rng`` (``2 + len(names) + 3 max_objects`` values), so benches drawn one after the other
    from one generator are independent of each other's outcomes. Returns name -> nudge, in
    the order the items were picked."""
    u_change, u_count = rng.random(2)
    keys = rng.random(len(names))
    z = rng.standard_normal((cfg.max_objects, 3))
    if not names or u_change >= cfg.probability:
        return {}
    n = 1 + int(u_count * min(cfg.max_objects, len(names)))
    picked = np.argsort(keys, kind="stable")[:n]
    sd = np.array([cfg.trans_sigma, cfg.trans_sigma, np.deg2rad(cfg.rot_sigma_deg)])
    return {
        names[int(i)]: (float(dx), float(dy), float(dyaw))
        for i, (dx, dy, dyaw) in zip(picked, z[:n] * sd, strict=True)
    }


def nudged_pose(T_map: Array, nudge: Nudge) -> Array:
    """``T_map`` moved by ``(dx, dy, dyaw)`` (m, m, rad) in the map plane, turning about its
    own vertical axis: ``R' = R_z(dyaw) R``, ``p' = p + (dx, dy, 0)``."""
    dx, dy, dyaw = nudge
    T = np.array(T_map, dtype=float)
    T[:3, :3] = rot_z(dyaw) @ T[:3, :3]
    T[:3, 3] += (dx, dy, 0.0)
    return T


def _quat_wxyz(R: Array) -> Array:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=float).ravel())
    return q


def _place(model: mujoco.MjModel, data: mujoco.MjData, name: str, T_map: Array) -> None:
    """Put loose item ``name`` at ``T_map`` in the model (and, if free, in the state)."""
    try:
        body = model.body(name).id
    except KeyError:
        raise SimulationError(f"loose item {name!r} has no body in the model") from None
    pos, quat = T_map[:3, 3], _quat_wxyz(T_map[:3, :3])
    if model.body_jntnum[body] == 0:
        if model.body_parentid[body] != 0:
            raise SimulationError(f"loose item {name!r} is not a child of the world body")
        model.body_pos[body] = pos
        model.body_quat[body] = quat
        return
    jnt = model.body_jntadr[body]
    if model.body_jntnum[body] != 1 or model.jnt_type[jnt] != mujoco.mjtJoint.mjJNT_FREE:
        raise SimulationError(f"loose item {name!r} must be static or have one free joint")
    qa, da = model.jnt_qposadr[jnt], model.jnt_dofadr[jnt]
    model.qpos0[qa : qa + 3] = pos
    model.qpos0[qa + 3 : qa + 7] = quat
    data.qpos[qa : qa + 7] = model.qpos0[qa : qa + 7]
    data.qvel[da : da + 6] = 0.0


def apply_scene_change(world: SimWorld, session: int) -> dict[str, Nudge]:
    """Start ``session``'s scene (0: teaching, k > 0: the k-th repeat): every loose item back
    at its taught pose, then, for ``session > 0``, each bench's change drawn by
    :func:`draw_scene_change` (benches in scene order, one generator
    ``world.error_model.session_rng("scene_change", session)``) applied to the model as the
    module docstring says; ends with ``mj_forward``.

    Returns what moved: name -> ``(dx, dy, dyaw)`` in map (m, m, rad); empty for the teaching
    session and for a profile with ``probability = 0``. Truth, for evaluation only."""
    k = int(session)
    if k < 0:
        raise InvalidInputError(f"session must be >= 0, got {session}")
    model, data = world.model, world.data
    benches = loose_items(world.scene)
    moved: dict[str, Nudge] = {}
    if k > 0:
        cfg = world.error_model.config.scene_change
        rng = world.error_model.session_rng("scene_change", k)
        for items in benches.values():
            moved.update(draw_scene_change([it.name for it in items], rng, cfg))
    for items in benches.values():
        for it in items:
            T = nudged_pose(it.T_map, moved[it.name]) if it.name in moved else it.T_map
            _place(model, data, it.name, T)
    mujoco.mj_forward(model, data)
    return moved
