"""MAAC: multi-actor-attention-critic with continuous actions (SAC subclass)."""

from vafn_sb3.maac.maac import MAAC
from vafn_sb3.maac.policies import AttentionCritic, MAACPolicy, MlpPolicy

__all__ = ["MAAC", "AttentionCritic", "MAACPolicy", "MlpPolicy"]
