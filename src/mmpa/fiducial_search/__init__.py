"""Fiducial search with a moving base (paper 002): spiral (eq. 1) and Kalman-filter stochastic
search (eq. 2-6), base velocity compensation (eq. 7), iterative planning (Algorithm 2) and the
search loop (Algorithm 1). Pure algorithms: no simulator imports."""

from mmpa.fiducial_search.compensation import arrival_times, compensate
from mmpa.fiducial_search.planning import (
    ArmLimits,
    PlanningConfig,
    SearchPlan,
    ToolPointIK,
    iterative_plan,
    sample_path,
    segment_durations,
)
from mmpa.fiducial_search.search import (
    TUNED_KF,
    FiducialResult,
    MovingRobot,
    PassResult,
    SearchConfig,
    SearchStrategy,
    Spiral,
    Stochastic,
    make_strategy,
    run_pass,
)
from mmpa.fiducial_search.spiral import SpiralConfig, spiral_points
from mmpa.fiducial_search.stochastic import (
    ConstantVelocityKF,
    GridSamples,
    StochasticConfig,
    grid_samples,
    transition,
)

__all__ = [
    "TUNED_KF",
    "ArmLimits",
    "ConstantVelocityKF",
    "FiducialResult",
    "GridSamples",
    "MovingRobot",
    "PassResult",
    "PlanningConfig",
    "SearchConfig",
    "SearchPlan",
    "SearchStrategy",
    "Spiral",
    "SpiralConfig",
    "Stochastic",
    "StochasticConfig",
    "ToolPointIK",
    "arrival_times",
    "compensate",
    "grid_samples",
    "iterative_plan",
    "make_strategy",
    "run_pass",
    "sample_path",
    "segment_durations",
    "spiral_points",
    "transition",
]
