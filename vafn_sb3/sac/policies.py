"""SAC-family policies (SAC, MTSAC, MAML-SAC).

SB3's SAC MLP policy, or the same policy with the shared per-arm actor.
"""

from stable_baselines3.sac.policies import SACPolicy

from vafn_sb3.common.agents import SharedAgentSACPolicy

#: Plain SAC policy over the joint observation (the default: "plain SAC").
MlpPolicy = SACPolicy
#: SAC with the parameter-shared decentralised actor of the MARL baselines (for like-for-like architectures).
SharedAgentPolicy = SharedAgentSACPolicy

__all__ = ["MlpPolicy", "SharedAgentPolicy"]
