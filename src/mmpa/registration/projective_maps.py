"""The images of the projective refinement (:mod:`mmpa.registration.projective`).

The target's organized depth image (H, W) m along the camera's optical axis, pinhole
intrinsics ``fx, fy, cx, cy`` (px): the vertex map ``V(u, v) = z (x_u, y_v, 1)`` with
``x_u = (u - cx) / fx``, ``y_v = (v - cy) / fy``; holes filled from the nearest valid pixel
within ``hole_fill_px`` (chessboard); the unit normal at a pixel
``n = dx x dy / |dx x dy|``, ``dx = V(u+r, v) - V(u-r, v)``, ``dy = V(u, v+r) - V(u, v-r)``
(central differences over ``r = normal_radius`` px, invalid across depth jumps larger than
``max_depth_jump``), computed on first use and kept (:class:`TargetMap`). The grey images of
the photometric term (luma in [0, 1]), bilinear sampling, and the IRLS weights of the robust
kernels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.robot.description import CameraIntrinsics

__all__ = [
    "TargetMap",
    "bilinear",
    "grey",
    "normal_map",
    "photometric_inputs",
    "robust_weights",
    "source_grey_levels",
    "target_at",
    "target_map",
    "vertex_map",
]


def robust_weights(r: Array, c: float, kernel: str = "huber") -> Array:
    """IRLS weights of residuals ``r`` (m) for a robust kernel of scale ``c`` (m):
    ``"huber"`` ``w = min(1, c / |r|)``; ``"geman_mcclure"`` ``w = 1 / (1 + (r / c)^2)^2``
    (the weight of ``rho(r) = (r^2 / 2) / (1 + (r / c)^2)``, ``w = rho'(r) / r``)."""
    a = np.abs(np.asarray(r, dtype=float))
    if kernel == "huber":
        return np.where(a <= c, 1.0, c / np.maximum(a, 1e-300))
    if kernel == "geman_mcclure":
        return 1.0 / np.square(1.0 + np.square(a / c))
    raise InvalidInputError(f"unknown robust kernel {kernel!r}; use 'huber' or 'geman_mcclure'")


def vertex_map(depth: Array, intr: CameraIntrinsics) -> Array:
    """``V(u, v) = z (u - cx)/fx, z (v - cy)/fy, z`` (H, W, 3) m; zero where ``depth <= 0``."""
    z = np.asarray(depth, dtype=float)
    if z.shape != (intr.height, intr.width):
        raise InvalidInputError(
            f"depth {z.shape} does not match the intrinsics {intr.height}x{intr.width}"
        )
    z = np.where(np.isfinite(z) & (z > 0), z, 0.0)
    u = (np.arange(intr.width) - intr.cx) / intr.fx
    v = (np.arange(intr.height) - intr.cy) / intr.fy
    return np.stack([z * u[None, :], z * v[:, None], z], axis=-1)


def normal_map(V: Array, radius: int, max_jump: float) -> tuple[Array, Array]:
    """Unit normals (H, W, 3) of a vertex map by central differences over ``radius`` px,
    oriented toward the camera, and the validity mask (H, W): all four neighbours valid and
    within ``max_jump`` in depth of the centre."""
    r = int(radius)
    H, W, _ = V.shape
    z = V[..., 2]
    valid = np.zeros((H, W), bool)
    N = np.zeros_like(V)
    c = (slice(r, H - r), slice(r, W - r))
    zc = z[c]
    zl, zr = z[r : H - r, : W - 2 * r], z[r : H - r, 2 * r :]
    zu, zd = z[: H - 2 * r, r : W - r], z[2 * r :, r : W - r]
    ok = (zc > 0) & (zl > 0) & (zr > 0) & (zu > 0) & (zd > 0)
    for zz in (zl, zr, zu, zd):
        ok &= np.abs(zz - zc) < max_jump
    dx = V[r : H - r, 2 * r :] - V[r : H - r, : W - 2 * r]
    dy = V[2 * r :, r : W - r] - V[: H - 2 * r, r : W - r]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1)
    ok &= norm > 0
    n = n / np.where(norm > 0, norm, 1.0)[..., None]
    flip = np.einsum("hwi,hwi->hw", n, V[c]) > 0
    n[flip] *= -1.0
    N[c] = n
    valid[c] = ok
    return N, valid


def grey(rgb: Array) -> Array:
    """Luma ``0.299 R + 0.587 G + 0.114 B`` in [0, 1] of RGB values (uint8 or floats in [0, 1]),
    shape ``rgb.shape[:-1]``."""
    c = np.asarray(rgb)
    f = c.astype(float) / 255.0 if c.dtype == np.uint8 else c.astype(float)
    return f @ np.array([0.299, 0.587, 0.114])


def photometric_inputs(
    points: Array, colors: Array, target_color: Array, intr: CameraIntrinsics
) -> tuple[Array, Array]:
    """Checked photometric inputs: the source points' grey values (N,) and the target's grey
    image (H, W)."""
    P = np.asarray(points)
    c = np.asarray(colors)
    if c.ndim != 2 or c.shape != (len(P), 3):
        raise InvalidInputError(
            f"source colours must be (N, 3) for the {len(P)} source points, got {c.shape}"
        )
    img = np.asarray(target_color)
    if img.shape != (intr.height, intr.width, 3):
        raise InvalidInputError(
            f"target colour image {img.shape} does not match the intrinsics "
            f"{intr.height}x{intr.width}x3"
        )
    g = grey(c)
    if not np.isfinite(g).all():
        raise InvalidInputError("source colours hold NaN or inf")
    return g, grey(img)


def bilinear(img: Array, u: Array, v: Array) -> Array:
    """Bilinear samples of ``img`` (H, W, C) at continuous pixel coordinates (callers keep
    ``0 <= u < W - 1``, ``0 <= v < H - 1``); shape (M, C)."""
    H, W, C = img.shape
    flat = img.reshape(H * W, C)
    u0 = np.floor(u).astype(np.intp)
    v0 = np.floor(v).astype(np.intp)
    a = (u - u0)[:, None]
    b = (v - v0)[:, None]
    i = v0 * W + u0
    return (1 - b) * ((1 - a) * flat[i] + a * flat[i + 1]) + b * (
        (1 - a) * flat[i + W] + a * flat[i + W + 1]
    )


def source_grey_levels(
    P: Array, g: Array, intr: CameraIntrinsics, sds: Sequence[float], keep: Array
) -> list[Array]:
    """The source's grey values ``g`` (N,) blurred like the target image by a Gaussian of
    each SD in ``sds`` (px; 0: unblurred), at the points ``keep`` (K,) of ``P`` (N, 3): the
    points (taken from the source camera's pixel grid) are put back on it once, blurred by
    normalized convolution (holes do not darken), and read back at their pixels; one (K,)
    array per SD."""
    H, W = intr.height, intr.width
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(intr.fx * P[:, 0] / P[:, 2] + intr.cx)
        v = np.rint(intr.fy * P[:, 1] / P[:, 2] + intr.cy)
    ok = (P[:, 2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    pix = v[ok].astype(np.intp) * W + u[ok].astype(np.intp)
    S = np.bincount(pix, weights=g[ok], minlength=H * W).astype(float).reshape(H, W)
    M = np.bincount(pix, minlength=H * W).astype(float).reshape(H, W)
    ok_k = ok[keep]
    uk, vk = u[keep][ok_k].astype(np.intp), v[keep][ok_k].astype(np.intp)
    out = []
    for sd in sds:
        gk = g[keep].copy()
        if sd > 0:
            Sb = ndimage.gaussian_filter(S, sd)
            Mb = ndimage.gaussian_filter(M, sd)
            with np.errstate(divide="ignore", invalid="ignore"):
                blurred = Sb[vk, uk] / Mb[vk, uk]
            gk[ok_k] = np.where(np.isfinite(blurred), blurred, gk[ok_k])
        out.append(gk)
    return out


@dataclass(frozen=True)
class TargetMap:
    """The target's depth image flattened (``H * W``), each pixel's vertex ``fill_x, fill_y,
    fill_z`` (m; that of the nearest valid pixel within ``hole_fill_px``, 0 where none) and
    the cache of :func:`target_at`: rows ``[q, n]`` of ``tgt`` (H W, 6), their validity
    ``tgt_ok`` and ``have`` (computed yet); ``n_valid`` the valid pixels of the image."""

    H: int
    W: int
    fill_z: Array
    fill_x: Array
    fill_y: Array
    n_valid: int
    rad: int
    max_depth_jump: float
    tgt: Array
    tgt_ok: Array
    have: Array


def target_map(
    target_depth: Array,
    intrinsics: CameraIntrinsics,
    normal_radius: int,
    max_depth_jump: float,
    hole_fill_px: int,
    hole_fill_max_valid: float,
) -> TargetMap:
    """The :class:`TargetMap` of ``target_depth`` (H, W) m (0 or non-finite: invalid)."""
    z_img = np.asarray(target_depth, dtype=float)
    if z_img.shape != (intrinsics.height, intrinsics.width):
        raise InvalidInputError(
            f"depth {z_img.shape} does not match the intrinsics "
            f"{intrinsics.height}x{intrinsics.width}"
        )
    H, W = z_img.shape
    # depth image flattened, 0 where invalid; the vertex map V(u, v) = z (x_u, y_v, 1)
    # (x_u = (u - cx)/fx, y_v = (v - cy)/fy)
    zf = np.where(np.isfinite(z_img) & (z_img > 0), z_img, 0.0).ravel()
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    xu = (np.arange(W) - cx) / fx
    yv = (np.arange(H) - cy) / fy
    valid = zf > 0
    n_valid = int(np.count_nonzero(valid))
    if n_valid < hole_fill_max_valid * H * W and hole_fill_px > 0:
        # holes (a sparse or hole-gridded depth image): each pixel's vertex is that of the
        # nearest valid pixel within hole_fill_px (none beyond)
        dist, (iy, ix) = ndimage.distance_transform_cdt(
            ~valid.reshape(H, W), metric="chessboard", return_indices=True
        )
        fill = np.where(dist.ravel() <= hole_fill_px, (iy * W + ix).ravel(), -1)
        fill_z = np.where(fill >= 0, zf[np.maximum(fill, 0)], 0.0)
        fill_x = fill_z * xu[np.maximum(fill, 0) % W]
        fill_y = fill_z * yv[np.maximum(fill, 0) // W]
    else:
        fill_z = zf
        fill_x = (zf.reshape(H, W) * xu[None, :]).ravel()
        fill_y = (zf.reshape(H, W) * yv[:, None]).ravel()
    # the target's vertex q = V(u, v) and unit normal n = dx x dy / |dx x dy| at a pixel,
    # dx = V(u+r, v) - V(u-r, v), dy = V(u, v+r) - V(u, v-r) (r = normal_radius, each vertex
    # at the nearest valid pixel within hole_fill_px), kept as rows [q, n] of ``tgt`` once
    # computed (the refinement's iterations hit nearly the same pixels again); tgt_ok: all
    # five vertices valid, the four within max_depth_jump of the centre, the normal defined
    return TargetMap(
        H,
        W,
        fill_z,
        fill_x,
        fill_y,
        n_valid,
        normal_radius,
        max_depth_jump,
        np.empty((H * W, 6)),
        np.zeros(H * W, bool),
        np.zeros(H * W, bool),
    )


def target_at(tm: TargetMap, pix: Array) -> tuple[Array, Array]:
    """``tgt`` rows (M, 6) and ``tgt_ok`` (M,) at the flat pixels ``pix`` (M,), each at
    least ``r`` px inside the image (computed on first use, then kept in ``tm``)."""
    rad, W = tm.rad, tm.W
    fill_z, fill_x, fill_y = tm.fill_z, tm.fill_x, tm.fill_y
    new = pix[~tm.have[pix]]
    if len(new):
        zc, xc, yc = fill_z[new], fill_x[new], fill_y[new]
        ok = zc > 0
        nb = []
        for d in (-rad, rad, -rad * W, rad * W):  # left, right, up, down
            z_, x_, y_ = fill_z[new + d], fill_x[new + d], fill_y[new + d]
            ok &= (z_ > 0) & (np.abs(z_ - zc) < tm.max_depth_jump)
            nb.append((x_, y_, z_))
        (xl, yl, zl), (xr, yr, zr), (xu_, yu, zu), (xd, yd, zd) = nb
        ax, ay, az = xr - xl, yr - yl, zr - zl
        bx, by, bz = xd - xu_, yd - yu, zd - zu
        nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        ok &= norm > 0
        norm[~ok] = 1.0
        tm.tgt[new] = np.column_stack([xc, yc, zc, nx / norm, ny / norm, nz / norm])
        tm.tgt_ok[new] = ok
        tm.have[new] = True
    return tm.tgt[pix], tm.tgt_ok[pix]
