"""Context adaptation: target estimators (``estimators/``) and the policies that use them (``policies``)."""

from vafn_sb3.inference.dynamics import DynamicsCompensation, ResponseFit, fit_response
from vafn_sb3.inference.estimators import (
    ESTIMATOR_READINGS,
    REFINE_SOLVER,
    REFINE_SOLVERS,
    REFINE_STEPS,
    FirstReadingsEstimator,
    GradientTargetEstimator,
    LearnedTargetEstimator,
)
from vafn_sb3.inference.policies import (
    ESTIMATOR_MODES,
    INFERENCE_MODES,
    GradientInferencePolicy,
    TargetInferencePolicy,
    collect_waypoint_readings,
    inference_policy_for_env,
    load_estimator,
)

__all__ = ["ESTIMATOR_MODES", "ESTIMATOR_READINGS", "INFERENCE_MODES", "REFINE_SOLVER", "REFINE_SOLVERS",
           "REFINE_STEPS", "DynamicsCompensation", "FirstReadingsEstimator", "GradientInferencePolicy",
           "GradientTargetEstimator", "LearnedTargetEstimator", "ResponseFit", "TargetInferencePolicy",
           "collect_waypoint_readings", "fit_response", "inference_policy_for_env", "load_estimator"]
