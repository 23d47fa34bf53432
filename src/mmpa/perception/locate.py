"""3D location of detected objects (paper 001 §3.2.1, Fig. 4).

"The center of the bounding box is regarded as the center of the object, whereas the longest
side of the bounding box is regarded as the graspable edge": the box center pixel is
deprojected with the depth image to the camera optical frame (z forward, x right, y down), and
carried to ``arm_base`` through the NOMINAL kinematics ``T_arm_base_camera = fk(q) @
T_flange_camera``. Pure numpy; no simulator.

Improvement over the paper (option ``depth_mode="median"``): the depth at the box center is
the median of the valid depths in a small window around it (a single pixel is often a hole or
an edge). The returned point is the visible surface point on the center ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.core.geometry import Array, apply, make_T

__all__ = [
    "DepthMissingError",
    "Location",
    "box_iou",
    "deproject",
    "grasp_axis_from_box",
    "grasp_yaw_from_mask",
    "locate",
    "look_at",
    "project",
]


class DepthMissingError(MMPAError):
    """No valid depth at (and around) the box center."""


@dataclass(frozen=True)
class Location:
    """An object located in 3D.

    ``p_camera``: (3,) m, optical frame; ``p_arm_base``: (3,) m; ``axis_arm_base``: (3,) unit
    vector of the graspable edge (longest box side) in ``arm_base``; ``depth``: m.
    """

    p_camera: Array
    p_arm_base: Array
    axis_arm_base: Array
    depth: float
    center_arm_base: Array | None = None  # improvement: surface point pushed to the center


def deproject(u: float, v: float, z: float, K: Array) -> Array:
    """Pixel ``(u, v)`` with depth ``z`` (m, along the optical axis) -> point (3,) in the
    optical frame: ``x = (u - cx) z / fx``, ``y = (v - cy) z / fy``."""
    K = np.asarray(K, float)
    if K.shape != (3, 3):
        raise InvalidInputError(f"K must be (3, 3), got {K.shape}")
    if not (np.isfinite(z) and z > 0):
        raise InvalidInputError(f"depth must be positive, got {z}")
    return np.array([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])


def project(p: Array, K: Array) -> Array:
    """Point(s) (..., 3) in the optical frame -> pixel(s) (..., 2)."""
    p = np.asarray(p, float)
    K = np.asarray(K, float)
    return np.stack(
        [K[0, 0] * p[..., 0] / p[..., 2] + K[0, 2], K[1, 1] * p[..., 1] / p[..., 2] + K[1, 2]],
        axis=-1,
    )


def box_iou(a: Array, b: Array) -> Array:
    """Intersection over union of every box of ``a`` (N, 4) with every box of ``b`` (M, 4),
    boxes ``[x1, y1, x2, y2]`` (pixels): (N, M)."""
    a = np.asarray(a, float).reshape(-1, 4)
    b = np.asarray(b, float).reshape(-1, 4)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(rb - lt, 0, None).prod(-1)
    aa = (a[:, 2:] - a[:, :2]).prod(-1)
    ab = (b[:, 2:] - b[:, :2]).prod(-1)
    return inter / np.maximum(aa[:, None] + ab[None] - inter, 1e-12)


def box_center_depth(depth: Array, box: Array, window: int = 2, mode: str = "median") -> float:
    """Depth (m) at the center of ``box`` = ``[x1, y1, x2, y2]`` (pixels of ``depth``).

    ``mode="center"``: the paper's single center pixel; ``"median"``: median of the valid
    (> 0) depths in a ``(2 window + 1)^2`` patch. Raises :class:`DepthMissingError` when none.
    """
    d = np.asarray(depth, float)
    if d.ndim != 2:
        raise InvalidInputError(f"depth must be (H, W), got {d.shape}")
    h, w = d.shape
    u = int(np.clip(round((box[0] + box[2]) / 2), 0, w - 1))
    v = int(np.clip(round((box[1] + box[3]) / 2), 0, h - 1))
    if mode == "center":
        z = d[v, u]
        if not (np.isfinite(z) and z > 0):
            raise DepthMissingError(f"no depth at the box center pixel ({u}, {v})")
        return float(z)
    if mode != "median":
        raise InvalidInputError(f"depth mode must be 'center' or 'median', got {mode!r}")
    patch = d[max(v - window, 0) : v + window + 1, max(u - window, 0) : u + window + 1]
    ok = patch[np.isfinite(patch) & (patch > 0)]
    if ok.size == 0:
        raise DepthMissingError(
            f"no valid depth within {window} px of the box center ({u}, {v}); the object may be "
            "too close (below the camera's minimum range) or on a hole of the depth image"
        )
    return float(np.median(ok))


def grasp_axis_from_box(box: Array) -> Array:
    """Paper 001: the longest box side is the graspable edge. Unit 2D image direction
    ``(du, dv)``: ``(1, 0)`` if the box is wider than tall, else ``(0, 1)``."""
    b = np.asarray(box, float)
    return np.array([1.0, 0.0]) if (b[2] - b[0]) >= (b[3] - b[1]) else np.array([0.0, 1.0])


def grasp_yaw_from_mask(mask: Array) -> Array:
    """Improvement: the principal axis (unit ``(du, dv)``) of a foreground mask (H, W) bool,
    from the eigenvector of its pixel covariance; handles objects diagonal in the image, where
    the paper's axis-aligned box side is ambiguous."""
    vv, uu = np.nonzero(np.asarray(mask, bool))
    if uu.size < 3:
        raise InvalidInputError("mask has fewer than 3 pixels")
    c = np.cov(np.stack([uu, vv]).astype(float))
    w, V = np.linalg.eigh(c)
    a = V[:, int(np.argmax(w))]
    return a / np.linalg.norm(a)


def locate(
    box: Array,
    depth: Array,
    K: Array,
    T_arm_base_camera: Array,
    depth_mode: str = "median",
    axis_2d: Array | None = None,
) -> Location:
    """Paper 001 §3.2.1: box center + depth -> optical frame -> ``arm_base``.

    ``box``: ``[x1, y1, x2, y2]`` pixels of ``depth``'s image (H, W), ``K`` its intrinsics;
    ``T_arm_base_camera`` from the nominal kinematics. The grasp axis is the longest box side
    (or ``axis_2d``), carried to 3D at the object's depth.
    """
    box = np.asarray(box, float)
    if box.shape != (4,) or not np.all(np.isfinite(box)) or box[2] <= box[0] or box[3] <= box[1]:
        raise InvalidInputError(f"box must be finite [x1, y1, x2, y2] with x2 > x1, y2 > y1: {box}")
    z = box_center_depth(depth, box, mode=depth_mode)
    uc, vc = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    p_cam = deproject(uc, vc, z, K)
    a2 = grasp_axis_from_box(box) if axis_2d is None else np.asarray(axis_2d, float)
    p2 = deproject(uc + 10 * a2[0], vc + 10 * a2[1], z, K)
    T = np.asarray(T_arm_base_camera, float)
    p_arm = apply(T, p_cam)
    ax = apply(T, p2) - p_arm
    ax /= np.linalg.norm(ax)
    # improvement: the center ray meets the object's near surface; a convex object's center
    # lies about one radius (half the short box side at this depth) further along the ray
    r = 0.5 * min(box[2] - box[0], box[3] - box[1]) * z / float(np.asarray(K)[0, 0])
    c_cam = p_cam + r * p_cam / np.linalg.norm(p_cam)
    return Location(
        p_camera=p_cam,
        p_arm_base=p_arm,
        axis_arm_base=ax,
        depth=z,
        center_arm_base=apply(T, c_cam),
    )


def look_at(eye: Array, target: Array, up_hint: Array = (0.0, 0.0, 1.0)) -> Array:
    """Optical-frame pose (4, 4) at ``eye`` with z toward ``target``; image "up" (-y) as
    close to ``up_hint`` as the view allows (for straight-down views pass a horizontal hint)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    n = np.linalg.norm(z)
    if n < 1e-9:
        raise InvalidInputError("eye and target coincide")
    z /= n
    up = np.asarray(up_hint, float)
    x = np.cross(-up, z)
    if np.linalg.norm(x) < 1e-6:
        raise InvalidInputError("up_hint is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.column_stack([x, y, z]), eye)
