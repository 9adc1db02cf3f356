"""SAC: Stable-Baselines3's SAC with vafn's per-arm shared actor as a policy alias, atomic, verified save/load and the
lean update (:mod:`vafn_sb3.sac.lean`)."""

from __future__ import annotations

from typing import ClassVar

from stable_baselines3 import SAC as SB3SAC
from stable_baselines3.common.policies import BasePolicy

from vafn_sb3.common.save import AtomicSaveMixin
from vafn_sb3.sac.lean import LeanSACMixin
from vafn_sb3.sac.policies import MlpPolicy, SharedAgentPolicy


class SAC(AtomicSaveMixin, LeanSACMixin, SB3SAC):
    """SB3's SAC, plus the ``"SharedAgentPolicy"`` alias (one actor shared by every arm, the default of the vafn YAMLs)
    and the lean update of the same losses (``lean_update=True``, the default; False runs SB3's ``SAC.train``).
    Parameters are SB3's ``SAC``'s, plus ``lean_update``."""

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "SharedAgentPolicy": SharedAgentPolicy,
    }
