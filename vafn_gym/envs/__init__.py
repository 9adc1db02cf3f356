"""The environments: ThreeArmEnv (one instruction per episode) and ThreeArmStreamEnv (queue-driven, long horizon)."""

from vafn_gym.envs.stream import ThreeArmStreamEnv
from vafn_gym.envs.three_arm import ThreeArmEnv

__all__ = ["ThreeArmEnv", "ThreeArmStreamEnv"]
