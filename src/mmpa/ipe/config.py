"""IPE parameters and results (paper 000 §3.2.2, Fig. 4; §4.3 for ``alpha`` and ``beta``).

Units: m and rad (``alpha`` as ``(x, y, z, roll, pitch, yaw)``), seconds for timings.
Frames (:mod:`mmpa.ipe.core`): ``T_Bk_Ck`` the nominal camera pose in the arm base at the
k-th view, ``dT_C`` the registration (eq. 3), ``dT_B`` the parking offset of the arm base
(eq. 4, from eq. 9-10). :meth:`IPEConfig.paper` is the paper's own IPE; the defaults add
what is marked "beyond the paper" (measurements: docs/ipe.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from mmpa.core.geometry import Array
from mmpa.ipe.core import DEFAULT_ALPHA, alpha_vector
from mmpa.registration import (
    IcpScale,
    ProjectiveConfig,
    ProjectiveResult,
    Registration,
    RegistrationConfig,
)

__all__ = ["FINAL_REFINEMENT", "PRIOR_SCALES", "IPEConfig", "IPEIteration", "IPEResult"]


#: the finer last registration: every 2nd pixel, 4 mm voxels, 15 colored-ICP iterations
FINAL_REFINEMENT = RegistrationConfig(
    presample=2, init_scales=(IcpScale(voxel=0.004, max_distance=0.006, max_iter=15),)
)

#: first registration from the localization prior: the 2D prior misses z, roll and pitch
#: (terrain), so start coarse with a wide gate and accept a larger correction
PRIOR_SCALES = (
    IcpScale(voxel=0.02, max_distance=0.08, max_iter=15),
    IcpScale(voxel=0.02, max_distance=0.04, max_iter=10),
    IcpScale(voxel=0.01, max_distance=0.015, max_iter=10),
)


class IPEConfig(BaseModel):
    """IPE parameters (paper 000 §4.3 defaults for alpha and beta)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    alpha: tuple[float, float, float, float, float, float] = DEFAULT_ALPHA  # m x3, rad x3
    beta: int = Field(5, ge=1)  # the paper uses 10 at Site 2'
    frames: int = Field(4, ge=1)  # captures averaged per view (paper: 1)
    use_color: bool = True  # False: drop colors, point-to-plane ICP (paper Table A.7 A.0/B.0)
    global_each_iteration: bool = False  # paper: True (FGR + colored ICP every time)
    min_depth: float = Field(0.2, gt=0)  # m, crop of the captured cloud
    max_depth: float = Field(1.5, gt=0)
    # beyond the paper: views are approached at this fraction of the joint velocity and
    # acceleration limits (None: as fast as the arm goes; a full-speed swing of the base
    # joint shoves the parked base: docs/ipe.md)
    move_speed: float | None = Field(0.3, gt=0, le=1)
    retreat: float = Field(0.15, ge=0)  # m the camera backs off when the first view fails
    prior_max_shift: float = Field(0.12, gt=0)  # m: correction accepted from the prior
    prior_max_rotation: float = Field(np.deg2rad(12.0), gt=0)  # rad
    max_translation: float = Field(1.0, gt=0)  # m: larger |dT_B| is implausible -> False
    max_rotation: float = Field(np.deg2rad(60.0), gt=0)  # rad
    # the competing-pose check (mmpa.registration.ambiguity) off: IPE registers every view
    # after the first from the previous estimate, so a wrong global first view only aims the
    # next one; the check costs ~0.35 s of the 0.5 s IPE compute target (docs/registration.md)
    registration: RegistrationConfig = RegistrationConfig(ambiguity_check="off")
    # beyond the paper: once converged, a projective point-to-plane refinement of the last
    # view at full resolution on its depth image (no voxel aliasing; estimates the relative
    # depth scale too), starting from the converged dT_C; None: off
    projective: ProjectiveConfig | None = ProjectiveConfig()
    # when the projective refinement is off or refused (e.g. a textured plane: point-to-plane
    # alone is degenerate there), one more colored registration at 4 mm voxels; None: off
    final: RegistrationConfig | None = FINAL_REFINEMENT
    # beyond the paper: a witness view (m sideways; None: off). Once converged, the camera
    # moves this far along its x axis from the taught viewpoint (by the estimate), and the
    # taught cloud is registered there too (ICP from the estimate's prediction, then the
    # projective and photometric refinements of the converged view): the two estimates of
    # the one parking offset must agree within ``witness_tolerance`` (m at the taught
    # camera, rad; :func:`view_consistency`), else no estimate. Two views near the taught one
    # are equivalent witnesses (the session's depth distortion cancels alike in both); a
    # registration that slid into a wrong minimum does not repeat from another viewpoint.
    # Costs an arm move, a capture and a registration (docs/ipe.md).
    witness: float | None = Field(None, gt=0)
    witness_tolerance: tuple[float, float] = (0.002, float(np.deg2rad(0.3)))

    @field_validator("alpha")
    @classmethod
    def _alpha(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        alpha_vector(v)
        return v

    @classmethod
    def paper(cls, **changes: object) -> IPEConfig:
        """The paper's own IPE settings (paper 000 §3.2, §4.3): one frame per view, global
        registration (FGR + colored ICP) every iteration, colored ICP whenever both clouds
        carry colour, no retreat, no projective or final refinement; ``changes`` on top
        (e.g. ``beta=10`` at Site 2')."""
        base = cls()
        reg = RegistrationConfig.paper()
        fields = {
            "frames": 1,
            "global_each_iteration": True,
            "retreat": 0.0,
            "projective": None,
            "final": None,
            "registration": reg,
        }
        return cls.model_validate({**base.model_dump(), **fields, **changes})


@dataclass(frozen=True)
class IPEIteration:
    """One pass of the loop: the joints the camera sampled at, the nominal ``T_Bk_Ck``, the
    registration (``dT_C`` = ``registration.T``), the updated ``dT_B`` and timings (s)."""

    k: int
    q: Array
    T_Bk_Ck: Array
    registration: Registration
    dT_B: Array | None
    difference: Array  # |[tx, ty, tz, r, p, y]| of dT_C (m, rad)
    seconds_move: float
    seconds_capture: float
    seconds_register: float
    # the projective refinement of this view (when on and the registration succeeded); when
    # ok, ``dT_B`` and ``difference`` come from it instead of ``registration.T``
    projective: ProjectiveResult | None = None


@dataclass
class IPEResult:
    """Outcome of IPE: ``ok`` (the execution flag of Fig. 4), ``dT_B`` (4x4; None on failure),
    a ``reason`` when not ok, and every iteration."""

    ok: bool
    dT_B: Array | None
    reason: str = ""
    iterations: list[IPEIteration] = field(default_factory=list)
    seconds_prepare: float = 0.0
    final: Registration | None = None  # the 4 mm fallback refinement (when it ran)
    # the full-resolution refinement of the converged view (depth + colour when on)
    projective: ProjectiveResult | None = None
    seconds_final: float = 0.0  # the converged view's photometric / 4 mm refinement
    # the witness view (``IPEConfig.witness``): its estimate of dT_B, how far it lies from
    # the result's ((m at the taught camera, rad); :func:`view_consistency`), its seconds
    witness_dT_B: Array | None = None
    witness_disagreement: tuple[float, float] | None = None
    seconds_witness: float = 0.0

    @property
    def n_iterations(self) -> int:
        return len(self.iterations)

    @property
    def seconds_compute(self) -> float:
        """Registration and preparation time (excludes arm motion and capture)."""
        return (
            self.seconds_prepare
            + self.seconds_final
            + self.seconds_witness
            + sum(it.seconds_register for it in self.iterations)
        )

    @property
    def estimates(self) -> list[Array]:
        """``dT_B`` after every iteration (Fig. 9)."""
        return [it.dT_B for it in self.iterations if it.dT_B is not None]
