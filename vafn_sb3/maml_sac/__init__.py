"""MAML-SAC: SAC meta-trained with MAML inner/outer updates (algo key ``maml_sac``), and its adapted policy."""

from stable_baselines3.sac.policies import CnnPolicy, MlpPolicy, MultiInputPolicy

from vafn_sb3.maml_sac.maml_sac import MAMLSAC
from vafn_sb3.maml_sac.policies import AdaptedSACPolicy

__all__ = ["AdaptedSACPolicy", "CnnPolicy", "MAMLSAC", "MlpPolicy", "MultiInputPolicy"]
