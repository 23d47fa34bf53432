"""ChArUco board detection and pose: pure functions over images and arrays.

``detect_charuco`` finds the board's inner chessboard corners in a colour image (OpenCV's
``CharucoDetector``: ArUco markers first, then the corners between them, refined to subpixel
by interpolation through the markers' homography); ``estimate_board_pose`` solves PnP on
them with the frame's intrinsics and reports the reprojection RMS.

Frames: the board frame is OpenCV's (origin at the outer corner of the first chessboard
square, x along the rows of squares, y along the columns, z into the board); the camera
frame is the optical frame (z forward, x right, y down). Units: m, pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.core.geometry import Array, make_T
from mmpa.maps.board import CharucoBoardSpec

__all__ = [
    "BoardNotFoundError",
    "CharucoBoardSpec",
    "CharucoDetection",
    "CharucoPose",
    "board_pose",
    "detect_charuco",
    "estimate_board_pose",
]


class BoardNotFoundError(MMPAError):
    """Too few ChArUco corners in the image to measure the board's pose."""


@dataclass(frozen=True)
class CharucoDetection:
    """Corners found in one image: ``ids`` (N,) int of the board's inner corners,
    ``image_points`` (N, 2) px, ``object_points`` (N, 3) m in the board frame, and
    ``n_markers`` the ArUco markers decoded."""

    ids: np.ndarray
    image_points: Array
    object_points: Array
    n_markers: int

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass(frozen=True)
class CharucoPose:
    """The board's pose in the camera optical frame, ``T_camera_board`` (4x4, m), from
    ``n_corners`` corners with reprojection RMS ``rms_px`` (max ``max_px``)."""

    T_camera_board: Array
    rms_px: float
    max_px: float
    n_corners: int
    detection: CharucoDetection


def _gray(image: np.ndarray) -> np.ndarray:

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    elif img.ndim != 2:
        raise InvalidInputError(f"need an (H, W) or (H, W, 3) image, got shape {img.shape}")
    if img.dtype != np.uint8:
        if np.issubdtype(img.dtype, np.floating):
            img = np.clip(np.round(img * 255.0 if img.max() <= 1.0 else img), 0, 255)
        img = img.astype(np.uint8)
    return np.ascontiguousarray(img)


def detect_charuco(image: np.ndarray, board: object) -> CharucoDetection:
    """ChArUco corners of ``board`` (a ``cv2.aruco.CharucoBoard``) in ``image`` (H, W, 3)
    RGB or (H, W) grey, uint8 (floats in [0, 1] or [0, 255] are converted). No corner:
    an empty detection (N = 0), not an error."""

    gray = _gray(image)
    params = cv2.aruco.CharucoParameters()
    det_params = cv2.aruco.DetectorParameters()
    det_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.CharucoDetector(board, params, det_params)
    corners, ids, _marker_corners, marker_ids = detector.detectBoard(gray)
    n_markers = 0 if marker_ids is None else len(marker_ids)
    if ids is None or len(ids) == 0:
        return CharucoDetection(np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 3)), n_markers)
    ids = np.asarray(ids, int).ravel()
    all_obj = np.asarray(board.getChessboardCorners(), float).reshape(-1, 3)  # type: ignore[attr-defined]
    return CharucoDetection(
        ids=ids,
        image_points=np.asarray(corners, float).reshape(-1, 2),
        object_points=all_obj[ids],
        n_markers=n_markers,
    )


def estimate_board_pose(
    detection: CharucoDetection,
    K: Array,
    dist: Array | None = None,
    min_corners: int = 8,
) -> CharucoPose:
    """``T_camera_board`` from the detected corners: iterative PnP (Levenberg-Marquardt on
    the reprojection error, started from the planar homography solution, OpenCV's
    ``SOLVEPNP_IPPE``) with intrinsics ``K`` (3, 3) and distortion ``dist`` (OpenCV order,
    default none). Reprojection residual ``r_k = pi(K, T p_k) - u_k`` (px):
    ``rms_px = sqrt(mean |r_k|^2)``. Raises :class:`BoardNotFoundError` below
    ``min_corners`` corners (a pose from fewer, nearly collinear corners is unreliable)."""

    K = np.asarray(K, float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InvalidInputError(f"K must be a finite 3x3 camera matrix, got shape {K.shape}")
    if min_corners < 4:
        raise InvalidInputError(f"min_corners must be >= 4 (PnP), got {min_corners}")
    n = len(detection)
    if n < min_corners:
        raise BoardNotFoundError(
            f"found {n} ChArUco corners ({detection.n_markers} markers), need {min_corners}"
        )
    d = np.zeros(5) if dist is None else np.asarray(dist, float).ravel()
    obj = detection.object_points.astype(np.float64)
    img = detection.image_points.astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, d, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise BoardNotFoundError(f"PnP failed on {n} corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, d, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, d)
    r = proj.reshape(-1, 2) - img
    e = np.linalg.norm(r, axis=1)
    R, _ = cv2.Rodrigues(rvec)
    T = make_T(R, tvec.ravel())
    if T[2, 3] <= 0:
        raise BoardNotFoundError("PnP put the board behind the camera")
    return CharucoPose(
        T_camera_board=T,
        rms_px=float(np.sqrt(np.mean(e**2))),
        max_px=float(e.max()),
        n_corners=n,
        detection=detection,
    )


def board_pose(image: np.ndarray, board: object, K: Array, min_corners: int = 8) -> CharucoPose:
    """Detect and solve in one call (:func:`detect_charuco`, :func:`estimate_board_pose`)."""
    return estimate_board_pose(detect_charuco(image, board), K, min_corners=min_corners)
