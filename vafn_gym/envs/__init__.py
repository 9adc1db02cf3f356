"""The environments: MultiArmEnv (one instruction per episode) and MultiArmStreamEnv (queue-driven, long horizon)."""

from vafn_gym.envs.multi_arm import MultiArmEnv
from vafn_gym.envs.stream import MultiArmStreamEnv

__all__ = ["MultiArmEnv", "MultiArmStreamEnv"]
