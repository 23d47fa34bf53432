"""The localization settings of a run, one model for the robot file, ``--config`` and ``--set``.

:class:`LocalizationConfig` holds the method and the settings of every method: ``amcl``
(:class:`~mmpa.localization.config.AMCLConfig`, Nav2's ``amcl`` parameter names: ``alpha1``,
``laser_model_type``, ``max_particles``, ``z_hit``, ``sigma_hit``, ``update_min_d``, ...; the
AMCL of ``amcl``, and the fields it changes of the AMCL inside ``enhanced``, ``enhanced-paper``
and ``tamcl``, which is otherwise Nav2's: :func:`amcl_of`), ``enhanced``
(:class:`~mmpa.localization.config.EnhancedConfig`, paper 001 Algorithm 1; its AMCL is
``amcl``, so ``enhanced.amcl`` is refused), ``hector``
(:class:`~mmpa.localization.hector.HectorConfig`) and ``initial_cov``, the diagonal of the
initial pose's covariance ``[xx, yy, aa]`` (m^2, m^2, rad^2; ROS amcl's ``initial_cov_xx``,
``initial_cov_yy``, ``initial_cov_aa``), which wins over a recorded ``/initialpose``'s
covariance; None: the recorded one, else ``amcl.initial_cov_*``.

Where a run's settings come from, lowest first: the defaults in code, the robot file's
``localization`` section, the ``--config`` file, the command's own options, ``--set``.
:func:`build_localizer` makes the localizer of a config.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array
from mmpa.localization.config import AMCLConfig, EnhancedConfig
from mmpa.localization.hector import HectorConfig
from mmpa.localization.localizer import METHODS, Localizer, make_localizer
from mmpa.maps.occupancy import OccupancyGrid

__all__ = [
    "GLOBAL_METHODS",
    "EnhancedSection",
    "LocalizationConfig",
    "amcl_of",
    "build_localizer",
    "initial_covariance",
    "start_localizer",
]

#: the methods that can start without a pose (particles uniform over the free space)
GLOBAL_METHODS = ("amcl", "enhanced", "enhanced-paper")


class EnhancedSection(EnhancedConfig):
    """:class:`EnhancedConfig` without its own AMCL: the one AMCL of a
    :class:`LocalizationConfig` is its ``amcl`` (not written out, refused when set)."""

    amcl: AMCLConfig = Field(AMCLConfig(), exclude=True)


class LocalizationConfig(BaseModel):
    """A localizer's settings (module docstring). Units: m, rad."""

    model_config = ConfigDict(extra="forbid")

    method: str = "enhanced"  # one of mmpa.localization.localizer.METHODS
    amcl: AMCLConfig = AMCLConfig()
    enhanced: EnhancedSection = EnhancedSection()
    hector: HectorConfig = HectorConfig()
    # [xx, yy, aa] m^2, m^2, rad^2: the initial pose's covariance (diagonal); None: the
    # recorded /initialpose's, else amcl.initial_cov_xx / _yy / _aa
    initial_cov: tuple[float, float, float] | None = None

    @field_validator("method")
    @classmethod
    def _known_method(cls, v: str) -> str:
        if v not in METHODS:
            raise ValueError(f"unknown method {v!r}; valid: {', '.join(METHODS)}")
        return v

    @field_validator("initial_cov")
    @classmethod
    def _positive_cov(
        cls, v: tuple[float, float, float] | None
    ) -> tuple[float, float, float] | None:
        if v is not None and not all(np.isfinite(c) and c > 0 for c in v):
            raise ValueError(f"the variances [xx, yy, aa] must be finite and > 0, got {list(v)}")
        return v

    @model_validator(mode="after")
    def _one_amcl(self) -> LocalizationConfig:
        if "amcl" in self.enhanced.model_fields_set:
            raise ValueError(
                "enhanced.amcl: the AMCL inside enhanced is set under amcl (one AMCL section)"
            )
        return self


def initial_covariance(cfg: LocalizationConfig, recorded: Array | None = None) -> Array | None:
    """The initial pose's covariance (3, 3): ``cfg.initial_cov`` (diagonal), else
    ``recorded`` when it is not all zeros, else None (the localizer's default,
    ``amcl.initial_cov_*``)."""
    if cfg.initial_cov is not None:
        return np.diag(np.asarray(cfg.initial_cov, float))
    if recorded is not None and np.any(recorded):
        return np.asarray(recorded, float)
    return None


def amcl_of(cfg: LocalizationConfig) -> AMCLConfig:
    """The AMCL settings of ``cfg.method``: ``cfg.amcl`` for ``amcl``; for the methods with
    an AMCL inside (enhanced, tamcl) Nav2's AMCL (:meth:`AMCLConfig.paper`, as paper 001 ran
    it) with the fields where ``cfg.amcl`` differs from AMCL's defaults on top (so that a
    saved ``config.yaml``, which writes every field, reruns alike): the scan refinement and
    its laser model are AMCL's defaults, not those of the reflector methods."""
    if cfg.method == "amcl":
        return cfg.amcl
    base = AMCLConfig()
    given = {k: v for k, v in cfg.amcl if v != getattr(base, k)}
    return AMCLConfig.paper().model_copy(update=given)


def build_localizer(
    cfg: LocalizationConfig,
    grid: OccupancyGrid,
    laser_pose: Array,
    rng: np.random.Generator | None = None,
) -> Localizer:
    """:func:`~mmpa.localization.localizer.make_localizer` of ``cfg.method`` with the
    settings of ``cfg`` (monitored: every estimate carries its health; ``enhanced-paper``
    keeps Algorithm 1 as printed, with the AMCL of ``cfg.amcl``)."""
    return make_localizer(
        cfg.method,
        grid,
        laser_pose,
        rng,
        amcl=amcl_of(cfg),
        enhanced=cfg.enhanced,
        hector=cfg.hector,
    )


def start_localizer(
    loc: Localizer,
    method: str,
    pose: Array | None,
    cov: Array | None = None,
    global_localization: bool = False,
) -> None:
    """Start ``loc`` (of ``method``) at ``pose`` with covariance ``cov`` (None: its
    default), or, with ``global_localization``, with particles uniform over the map's free
    space (:data:`GLOBAL_METHODS` only; the pose is not used)."""
    if global_localization:
        if method not in GLOBAL_METHODS:
            raise InvalidInputError(
                f"global localization (--global) needs a particle filter: {method} tracks "
                f"from a pose; use one of {', '.join(GLOBAL_METHODS)}"
            )
        loc.global_localization()  # type: ignore[attr-defined]
        return
    if pose is None:
        raise InvalidInputError("no initial pose: give one (--initial-pose) or use --global")
    loc.initialize(np.asarray(pose, float), cov)
