"""MADDPG: centralised critic, decentralised parameter-shared deterministic actors (TD3 subclass)."""

from vafn_sb3.maddpg.maddpg import MADDPG
from vafn_sb3.maddpg.policies import MADDPGPolicy, MlpPolicy

__all__ = ["MADDPG", "MADDPGPolicy", "MlpPolicy"]
