"""A ChArUco calibration board's specification: squares, markers, dictionary, print size,
and the board frame in the frame of the box that carries it.

Frames: the board frame is OpenCV's (origin at the outer corner of the first chessboard
square, x along the rows of squares, y along the columns, z into the board). Units: m.
The texture spans the top (+z) face of a box geom ``g`` (centre, z up), image top-left at
the face's (-x, +y) corner, so ``T_g_board = [diag(1, -1, -1) | (-w / 2 + margin,
h / 2 - margin, thickness / 2)]`` (:attr:`CharucoBoardSpec.T_geom_board`).
"""

from __future__ import annotations

from functools import cached_property

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from mmpa.core.geometry import Array, make_T

__all__ = ["CharucoBoardSpec"]


_DICTS = (
    "DICT_4X4_50",
    "DICT_4X4_100",
    "DICT_5X5_50",
    "DICT_5X5_100",
    "DICT_6X6_50",
    "DICT_6X6_250",
)


class CharucoBoardSpec(BaseModel):
    """A ChArUco board: ``squares_x`` x ``squares_y`` chessboard squares of ``square`` m with
    ArUco markers of ``marker`` m from ``dictionary`` in the white squares, printed with a
    white ``margin`` m around it, ``thickness`` m thick; the texture has ``px_per_m`` pixels
    per metre. Default: 7 x 5 squares of 40 mm (24 inner corners), 30 mm markers."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    squares_x: int = Field(7, ge=3, le=20)
    squares_y: int = Field(5, ge=3, le=20)
    square: float = Field(0.04, gt=0, le=0.5)
    marker: float = Field(0.03, gt=0, le=0.5)
    dictionary: str = "DICT_5X5_100"
    margin: float = Field(0.02, ge=0, le=0.2)
    thickness: float = Field(0.004, gt=0, le=0.05)
    px_per_m: float = Field(2500.0, ge=500, le=10000)

    @model_validator(mode="after")
    def _check(self) -> CharucoBoardSpec:
        if self.marker >= self.square:
            raise ValueError(
                f"marker ({self.marker} m) must be smaller than square ({self.square} m)"
            )
        if self.dictionary not in _DICTS:
            raise ValueError(f"dictionary {self.dictionary!r} unknown; one of {list(_DICTS)}")
        return self

    @property
    def size(self) -> tuple[float, float]:
        """``(width, height)`` of the chessboard area (m)."""
        return self.squares_x * self.square, self.squares_y * self.square

    @property
    def face_size(self) -> tuple[float, float]:
        """``(width, height)`` of the printed face, margin included (m)."""
        w, h = self.size
        return w + 2 * self.margin, h + 2 * self.margin

    @property
    def n_corners(self) -> int:
        """Inner chessboard corners (the ChArUco corners)."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    def cv_board(self) -> object:
        """The :class:`cv2.aruco.CharucoBoard` (OpenCV >= 4.7 layout, not the legacy one)."""

        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square, self.marker, d)

    def corners(self) -> Array:
        """(N, 3) ChArUco corners in the board frame (m), N = :attr:`n_corners`."""
        return np.asarray(self.cv_board().getChessboardCorners(), float).reshape(-1, 3)

    def image(self) -> np.ndarray:
        """The printed face as an RGB uint8 image (H, W, 3): the board plus its margin."""
        w, h = self.size
        m = round(self.margin * self.px_per_m)
        size = (round(w * self.px_per_m) + 2 * m, round(h * self.px_per_m) + 2 * m)
        gray = self.cv_board().generateImage(size, marginSize=m, borderBits=1)
        return np.repeat(np.asarray(gray, np.uint8)[..., None], 3, axis=2)

    @cached_property
    def T_geom_board(self) -> Array:
        """Board frame in the box geom's frame (module docstring)."""
        w, h = self.face_size
        R = np.diag([1.0, -1.0, -1.0])
        return make_T(R, (-w / 2 + self.margin, h / 2 - self.margin, self.thickness / 2))
