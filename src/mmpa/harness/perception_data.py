"""Training and test data rendered by the digital twin, labelled by segmentation rendering.

Each sample: the seven objects of paper 001 Fig. 11 (a random subset) and distractors at random
poses on the grasp desk, one of the three light conditions (with jitter), a wrist-camera
viewpoint reached by the nominal IK, a 320x240 RGB image with the camera's noise model, and
boxes from MuJoCo's segmentation rendering (the body id at each pixel; a box is the extent of
an object's visible pixels; objects with fewer than ``min_pixels`` visible are not labelled).

Two kinds of viewpoint:

- *random views* (the default): any view of the desk from the robot's side, 0.32-0.65 m away,
  50-90 deg elevation, camera roll +-20 deg; objects are often cut by the image border;
- *working views* (``work_view_prob``): the view the robot takes before a grasp (paper 001
  Table 3 counts a detection success when the target is detected there): the base parked at
  the desk, the camera ``LOOK_HEIGHT`` above the desk looking straight down at ``LOOK_TARGET``
  (the ``grasp`` experiment's first view, :func:`mmpa.servo.grasp.look_configuration`), one
  *target* object in the reachable region and the others anywhere on the desk. These images
  go through the robot's own camera (640x480, the reference noise model) and the detector's
  downsampling (:func:`mmpa.perception.ssd.to_input`), exactly as the robot sees them; the
  target's class is stored per image (``Dataset.target``, -1 for random views).
  A fraction ``work_servo_prob`` of the working views are *servo views* instead: the views
  of the tracking grasp's approach, the tool pointing down ``work_servo_standoff`` above the
  target's top (the tracking and final standoffs lie in this range), offset laterally by up
  to ``work_servo_jitter`` and turned to a random yaw; the camera sits beside the tool axis,
  so the target appears off-center, often cut by the lower image border (where the servo
  sees it; docs/experiments.md).

This module drives the simulator (a data generator, like an operator); the data set itself
(:class:`~mmpa.perception.dataset.Dataset`) lives in :mod:`mmpa.perception.dataset`, which the
detector and its training use without the simulator.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.backends.twin.error_model import CameraNoise, ErrorModelConfig
from mmpa.backends.twin.noise import color_noise
from mmpa.backends.twin.sensors import SimCamera
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.core.geometry import Array, inv, make_T, rot_z, se2_to_T
from mmpa.perception import CLASSES, LIGHTING_CONDITIONS
from mmpa.perception.dataset import Dataset, Sample, load_dataset, save_dataset
from mmpa.perception.locate import look_at
from mmpa.robot.description import CameraIntrinsics
from mmpa.robot.kinematics import ik_nearest
from mmpa.servo.grasp import look_configuration

if TYPE_CHECKING:
    from mmpa.backends.twin.world import SimWorld

__all__ = [
    "DESK_PARK",
    "LOOK_HEIGHT",
    "LOOK_TARGET",
    "REGION",
    "Dataset",
    "DatasetConfig",
    "Sample",
    "desk_frame",
    "load_dataset",
    "random_table_scene",
    "render_dataset",
    "sample_view",
    "save_dataset",
    "servo_view_configuration",
]

# Robot parked in front of the grasp desk (map): facing +y, 0.4 m from the desk's near edge.
DESK_PARK = (2.70, 0.85, np.pi / 2)
# Light factor ranges per condition (relative to the built-in lights) and extra sensor noise.
LIGHT_RANGES = {"dark": (0.10, 0.28), "normal": (0.75, 1.3), "high": (1.8, 2.8)}
NOISE_SIGMA = {"dark": 5.0 / 255, "normal": 2.0 / 255, "high": 2.0 / 255}
# The grasp experiment's desk geometry: the reachable part of the desk (desk-top frame, m)
# where trial objects are placed, and the first view of the desk (the camera LOOK_HEIGHT above
# the desk top looking straight down at LOOK_TARGET).
REGION = (-0.15, 0.15, -0.22, 0.0)
LOOK_TARGET = (0.47, 0.0)  # arm_base x, y of the first view
LOOK_HEIGHT = 0.45  # m above the desk top


class DatasetConfig(BaseModel):
    """Rendered data set. ``lighting``: fractions of images per condition."""

    model_config = ConfigDict(extra="forbid")
    n_images: int = Field(2000, ge=1)
    seed: int = Field(0, ge=0)  # every random draw flows from it (numpy: >= 0)
    width: int = 320
    height: int = 240
    objects_min: int = Field(1, ge=1)
    objects_max: int = Field(5, ge=1, le=len(CLASSES))
    distractor_prob: float = Field(0.6, ge=0, le=1)
    lighting: dict[str, float] = Field(default_factory=lambda: {"dark": 1, "normal": 1, "high": 1})
    view_distance: tuple[float, float] = (0.32, 0.65)  # m, camera to desk target
    view_elevation_deg: tuple[float, float] = (50.0, 90.0)
    base_jitter: tuple[float, float, float] = (0.15, 0.06, 0.2)  # m, m, rad around DESK_PARK
    min_pixels: int = Field(25, ge=1)
    work_view_prob: float = Field(0.0, ge=0, le=1)  # fraction of working views (module doc)
    work_exact_lighting: bool = False  # working views at the twin's exact condition factors
    work_base_jitter: tuple[float, float, float] = (0.05, 0.03, 0.05)  # the grasp experiment's
    work_look_jitter: float = Field(0.03, ge=0)  # m, look target jitter in x and y
    work_servo_prob: float = Field(0.0, ge=0, le=1)  # of the working views: servo views
    work_servo_standoff: tuple[float, float] = (0.14, 0.30)  # m, TCP above the target's top
    work_servo_jitter: float = Field(0.03, ge=0)  # m, TCP offset from the target in x and y
    profile: str = "realistic"  # the twin's error model profile (its camera noise)


def desk_frame(world: SimWorld) -> tuple[Array, float, tuple[float, float]]:
    """``(T_map_desk_top, top_height, (half_length, half_depth))`` of the grasp desk."""
    d = world.scene.grasp_desk
    if d is None:
        raise ConfigError("the scene has no grasp_desk")
    T = make_T(rot_z(np.deg2rad(d.yaw_deg)), [d.center[0], d.center[1], d.size[2]])
    return T, float(d.size[2]), (d.size[0] / 2, d.size[1] / 2)


def _footprint(world: SimWorld, name: str) -> tuple[float, float]:
    """(footprint radius, rest height of the body origin above the desk top)."""
    for o in world.scene.grasp_objects:
        if o.name == name:
            if o.kind == "cube":
                return o.size[0] * 1.42, o.size[0]
            if o.kind == "ball":
                return o.size[0], o.size[0]
            if o.lying:
                return o.size[1], o.size[0]
            return o.size[0], o.size[1]
    d = world.scene.grasp_desk
    for it in d.items if d else []:
        if it.name == name:
            sx, sy, _ = it.size or (0.08, 0.08, 0.08)
            return 0.5 * float(np.hypot(sx, sy)), 0.0
    raise InvalidInputError(f"unknown object {name!r}")


def park_objects(world: SimWorld, names: list[str]) -> None:
    """Put unused objects on the floor in the lobby's corner, out of every view."""
    for i, n in enumerate(names):
        _, h = _footprint(world, n)
        world.place_object(n, np.array([3.9, -2.9 + 0.25 * i, h + 0.002]))


def random_table_scene(
    world: SimWorld,
    rng: np.random.Generator,
    objects: list[str],
    distractors: list[str],
    region: tuple[float, float, float, float] | None = None,
) -> dict[str, Array]:
    """Place ``objects`` and ``distractors`` at random non-overlapping poses on the grasp desk
    (desk-top ``region = (x_min, x_max, y_min, y_max)``, default: the whole top with margins);
    park every other movable body. Returns the map positions placed."""
    T_desk, _, (hx, hy) = desk_frame(world)
    x0, x1, y0, y1 = region or (-hx + 0.06, hx - 0.06, -hy + 0.06, hy - 0.06)
    placed: list[tuple[float, float, float]] = []
    out: dict[str, Array] = {}
    for name in [*distractors, *objects]:
        r, h = _footprint(world, name)
        for _ in range(200):
            x, y = rng.uniform(x0, x1), rng.uniform(y0, y1)
            if all(np.hypot(x - a, y - b) > r + c + 0.01 for a, b, c in placed):
                break
        else:
            continue
        placed.append((x, y, r))
        p = T_desk[:3, :3] @ np.array([x, y, h + 0.001]) + T_desk[:3, 3]
        world.place_object(name, p, yaw=float(rng.uniform(-np.pi, np.pi)))
        out[name] = p
    park_objects(world, [n for n in desk_object_names(world) if n not in out])
    return out


def desk_object_names(world: SimWorld) -> list[str]:
    """Grasp objects and the grasp desk's free items (distractors)."""
    d = world.scene.grasp_desk
    extra = [it.name for it in (d.items if d else []) if it.free and it.name]
    return [o.name for o in world.scene.grasp_objects] + extra


def sample_view(
    world: SimWorld, rng: np.random.Generator, cfg: DatasetConfig, target: Array
) -> Array | None:
    """A random wrist-camera view of ``target`` (map) from the robot's side; the arm
    configuration (6,) by nominal IK (None if unreachable)."""

    rb = world.nominal
    pose = world.truth.base_pose2d()
    el = np.deg2rad(rng.uniform(*cfg.view_elevation_deg))
    az = pose[2] + np.pi + rng.uniform(-0.5, 0.5)  # look from the robot's side
    dist = rng.uniform(*cfg.view_distance)
    eye = np.asarray(target) + dist * np.array(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    )
    heading = np.array([np.cos(pose[2]), np.sin(pose[2]), 0.0])
    T_map_cam = look_at(eye, target, up_hint=heading + np.array([0, 0, 1e-3]))
    T_map_cam = T_map_cam @ make_T(rot_z(rng.uniform(-0.35, 0.35)))
    T_map_arm = world.truth.T_map_arm_base()
    T_arm_flange = inv(T_map_arm) @ T_map_cam @ inv(rb.camera.T_flange_camera)
    q_min, q_max = rb.arm.q_limits
    try:
        q = ik_nearest(rb.arm.dh, T_arm_flange, np.array(rb.arm.view_bench), q_min, q_max)
    except Exception:
        return None
    # keep the elbow up and the camera above the desk (no views through the arm)
    return q


def boxes_from_segmentation(
    seg: np.ndarray, body_ids: dict[int, int], min_pixels: int
) -> tuple[np.ndarray, np.ndarray]:
    """Boxes ``[x1, y1, x2 + 1, y2 + 1]`` of every labelled body with ``>= min_pixels``
    visible pixels in ``seg`` (H, W body ids)."""
    boxes, labels = [], []
    for bid, cls in body_ids.items():
        vv, uu = np.nonzero(seg == bid)
        if uu.size < min_pixels:
            continue
        boxes.append([uu.min(), vv.min(), uu.max() + 1, vv.max() + 1])
        labels.append(cls)
    return (
        np.array(boxes, np.float32).reshape(-1, 4),
        np.array(labels, np.int64),
    )


def render_dataset(cfg: DatasetConfig, log: object = None, progress: object = None) -> Dataset:
    """Render ``cfg.n_images`` labelled images (seeded by ``cfg.seed``)."""
    errors = _checked_error_model(cfg)
    rng = np.random.default_rng(cfg.seed)
    world = SimWorld(site="0", errors=errors)
    cam, noise = _dataset_camera(world, cfg, rng)
    try:
        samples, targets = _render_samples(world, cam, noise, rng, cfg, log, progress)
    finally:
        cam.close()
        world.close()
    return Dataset(
        np.stack([s.image for s in samples]),
        [s.boxes for s in samples],
        [s.labels for s in samples],
        np.array([s.lighting for s in samples], int),
        np.array(targets, int),
    )


def _checked_error_model(cfg: DatasetConfig) -> ErrorModelConfig:
    """The twin's error model of ``cfg.profile``; raises :class:`ConfigError` on a bad
    object count range, an unknown lighting condition or profile."""
    if cfg.objects_max < cfg.objects_min:
        raise ConfigError("objects_max must be >= objects_min")
    unknown = set(cfg.lighting) - set(LIGHTING_CONDITIONS)
    if unknown:
        raise ConfigError(f"unknown lighting {sorted(unknown)}; known {LIGHTING_CONDITIONS}")

    try:
        return ErrorModelConfig(profile=cfg.profile)  # type: ignore[arg-type]
    except ValueError:
        raise ConfigError(
            f"unknown error model profile {cfg.profile!r}; use ideal, reference, realistic or harsh"
        ) from None


def _dataset_camera(
    world: SimWorld, cfg: DatasetConfig, rng: np.random.Generator
) -> tuple[SimCamera, CameraNoise]:
    """The wrist camera scaled to ``cfg.width`` x ``cfg.height`` (principal point centred)
    with the error model's camera noise (drawn from ``rng``), and that noise model."""
    cam_desc = world.true_robot.camera
    k0 = cam_desc.color
    s = cfg.width / k0.width
    k = CameraIntrinsics(
        width=cfg.width,
        height=cfg.height,
        fx=k0.fx * s,
        fy=k0.fy * s,
        cx=(cfg.width - 1) / 2,
        cy=(cfg.height - 1) / 2,
    )
    desc = cam_desc.model_copy(update={"color": k})
    noise = world.error_model.config.camera
    cam = SimCamera(world.model, world.data, desc, noise, rng, lambda: world.time)
    return cam, noise


def _render_samples(
    world: SimWorld,
    cam: SimCamera,
    noise: CameraNoise,
    rng: np.random.Generator,
    cfg: DatasetConfig,
    log: object,
    progress: object,
) -> tuple[list[Sample], list[int]]:
    """The samples and their targets (class index, -1 for a random view): per image a base
    pose (random views share one per 50), the objects and distractors (random colours), then
    a working view (with ``cfg.work_view_prob``) or a random one; a view that fails is drawn
    again."""
    body_ids = {world.model.body(n).id: i for i, n in enumerate(CLASSES)}
    distractors = [n for n in desk_object_names(world) if n not in CLASSES]
    dgeoms = [
        g
        for g in range(world.model.ngeom)
        if world.model.geom_bodyid[g] in {world.model.body(n).id for n in distractors}
    ]
    conds = list(cfg.lighting)
    pc = np.array([cfg.lighting[c] for c in conds], float)
    pc /= pc.sum()
    samples: list[Sample] = []
    targets: list[int] = []
    i = 0
    was_work = False
    while i < cfg.n_images:
        # (no draw without working views: random-view data sets keep their old streams)
        work = cfg.work_view_prob > 0 and bool(rng.random() < cfg.work_view_prob)
        if i % 50 == 0 or work or was_work:  # random views share a base pose per 50
            x, y, th = DESK_PARK
            j = np.array(cfg.work_base_jitter if work else cfg.base_jitter)
            pose = np.array([x, y, th]) + rng.uniform(-1, 1, 3) * j
            world.reset(pose2d=pose, settle=0.0)
        was_work = work
        n_obj = int(rng.integers(cfg.objects_min, cfg.objects_max + 1))
        objs = list(rng.choice(CLASSES, n_obj, replace=False))
        dis = [d for d in distractors if rng.random() < cfg.distractor_prob]
        for g in dgeoms:
            world.model.geom_rgba[g, :3] = rng.uniform(0.05, 0.95, 3)
        if work:
            cond = conds[int(rng.choice(len(conds), p=pc))]
            s = _work_view_sample(world, rng, cfg, cond, objs, dis, body_ids)
        else:
            s = _random_view_sample(world, cam, noise, rng, cfg, conds, pc, objs, dis, body_ids)
        if s is None:
            continue
        samples.append(s)
        targets.append(CLASSES.index(objs[0]) if work else -1)
        i += 1
        if progress is not None:
            progress(i / cfg.n_images)  # type: ignore[operator]
        if log is not None and i % 100 == 0:
            log(f"rendered {i}/{cfg.n_images}")  # type: ignore[operator]
    return samples, targets


def _random_view_sample(
    world: SimWorld,
    cam: SimCamera,
    noise: CameraNoise,
    rng: np.random.Generator,
    cfg: DatasetConfig,
    conds: list[str],
    pc: Array,
    objs: list[str],
    dis: list[str],
    body_ids: dict[int, int],
) -> Sample | None:
    """One random view (module doc): the objects anywhere on the desk, a view of one of them
    (aim jittered by 5 cm), a light condition drawn by ``pc`` with a jittered factor, the
    condition's extra sensor noise; None when nothing was placed or the view is unreachable."""
    placed = random_table_scene(world, rng, objs, dis)
    if not placed:
        return None
    target = placed[str(rng.choice(list(placed)))] + rng.normal(0, 0.05, 3) * [1, 1, 0]
    q = sample_view(world, rng, cfg, target)
    if q is None:
        return None
    world.set_arm_configuration(q)
    cond = conds[int(rng.choice(len(conds), p=pc))]
    world.set_lighting(float(rng.uniform(*LIGHT_RANGES[cond])))
    color, _ = cam._render()
    seg = cam.segmentation()
    b, lab = boxes_from_segmentation(seg, body_ids, cfg.min_pixels)
    noisy = noise.model_copy(update={"color_sigma": NOISE_SIGMA[cond]})
    return Sample(color_noise(color, rng, noisy), b, lab, LIGHTING_CONDITIONS.index(cond))


def _work_view_sample(
    world: SimWorld,
    rng: np.random.Generator,
    cfg: DatasetConfig,
    cond: str,
    objs: list[str],
    dis: list[str],
    body_ids: dict[int, int],
) -> Sample | None:
    """One working view (module doc): ``objs[0]`` is the target, placed in the grasp
    experiment's reachable region; the image is the robot camera's frame downsampled to
    ``cfg.width`` x ``cfg.height``, boxes from the full-resolution segmentation."""
    from mmpa.perception.ssd import to_input

    placed = random_table_scene(world, rng, objs[1:], dis)
    _place_in_region(world, rng, objs[0], placed, REGION)
    _, top, _ = desk_frame(world)
    rb = world.nominal
    # (no draw without servo views: working-view data sets keep their old streams)
    servo = cfg.work_servo_prob > 0 and bool(rng.random() < cfg.work_servo_prob)
    try:
        if servo:
            q = servo_view_configuration(world, rng, cfg, objs[0])
        else:
            look = np.array(
                [*(np.array(LOOK_TARGET) + rng.uniform(-1, 1, 2) * cfg.work_look_jitter), 0.0]
            )
            look[2] = top - rb.T_base_link_arm_base[2, 3]
            q = look_configuration(rb, look, LOOK_HEIGHT)
    except Exception:
        return None
    world.set_arm_configuration(q)
    if cfg.work_exact_lighting:
        world.set_lighting(cond)
    else:
        world.set_lighting(float(rng.uniform(*LIGHT_RANGES[cond])))
    full = world.camera.capture().color
    img, sx, sy = to_input(full, cfg.width, cfg.height)
    seg = world.camera.segmentation()
    b, lab = boxes_from_segmentation(seg, body_ids, round(cfg.min_pixels * sx * sy))
    b = b / np.array([sx, sy, sx, sy], np.float32)
    return Sample(img, b.astype(np.float32), lab, LIGHTING_CONDITIONS.index(cond))


def servo_view_configuration(
    world: SimWorld, rng: np.random.Generator, cfg: DatasetConfig, name: str
) -> Array:
    """Joint angles (6,) of a servo view of ``name`` (module doc): the TCP at
    ``p_top + (dx, dy, s)`` in ``arm_base`` with ``dx, dy ~ U(-j, j)`` (``j =
    cfg.work_servo_jitter``), ``s ~ U(cfg.work_servo_standoff)``, the tool z pointing down and
    the tool x at a yaw ``~ U(-pi, pi)``; ``p_top`` is the object's origin raised by its rest
    height (the top of an upright object). Nominal IK nearest the first view's configuration;
    raises :class:`mmpa.core.errors.UnreachableError` (or another IK error) when out of reach."""

    rb = world.nominal
    _, h = _footprint(world, name)
    T_map_arm = world.truth.T_map_arm_base()
    p = (inv(T_map_arm) @ world.truth.T_map_object(name))[:3, 3] + np.array([0.0, 0.0, h])
    j = cfg.work_servo_jitter
    p_tcp = p + np.array([*(rng.uniform(-1, 1, 2) * j), rng.uniform(*cfg.work_servo_standoff)])
    yaw = rng.uniform(-np.pi, np.pi)
    x = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    z = np.array([0.0, 0.0, -1.0])
    T_arm_tcp = make_T(np.column_stack([x, np.cross(z, x), z]), p_tcp)
    T_arm_flange = T_arm_tcp @ inv(rb.gripper.T_flange_tcp)
    q_min, q_max = rb.arm.q_limits

    _, top, _ = desk_frame(world)
    look = np.array([*LOOK_TARGET, top - rb.T_base_link_arm_base[2, 3]])
    q_ref = look_configuration(rb, look, LOOK_HEIGHT)  # the servo's branch
    return ik_nearest(rb.arm.dh, T_arm_flange, q_ref, q_min, q_max)


def _place_in_region(
    world: SimWorld,
    rng: np.random.Generator,
    name: str,
    placed: dict[str, Array],
    region: tuple[float, float, float, float],
) -> None:
    """Put ``name`` in the desk-top ``region`` at least its footprint + 0.1 m away from the
    already placed objects (300 tries, else the last draw), at a random yaw."""
    T_desk, _, _ = desk_frame(world)
    r, h = _footprint(world, name)
    local = [(inv(T_desk) @ np.append(p, 1.0))[:2] for p in placed.values()]
    x0, x1, y0, y1 = region
    xy = np.zeros(2)
    for _ in range(300):
        xy = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        if all(np.linalg.norm(xy - q) > r + 0.1 for q in local):
            break
    p = T_desk[:3, :3] @ np.array([*xy, h + 0.001]) + T_desk[:3, 3]
    world.place_object(name, p, yaw=float(rng.uniform(-np.pi, np.pi)))


def base_pose_T(pose2d: Array) -> Array:
    return se2_to_T(*pose2d)
