"""Deprecated: moved to :mod:`vafn_sb3.inference.estimators.gradient`; this alias goes in a later release."""

import warnings

from vafn_sb3.inference.estimators.gradient import (  # noqa: F401
    BASELINE_STEP_SIZES,
    REFINE_MAX_STEP,
    REFINE_SCALE,
    REFINE_STEP_SIZE,
    GradientTargetEstimator,
)

warnings.warn("vafn_sb3.gradient_estimator moved to vafn_sb3.inference.estimators.gradient", DeprecationWarning,
              stacklevel=2)
