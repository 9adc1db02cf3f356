"""Deprecated: moved to :mod:`vafn_sb3.inference`; this alias goes in a later release."""

import warnings

from vafn_sb3.inference.estimators.base import (  # noqa: F401
    ESTIMATOR_READINGS,
    REFINE_SOLVER,
    REFINE_SOLVERS,
    REFINE_STEPS,
    FirstReadingsEstimator,
    fit_minibatches,
    seeded_mlp,
)
from vafn_sb3.inference.estimators.learned import LearnedTargetEstimator  # noqa: F401
from vafn_sb3.inference.policies import (  # noqa: F401
    ESTIMATOR_MODES,
    INFERENCE_MODES,
    MIN_SEPARATION,
    GradientInferencePolicy,
    TargetInferencePolicy,
    collect_waypoint_readings,
    inference_policy_for_env,
    load_estimator,
)

warnings.warn("vafn_sb3.target_inference moved to vafn_sb3.inference", DeprecationWarning, stacklevel=2)
