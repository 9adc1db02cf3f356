"""SAC: Stable-Baselines3's SAC with vafn's per-arm shared actor as a policy alias and atomic, verified save/load."""

from __future__ import annotations

from typing import ClassVar

from stable_baselines3 import SAC as SB3SAC
from stable_baselines3.common.policies import BasePolicy

from vafn_sb3.common.serialization import AtomicSaveMixin
from vafn_sb3.sac.policies import MlpPolicy, SharedAgentPolicy


class SAC(AtomicSaveMixin, SB3SAC):
    """SB3's SAC unchanged, plus the ``"SharedAgentPolicy"`` alias (one actor shared by every arm, the default of the
    vafn YAMLs). Parameters are SB3's ``SAC``'s."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "SharedAgentPolicy": SharedAgentPolicy,
    }
