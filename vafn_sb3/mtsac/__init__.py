"""MTSAC: multi-task SAC + fine-tuning, the non-meta adaptation baseline (SAC subclass)."""

from vafn_sb3.mtsac.mtsac import MTSAC
from vafn_sb3.sac.policies import MlpPolicy, SharedAgentPolicy

__all__ = ["MTSAC", "MlpPolicy", "SharedAgentPolicy"]
