"""vafn_sb3: MAML-SAC, the MARL baselines and the online adaptive controller, as Stable-Baselines3 algorithms."""

from vafn_sb3.callbacks import MetaEvalCallback, RolloutCollisionCallback, SuccessCollisionEvalCallback
from vafn_sb3.common.adaptation import Adaptable, AdaptedPolicy, collect_support, evaluate_adaptation
from vafn_sb3.common.agents import shared_actor_for_env
from vafn_sb3.common.adaptation_curves import AdaptationCurve, aggregate_adaptation, plot_adaptation
from vafn_sb3.inference import (
    GradientInferencePolicy,
    GradientTargetEstimator,
    LearnedTargetEstimator,
    TargetInferencePolicy,
    collect_waypoint_readings,
)
from vafn_sb3.maac import MAAC
from vafn_sb3.maddpg import MADDPG
from vafn_sb3.maml_sac import MAMLSAC
from vafn_sb3.mappo import MAPPO
from vafn_sb3.mtsac import MTSAC
from vafn_sb3.online import OnlineController
from vafn_sb3.pretrained import available_pretrained, load_pretrained, pretrained_info
from vafn_sb3.sac import SAC

__all__ = [
    "MAAC",
    "MADDPG",
    "MAMLSAC",
    "MAPPO",
    "MTSAC",
    "Adaptable",
    "AdaptationCurve",
    "AdaptedPolicy",
    "MetaEvalCallback",
    "OnlineController",
    "SAC",
    "RolloutCollisionCallback",
    "SuccessCollisionEvalCallback",
    "GradientInferencePolicy",
    "GradientTargetEstimator",
    "LearnedTargetEstimator",
    "TargetInferencePolicy",
    "aggregate_adaptation",
    "available_pretrained",
    "collect_support",
    "collect_waypoint_readings",
    "evaluate_adaptation",
    "load_pretrained",
    "plot_adaptation",
    "pretrained_info",
    "shared_actor_for_env",
]

from vafn_sb3.common.serialization import atomic_write, load_weights, save_weights  # noqa: E402

__all__ += ["atomic_write", "load_weights", "save_weights"]

from vafn_sb3.aliases import register_stock_aliases  # noqa: E402

register_stock_aliases()  # our policies as stock SB3 aliases: `python -m rl_zoo3.train --gym-packages vafn_sb3`
__all__ += ["register_stock_aliases"]
