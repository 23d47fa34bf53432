"""A ChArUco calibration board in the twin: OpenCV's board image as a texture on a thin box.

The board is a fixed body ``calibration_board`` in front of a work site, placed in the park
pose's frame (``base_link`` of the nominal park pose: x ahead, y left, z up), its printed face
up and tilted toward the robot by ``tilt_deg`` (at a workbench site: nearly upright in front
of the desk, :meth:`BoardPlacement.for_site`). It is added to the world's MJCF when the world
is built (:func:`board_world`), so everything the twin renders sees it.

Frames. The *board frame* is OpenCV's (:class:`cv2.aruco.CharucoBoard`): origin at the outer
corner of the top-left chessboard square of the generated image, x along the image columns,
y along the image rows, z into the board (away from the viewer); its chessboard corner ``k``
is ``board.getChessboardCorners()[k]`` (m). The texture spans the box's top face, image
top-left at the face's (-x, +y) corner (measured: MuJoCo maps a 2D texture so on a box's +z
face), so with the box geom frame ``g`` (centre, z up):

    T_g_board = [diag(1, -1, -1) | (-w / 2 + margin, h / 2 - margin, thickness / 2)]

with ``w, h`` the face size (board plus a white margin each side) in metres.

Units: m, degrees in configuration fields ending in ``_deg``.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import TYPE_CHECKING

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.backends.twin import textures
from mmpa.backends.twin.mjcf import BuiltModel
from mmpa.backends.twin.scene import load_scene
from mmpa.backends.twin.world import SimWorld as _SimWorld
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array, inv, make_T, rot_y, rot_z, se2_to_T
from mmpa.maps.board import CharucoBoardSpec

if TYPE_CHECKING:
    from mmpa.backends.twin.error_model import ErrorModelConfig
    from mmpa.backends.twin.scene import SceneConfig
    from mmpa.backends.twin.world import SimWorld
    from mmpa.robot.description import RobotDescription

__all__ = [
    "BOARD_BODY",
    "BoardPlacement",
    "CharucoBoardSpec",
    "T_board_camera_truth",
    "T_map_board_truth",
    "add_board",
    "board_world",
]

#: name of the board's body (and prefix of its geom, texture and material) in the model
BOARD_BODY = "calibration_board"


class BoardPlacement(BaseModel):
    """Where the board stands: its face centre at ``position`` (m) in the frame of the site's
    nominal park pose (x ahead, y left, z up from the floor), long side along the robot's
    heading, turned by ``yaw_deg`` about z, face tilted toward the robot by ``tilt_deg``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    position: tuple[float, float, float] = (0.62, 0.0, 0.30)
    yaw_deg: float = Field(0.0, ge=-180, le=180)
    tilt_deg: float = Field(15.0, ge=0, le=80)

    @classmethod
    def for_site(cls, scene: SceneConfig, site: str) -> BoardPlacement:
        """Where the board goes at ``site``: the default (free space ahead, 0.30 m up, tilted
        15 deg) unless the site has a workbench ahead; then the board stands nearly upright
        (tilted 70 deg) 0.06 m in front of the desk top's near edge, its lower edge 0.03 m
        above the top, so the desk neither hides it nor cuts it."""
        st = scene.site(site)
        if st.workbench is None:
            return cls()
        bench = scene.workbench(st.workbench)
        x, y, yaw = (float(v) for v in st.pose2d)
        c, s_ = np.cos(np.deg2rad(bench.yaw_deg)), np.sin(np.deg2rad(bench.yaw_deg))
        R_desk = np.array([[c, s_], [-s_, c]])  # map -> desk top frame (2D)
        o = R_desk @ (np.array([x, y]) - np.asarray(bench.center))
        d = R_desk @ np.array([np.cos(yaw), np.sin(yaw)])
        half = np.array(bench.size[:2]) / 2
        with np.errstate(divide="ignore"):
            t1, t2 = (-half - o) / d, (half - o) / d
        t_in, t_out = float(np.max(np.minimum(t1, t2))), float(np.min(np.maximum(t1, t2)))
        if not (t_in < t_out and t_in > 0.2):  # the park heading misses the desk
            return cls()
        return cls(position=(t_in - 0.06, 0.0, bench.size[2] + 0.18), tilt_deg=70.0)

    def T_park_geom(self, spec: CharucoBoardSpec) -> Array:
        """The box geom's pose in the park frame: its top face centre at ``position``."""
        R = rot_z(np.deg2rad(self.yaw_deg)) @ rot_y(-np.deg2rad(self.tilt_deg))
        p = np.asarray(self.position, float) - R @ np.array([0.0, 0.0, spec.thickness / 2])
        return make_T(R, p)

    def T_map_geom(self, site_pose2d: Array, spec: CharucoBoardSpec) -> Array:
        """The box geom's pose in map for a park pose ``[x, y, yaw]``."""
        x, y, yaw = (float(v) for v in np.asarray(site_pose2d, float))
        return se2_to_T(x, y, yaw) @ self.T_park_geom(spec)

    def T_map_board(self, site_pose2d: Array, spec: CharucoBoardSpec) -> Array:
        """The board frame (OpenCV's) in map: the TRUE board pose (it is built there)."""
        return self.T_map_geom(site_pose2d, spec) @ spec.T_geom_board

    def T_armbase_board(self, spec: CharucoBoardSpec, robot: RobotDescription) -> Array:
        """The board frame in ``robot``'s arm base frame where the placement means it to
        stand, through the NOMINAL arm mount at the exact park pose: the rough guess a user
        measures (not the truth: the base parks off and the mount is off)."""
        return inv(robot.T_base_link_arm_base) @ self.T_park_geom(spec) @ spec.T_geom_board


def _f(*xs: float) -> str:
    return " ".join(f"{float(x):.12g}" for x in xs)


def add_board(
    xml: str, assets: dict[str, bytes], spec: CharucoBoardSpec, T_map_geom: Array
) -> tuple[str, dict[str, bytes]]:
    """Add the board to an MJCF document: its texture and material, and a fixed body
    ``calibration_board`` holding a thin box as the *last* child of the worldbody (so the
    ids of every other body and geom are unchanged). The box is visual only (contype and
    conaffinity 0): the arm may not touch it anyway. Returns ``(xml, assets)``."""

    T = np.asarray(T_map_geom, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InvalidInputError(f"T_map_geom must be a finite 4x4 transform, got {T.shape}")
    root = ET.fromstring(xml)
    asset = root.find("asset")
    world = root.find("worldbody")
    if asset is None or world is None:
        raise InvalidInputError("MJCF without <asset> or <worldbody>: not a world model")
    fname = f"{BOARD_BODY}.png"
    assets = {**assets, fname: textures.png_bytes(spec.image())}
    ET.SubElement(asset, "texture", name=f"tex_{BOARD_BODY}", type="2d", file=fname)
    ET.SubElement(
        asset,
        "material",
        name=f"mat_{BOARD_BODY}",
        texture=f"tex_{BOARD_BODY}",
        specular="0.05",
        shininess="0.1",
    )
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, T[:3, :3].ravel())
    body = ET.SubElement(world, "body", name=BOARD_BODY, pos=_f(*T[:3, 3]), quat=_f(*quat))
    w, h = spec.face_size
    ET.SubElement(
        body,
        "geom",
        name=f"{BOARD_BODY}_face",
        type="box",
        size=_f(w / 2, h / 2, spec.thickness / 2),
        material=f"mat_{BOARD_BODY}",
        contype="0",
        conaffinity="0",
        group="0",
    )
    return ET.tostring(root, encoding="unicode"), assets


def board_world(
    site: str = "0",
    spec: CharucoBoardSpec | None = None,
    placement: BoardPlacement | None = None,
    *,
    errors: ErrorModelConfig | None = None,
    robot: RobotDescription | None = None,
    scene: SceneConfig | None = None,
    episode: int = 0,
) -> SimWorld:
    """A :class:`~mmpa.backends.twin.world.SimWorld` at ``site`` with the board in front of the
    site's
    park pose (``errors``, ``robot``, ``scene``, ``episode``: as ``SimWorld`` takes them).
    The board's TRUE pose: :func:`T_map_board_truth`."""

    spec = spec or CharucoBoardSpec()
    placement = placement or BoardPlacement()
    scene = scene or load_scene()
    pose = scene.site(site).pose2d

    T_map_geom = placement.T_map_geom(pose, spec)

    def with_board(built: BuiltModel) -> BuiltModel:
        return BuiltModel(*add_board(built.xml, built.assets, spec, T_map_geom))

    return _SimWorld(
        scene=scene, robot=robot, errors=errors, site=site, episode=episode, model_hook=with_board
    )


def T_map_board_truth(world: SimWorld, spec: CharucoBoardSpec) -> Array:
    """The TRUE board frame in map, read from the built model (evaluation only)."""
    b = world.data.body(BOARD_BODY)
    return make_T(np.asarray(b.xmat).reshape(3, 3), b.xpos) @ spec.T_geom_board


def T_board_camera_truth(world: SimWorld, spec: CharucoBoardSpec) -> Array:
    """TRUE camera optical frame in the board frame (evaluation only)."""
    return inv(T_map_board_truth(world, spec)) @ world.truth.T_map_camera()
