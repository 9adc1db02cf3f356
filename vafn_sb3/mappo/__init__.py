"""MAPPO: shared decentralised actor, centralised critic, per-agent clipped ratios, ValueNorm (PPO subclass)."""

from vafn_sb3.mappo.mappo import MAPPO
from vafn_sb3.mappo.policies import MAPPOPolicy, MlpPolicy

__all__ = ["MAPPO", "MAPPOPolicy", "MlpPolicy"]
