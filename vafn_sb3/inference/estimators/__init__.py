"""Target estimators: from a waypoint's first (position, distance) readings to its target."""

from vafn_sb3.inference.estimators.base import (
    ESTIMATOR_READINGS,
    REFINE_SOLVER,
    REFINE_SOLVERS,
    REFINE_STEPS,
    FirstReadingsEstimator,
)
from vafn_sb3.inference.estimators.gradient import GradientTargetEstimator
from vafn_sb3.inference.estimators.learned import LearnedTargetEstimator

__all__ = ["ESTIMATOR_READINGS", "REFINE_SOLVER", "REFINE_SOLVERS", "REFINE_STEPS", "FirstReadingsEstimator",
           "GradientTargetEstimator", "LearnedTargetEstimator"]
