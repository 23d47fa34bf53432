"""Where to grasp: the object's top surface, the desk under it and the grasp height, from a
detection box and the depth image (improvement over paper 001 §3.2.1).

The paper takes the box center, deprojected with the depth there, as the object center. For a
tall object seen obliquely (a 0.2 m bottle) that pixel lies on the object's side, and its
height depends on the viewpoint: the gripper then aims too low and too far, the palm lands on
the bottle top ("the fingers land on the cap"). Here every valid depth pixel of the box is
deprojected to ``arm_base`` (nominal kinematics)::

    p_i = R_ab_cam K^-1 (u_i, v_i, 1) z_i + t_ab_cam                      (m, arm_base)

- the desk height ``z_desk``: a low percentile of the heights on a ring just outside the box
  (desk pixels around the object);
- the foreground: box points higher than ``z_desk + fg_min``, split into surfaces: 4-neighbour
  pixels belong to one surface when their points lie within ``gap_abs + gap_rel * s`` of each
  other (``s`` the pixel footprint, m). The object is the surface whose image bounding box
  overlaps the detection box best (IoU): the box was drawn around it, while another object in
  a corner of the box (a lying stick's box crossing a taller cup) fills only part of it. Of the
  surfaces whose IoU reaches ``fit_keep`` times the best, the one with the highest median
  height: the desk, counted as foreground when the desk height is underestimated (the ring
  outside the box on the floor), fills the box as well as the object on it;
- the top ``z_top``: a high percentile of the foreground heights (robust to flying pixels);
- the top center: the mean ``x, y`` of the foreground points within ``top_band`` of ``z_top``
  (the top band), and its long axis in the x-y plane (a lying stick's ridge: the grasp axis).
  For the convex objects of paper 001 Fig. 11 resting on the desk (upright cylinder, lying
  cylinder, ball, cube) it lies on the vertical through the object's center whatever the view.

The grasp height of the tool center point (TCP, between the fingertips) for a top-down grasp
with fingers reaching ``pad_below`` under the TCP and a palm ``palm_above`` over it::

    z_grasp = max((z_top + z_desk) / 2,  z_top - palm_clearance,  z_desk + pad_clearance)

mid-height, but never so low that the palm (``palm_clearance`` > ``palm_above``) meets the top
of a tall object, nor the fingertips the desk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.perception.locate import box_iou

__all__ = ["TopSurface", "box_points", "desk_height", "grasp_height", "surfaces", "top_surface"]


@dataclass(frozen=True)
class TopSurface:
    """``p_top`` (3,): top center (x, y) at the top height, m, ``arm_base``; ``z_desk``: the
    desk height under the object (m); ``n_top``/``n_fg``: pixels in the top band / foreground;
    ``axis_xy``: unit direction (2,) in the ``arm_base`` x-y plane of the long axis of the top
    band (a lying stick's ridge), ``None`` when it has no clear long axis (the top of a ball,
    cube or upright cylinder: eigenvalue ratio below ``axis_ratio``)."""

    p_top: Array
    z_desk: float
    n_top: int
    n_fg: int
    axis_xy: Array | None


def _clip_box(box: Array, w: int, h: int) -> tuple[int, int, int, int]:
    b = np.asarray(box, float)
    if b.shape != (4,) or not np.all(np.isfinite(b)) or b[2] <= b[0] or b[3] <= b[1]:
        raise InvalidInputError(f"box must be finite [x1, y1, x2, y2] with x2 > x1, y2 > y1: {b}")
    x1, y1 = int(np.clip(np.floor(b[0]), 0, w)), int(np.clip(np.floor(b[1]), 0, h))
    x2, y2 = int(np.clip(np.ceil(b[2]), 0, w)), int(np.clip(np.ceil(b[3]), 0, h))
    return x1, y1, x2, y2


def box_points(
    depth: Array, K: Array, T_arm_base_camera: Array, uu: Array, vv: Array
) -> tuple[Array, Array]:
    """Deproject pixels ``(uu, vv)`` (N,) int with valid depth (> 0) to ``arm_base``:
    returns ``(points (M, 3) m, keep (N,) bool)``."""
    z = np.asarray(depth)[vv, uu].astype(float)
    keep = np.isfinite(z) & (z > 0)
    z = z[keep]
    K = np.asarray(K, float)
    x = (uu[keep] - K[0, 2]) / K[0, 0] * z
    y = (vv[keep] - K[1, 2]) / K[1, 1] * z
    T = np.asarray(T_arm_base_camera, float)
    p = np.stack([x, y, z], axis=1) @ T[:3, :3].T + T[:3, 3]
    return p, keep


def desk_height(
    depth: Array,
    K: Array,
    T_arm_base_camera: Array,
    box: Array,
    margin: float = 0.15,
    percentile: float = 30.0,
    min_points: int = 5,
) -> float | None:
    """Height (m, ``arm_base`` z) of the surface around ``box``: the ``percentile`` of the
    heights on the rectangle ``margin`` x the longer box side (+ 4 px) outside the box (48
    samples); ``None`` when fewer than ``min_points`` have depth."""
    d = np.asarray(depth)
    h, w = d.shape
    x1, y1, x2, y2 = (float(v) for v in np.asarray(box, float))
    m = margin * max(x2 - x1, y2 - y1) + 4
    xs = np.clip(np.array([x1 - m, x2 + m]), 0, w - 1)
    ys = np.clip(np.array([y1 - m, y2 + m]), 0, h - 1)
    lu = np.linspace(xs[0], xs[1], 12).astype(int)
    lv = np.linspace(ys[0], ys[1], 12).astype(int)
    uu = np.concatenate([lu, lu, np.full(12, int(xs[0])), np.full(12, int(xs[1]))])
    vv = np.concatenate([np.full(12, int(ys[0])), np.full(12, int(ys[1])), lv, lv])
    p, _ = box_points(d, K, T_arm_base_camera, uu, vv)
    if len(p) < min_points:
        return None
    return float(np.percentile(p[:, 2], percentile))


def surfaces(points: Array, depth: Array, gap: float) -> tuple[int, Array]:
    """Connected surfaces of a grid of points: ``points`` (H, W, 3) m and ``depth`` (H, W) m
    (0 or NaN: no point, never connected); 4-neighbours join when their points lie closer
    than ``gap`` (scalar m, or (H, W) per pixel: the larger of the pair's). Returns
    ``(n, labels (H, W) int)``, -1 where there is no point."""
    P = np.asarray(points, float)
    z = np.asarray(depth, float)
    h, w = z.shape
    ok = np.isfinite(z) & (z > 0)
    g = np.broadcast_to(np.asarray(gap, float), (h, w))
    idx = np.arange(h * w).reshape(h, w)
    rows, cols = [], []
    for a, b in ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1, :], np.s_[1:, :])):
        d = np.linalg.norm(P[a] - P[b], axis=-1)
        join = ok[a] & ok[b] & (d < np.maximum(g[a], g[b]))
        rows.append(idx[a][join])
        cols.append(idx[b][join])
    r, c = np.concatenate(rows), np.concatenate(cols)
    adj = coo_matrix((np.ones(len(r), bool), (r, c)), shape=(h * w, h * w))
    _, lab = connected_components(adj, directed=False)
    lab = lab.reshape(h, w)
    keep = np.unique(lab[ok])
    relabel = np.full(h * w, -1)
    relabel[keep] = np.arange(len(keep))
    out = np.where(ok, relabel[np.maximum(lab, 0)], -1)
    return len(keep), out


def top_surface(
    depth: Array,
    K: Array,
    T_arm_base_camera: Array,
    box: Array,
    z_desk: float,
    fg_min: float = 0.008,
    top_band: float = 0.012,
    top_percentile: float = 97.0,
    stride: int = 2,
    min_points: int = 12,
    axis_ratio: float = 2.25,
    gap_abs: float = 0.005,
    gap_rel: float = 3.0,
    fit_keep: float = 0.5,
) -> TopSurface | None:
    """The object's top center in ``arm_base`` from the box pixels above ``z_desk`` (every
    ``stride``-th pixel) on the foreground surface that fits the box best (module doc;
    ``gap_rel <= 0`` and ``gap_abs <= 0``: all the foreground, no split); ``None`` when fewer
    than ``min_points`` foreground pixels have depth (object out of the camera's range, box on
    a hole)."""
    d = np.asarray(depth)
    if d.ndim != 2:
        raise InvalidInputError(f"depth must be (H, W), got {d.shape}")
    h, w = d.shape
    x1, y1, x2, y2 = _clip_box(box, w, h)
    vv, uu = np.mgrid[y1:y2:stride, x1:x2:stride]
    shape = uu.shape
    uu, vv = uu.ravel(), vv.ravel()
    p, keep = box_points(d, K, T_arm_base_camera, uu, vv)
    fg = p[:, 2] > z_desk + fg_min
    if int(fg.sum()) < min_points:
        return None
    if gap_abs > 0 or gap_rel > 0:
        # the foreground's surfaces on the pixel grid; the one that fits the box best
        P = np.full((uu.size, 3), np.nan)
        P[keep] = p
        zc = np.zeros(uu.size)
        zc[np.flatnonzero(keep)[fg]] = d[vv, uu][keep][fg]
        foot = zc * stride / float(np.asarray(K)[0, 0])  # pixel footprint (m) at that depth
        n, lab = surfaces(
            P.reshape(*shape, 3), zc.reshape(shape), gap_abs + gap_rel * foot.reshape(shape)
        )
        lab = lab.ravel()[keep]  # per point of p
        uk, vk = uu[keep], vv[keep]  # the pixel of each point of p
        fits = []  # (IoU with the box, median height, label)
        for k in range(n):
            m = lab == k
            if m.sum() < min_points:
                continue
            u, v = uk[m], vk[m]
            fit = (u.min(), v.min(), u.max() + stride, v.max() + stride)
            iou = float(box_iou(fit, (x1, y1, x2, y2))[0, 0])
            fits.append((iou, float(np.median(p[m, 2])), k))
        if not fits:
            return None
        best_iou = max(f[0] for f in fits)
        # of the surfaces that fit the box nearly as well as the best, the one standing highest
        # (median height: the desk counted as foreground under a wrong desk height fills the
        # box too, in pieces, and a piece may hold a taller object's wall and rim)
        best = max((f for f in fits if f[0] >= fit_keep * best_iou), key=lambda f: f[1])[2]
        fg = lab == best
    n_fg = int(fg.sum())
    pf = p[fg]
    z_top = float(np.percentile(pf[:, 2], top_percentile))
    band = pf[:, 2] >= z_top - top_band
    top = pf[band, :2]
    xy = top.mean(axis=0)
    axis = None
    if len(top) >= 3:  # long axis of the top band (variance ratio = squared length ratio)
        ev, V = np.linalg.eigh(np.cov(top.T))
        if ev[1] >= axis_ratio * max(ev[0], 1e-12):
            axis = V[:, 1]
    return TopSurface(
        p_top=np.array([xy[0], xy[1], z_top]),
        z_desk=float(z_desk),
        n_top=int(band.sum()),
        n_fg=n_fg,
        axis_xy=axis,
    )


def grasp_height(
    z_top: float,
    z_desk: float,
    pad_clearance: float = 0.024,
    palm_clearance: float = 0.065,
) -> float:
    """TCP height (m) of a top-down grasp: mid-height of the object, but at most
    ``palm_clearance`` below its top (the palm stays over a tall object) and at least
    ``pad_clearance`` above the desk (fingertips off the desk)."""
    if not (np.isfinite(z_top) and np.isfinite(z_desk)) or z_top < z_desk:
        raise InvalidInputError(f"object top {z_top} must be finite and above the desk {z_desk}")
    mid = 0.5 * (z_top + z_desk)
    return float(max(mid, z_top - palm_clearance, z_desk + pad_clearance))
