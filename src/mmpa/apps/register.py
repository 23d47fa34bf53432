"""Register two recorded RGB-D frames (``mmpa register``, issue 20): PNG pairs or a bag.

Frames come from a colour PNG + a 16-bit depth PNG (scaled by ``depth_scale`` m per unit) and
an intrinsics file (:func:`load_intrinsics`), or from a ROS 1 / ROS 2 bag through
:class:`~mmpa.backends.bag.reader.BagCamera` (the frames nearest to two times,
:func:`frames_from_bag`).
:func:`register_frames` deprojects both (depth cropped to the config's
``[min_depth, max_depth]``), runs :func:`mmpa.registration.register` and, with ``refine``,
:func:`mmpa.registration.refine_projective` on frame 2's depth and colour images (depth +
photometric) from the accepted ICP pose. The pose is ``T_2_1``: ``p_frame2 = T p_frame1``
(camera optical frames, metres).
:func:`summary` / :func:`write_outputs` give ``summary.json`` and ``T.csv``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, UnidentifiedImageError

from mmpa.backends.bag.reader import BagCamera, BagTopics, bag_topics
from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.core.geometry import Array
from mmpa.registration import (
    ProjectiveConfig,
    ProjectiveResult,
    Registration,
    RegistrationConfig,
    refine_projective,
    register,
)
from mmpa.robot.description import CameraIntrinsics
from mmpa.robot.interfaces import RGBDFrame

__all__ = [
    "BagTopics",
    "FrameRegistration",
    "frames_from_bag",
    "load_intrinsics",
    "load_png_frame",
    "register_frames",
    "summary",
    "write_outputs",
]

_MAX_INTRINSICS_BYTES = 64 * 1024


def _numbers(path: Path) -> list[float]:
    if not path.is_file():
        raise InvalidInputError(f"intrinsics file {path} does not exist")
    if path.stat().st_size > _MAX_INTRINSICS_BYTES:
        raise InvalidInputError(f"intrinsics file {path} is too large for a camera matrix")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise InvalidInputError(f"cannot read the intrinsics file {path}: {e}") from None
    vals: list[float] = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].replace(",", " ")
        for tok in line.split():
            try:
                vals.append(float(tok))
            except ValueError:
                raise InvalidInputError(
                    f"intrinsics file {path}: {tok!r} is not a number"
                ) from None
    return vals


def load_intrinsics(path: str | Path, width: int, height: int) -> CameraIntrinsics:
    """Pinhole intrinsics of a ``width`` x ``height`` image from ``path``: either a 3x3 camera
    matrix (9 numbers, ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``) or one TUM-style line
    ``fx fy cx cy`` (pixels). ``#`` starts a comment; commas count as spaces."""
    path = Path(path)
    v = _numbers(path)
    if len(v) == 9:
        K = np.asarray(v).reshape(3, 3)
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0 or abs(K[0, 1]) > 1e-9:
            raise InvalidInputError(
                f"intrinsics file {path}: not a pinhole camera matrix without skew "
                f"([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), got {K.tolist()}"
            )
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    elif len(v) == 4:
        fx, fy, cx, cy = v
    else:
        raise InvalidInputError(
            f"intrinsics file {path}: expected a 3x3 matrix (9 numbers) or 'fx fy cx cy' "
            f"(4 numbers), got {len(v)} numbers"
        )
    if not all(math.isfinite(x) for x in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0:
        raise InvalidInputError(
            f"intrinsics file {path}: fx, fy must be positive and finite, got {fx}, {fy}"
        )
    return CameraIntrinsics(
        width=width, height=height, fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy)
    )


def _open_png(path: Path, what: str) -> Any:

    if not path.is_file():
        raise InvalidInputError(f"{what} image {path} does not exist")
    try:
        img = Image.open(path)
        img.load()
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise InvalidInputError(f"{what} image {path} cannot be read as an image: {e}") from None
    return img


def load_png_frame(
    color: str | Path,
    depth: str | Path,
    intrinsics: str | Path,
    depth_scale: float = 0.001,
    stamp: float = 0.0,
) -> RGBDFrame:
    """An :class:`RGBDFrame` from a colour image (any 8-bit mode, converted to RGB), a
    single-channel integer depth image (``depth_scale`` m per unit, 0 = no depth; the usual
    16-bit PNG in mm takes 0.001) aligned to it, and an intrinsics file
    (:func:`load_intrinsics`)."""
    if not (math.isfinite(depth_scale) and depth_scale > 0):
        raise InvalidInputError(f"depth scale must be positive (m per unit), got {depth_scale}")
    color, depth = Path(color), Path(depth)
    c_img = _open_png(color, "colour")
    d_img = _open_png(depth, "depth")
    rgb = np.asarray(c_img.convert("RGB"), dtype=np.uint8)
    raw = np.asarray(d_img)
    if raw.ndim != 2 or raw.dtype.kind not in "ui":
        raise InvalidInputError(
            f"depth image {depth} must be single-channel integer depth (a 16-bit PNG), got mode "
            f"{d_img.mode} with shape {raw.shape}"
        )
    if raw.shape != rgb.shape[:2]:
        raise InvalidInputError(
            f"depth image {depth} is {raw.shape[1]}x{raw.shape[0]}, colour image {color} is "
            f"{rgb.shape[1]}x{rgb.shape[0]}: they must be aligned, of the same size"
        )
    h, w = raw.shape
    k = load_intrinsics(intrinsics, w, h)
    d = np.where(raw > 0, raw.astype(np.float64) * depth_scale, 0.0).astype(np.float32)
    return RGBDFrame(color=rgb, depth=d, intrinsics=k, stamp=stamp, frame_id=color.stem)


def frames_from_bag(
    bag: str | Path, t1: float, t2: float, topics: Any = None
) -> tuple[RGBDFrame, RGBDFrame]:
    """The bag's RGB-D frames (``BagCamera``: colour + same-stamp depth + nearest camera info)
    nearest to ``t1`` and ``t2`` s after the first frame's stamp. Times before 0 or past the
    last frame by more than half the median frame interval, and two times that pick the same
    frame, are refused."""

    for name, t in (("--from", t1), ("--to", t2)):
        if not math.isfinite(t):
            raise InvalidInputError(f"{name} must be a finite time (s), got {t}")

    tp = topics or BagTopics()
    have = bag_topics(bag)
    # checked here: read_messages with none of its topics in the bag reads every topic
    absent = [t for t in (tp.color, tp.depth, tp.camera_info) if t not in have]
    if absent:
        images = sorted(
            t for t, (ty, _) in have.items() if ty.split("/")[-1] in ("Image", "CameraInfo")
        )
        raise InvalidInputError(
            f"{bag}: no topic {', '.join(absent)} in the bag (its image / camera info topics: "
            f"{', '.join(images) or 'none'}); set --color-topic / --depth-topic / --info-topic"
        )
    cam = BagCamera(bag, tp)
    frames = [cam.capture() for _ in range(len(cam))]
    stamps = np.array([f.stamp for f in frames])
    rel = stamps - stamps[0]
    tol = 0.5 * float(np.median(np.diff(rel))) if len(rel) > 1 else 0.05
    span = float(rel[-1])
    picked = []
    for name, t in (("--from", t1), ("--to", t2)):
        if t < -tol or t > span + tol:
            raise InvalidInputError(
                f"{bag}: {name} {t:g} s is beyond the bag's camera frames "
                f"(0 to {span:.3f} s after the first frame, {len(frames)} frames)"
            )
        picked.append(int(np.argmin(np.abs(rel - t))))
    if picked[0] == picked[1]:
        raise InvalidInputError(
            f"{bag}: --from {t1:g} s and --to {t2:g} s pick the same frame "
            f"(at {rel[picked[0]]:.3f} s); give times of two different frames"
        )
    return frames[picked[0]], frames[picked[1]]


@dataclass(frozen=True)
class FrameRegistration:
    """Result of :func:`register_frames`: ``icp`` the global + colored-ICP registration,
    ``projective`` the depth-image refinement (``None`` when not run: ``refine`` off or ICP
    refused), ``T`` (4, 4) the pose reported (``T_2_1``; the projective pose when it was
    accepted, else the ICP pose), ``ok`` the verdict (the ICP acceptance), ``reason`` why
    not, ``n_points`` the deprojected points of frames 1 and 2."""

    icp: Registration
    projective: ProjectiveResult | None
    T: Array
    ok: bool
    reason: str
    n_points: tuple[int, int]
    stamps: tuple[float, float]


def register_frames(
    f1: RGBDFrame,
    f2: RGBDFrame,
    cfg: RegistrationConfig | None = None,
    refine: bool = True,
    projective_cfg: ProjectiveConfig | None = None,
) -> FrameRegistration:
    """Register frame 1 (source) onto frame 2 (target); see the module docstring."""
    cfg = cfg or RegistrationConfig()
    c1 = f1.to_point_cloud(cfg.min_depth, cfg.max_depth)
    c2 = f2.to_point_cloud(cfg.min_depth, cfg.max_depth)
    for name, c in (("frame 1", c1), ("frame 2", c2)):
        if len(c.points) < cfg.min_points:
            raise InvalidInputError(
                f"{name} has {len(c.points)} valid depth pixels in "
                f"[{cfg.min_depth}, {cfg.max_depth}] m, need {cfg.min_points} (wrong depth scale?)"
            )
    icp = register(c1, c2, cfg)
    proj = None
    T = icp.T
    if refine and icp.ok:
        colour = (
            {"source_colors": c1.colors, "target_color": f2.color} if c1.colors is not None else {}
        )
        proj = refine_projective(
            c1.points, f2.depth, f2.intrinsics, icp.T, projective_cfg, **colour
        )
        if proj.ok:
            T = proj.T
    return FrameRegistration(
        icp=icp,
        projective=proj,
        T=np.asarray(T, dtype=float),
        ok=bool(icp.ok),
        reason=icp.reason,
        n_points=(len(c1.points), len(c2.points)),
        stamps=(float(f1.stamp), float(f2.stamp)),
    )


def _motion(T: Array) -> tuple[float, float]:
    """Translation (mm) and rotation angle (deg) of ``T``."""
    c = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(T[:3, 3]) * 1e3), float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def summary(r: FrameRegistration) -> dict[str, Any]:
    """JSON-ready summary: the reported pose and its motion, the ICP and projective metrics,
    the verdict."""
    t_mm, r_deg = _motion(r.T)
    out: dict[str, Any] = {
        "T_2_1": r.T.tolist(),
        "pose_from": "projective" if r.projective is not None and r.projective.ok else "icp",
        "translation_mm": t_mm,
        "rotation_deg": r_deg,
        "ok": r.ok,
        "reason": r.reason,
        "n_points": list(r.n_points),
        "stamps": list(r.stamps),
        "icp": {
            "T": r.icp.T.tolist(),
            "fitness": float(r.icp.fitness),
            "rmse": float(r.icp.rmse),
            "ok": bool(r.icp.ok),
            "reason": r.icp.reason,
            "n_correspondences": int(r.icp.n_correspondences),
            "seconds": float(r.icp.seconds),
        },
        "projective": None,
    }
    p = r.projective
    if p is not None:
        out["projective"] = {
            "T": np.asarray(p.T).tolist(),
            "scale": float(p.scale),
            "rmse": float(p.rmse),
            "n_inliers": int(p.n_inliers),
            "inlier_fraction": float(p.inlier_fraction),
            "ok": bool(p.ok),
            "reason": p.reason,
            "iterations": int(p.iterations),
            "seconds": float(p.seconds),
        }
    return out


def write_outputs(out: Path, r: FrameRegistration) -> dict[str, Any]:
    """Write ``summary.json`` and ``T.csv`` (the 4x4 ``T_2_1``, 4 rows of 4) under ``out``;
    returns the summary."""
    s = summary(r)
    try:
        (out / "summary.json").write_text(json.dumps(s, indent=2))
        np.savetxt(out / "T.csv", r.T, delimiter=",", fmt="%.9f")
    except OSError as e:
        raise MMPAError(f"cannot write the results under {out}: {e}") from None
    return s
