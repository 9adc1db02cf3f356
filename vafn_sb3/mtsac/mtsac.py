"""MTSAC: multi-task SAC pre-trained on the train-task distribution, adapted by fine-tuning (SAC subclass)."""

from __future__ import annotations

from typing import ClassVar, TypeVar

from stable_baselines3 import SAC
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import MaybeCallback

from vafn_sb3.common.finetune import FineTuneAdaptation
from vafn_sb3.common.save import AtomicSaveMixin
from vafn_sb3.sac.lean import LeanSACMixin
from vafn_sb3.sac.policies import MlpPolicy, SharedAgentPolicy

SelfMTSAC = TypeVar("SelfMTSAC", bound="MTSAC")


class MTSAC(AtomicSaveMixin, FineTuneAdaptation, LeanSACMixin, SAC):
    """Plain SB3 SAC trained on the union of training tasks; ``adapt`` fine-tunes it on the support set.

    Training is SB3's SAC (by default through the lean update of the same losses, ``lean_update=True``; see
    :mod:`vafn_sb3.sac.lean`): pre-train on an env that samples training instructions every episode (e.g.
    ``VAFN/ThreeArmReachHidden-v1`` with ``split="train"``). ``adapt`` (from
    :class:`~vafn_sb3.common.finetune.FineTuneAdaptation`) runs ``k`` full-batch SAC updates (critic, actor,
    temperature, target networks, with SAC's own Adam optimisers) on exactly the support data MAML-SAC receives, then
    restores the model. This is the "multi-task pre-training + fine-tuning" baseline of Mandi et al. (NeurIPS 2022).
    Policies: ``"MlpPolicy"`` (SB3's) or ``"SharedAgentPolicy"`` (the decentralised per-agent actor). Parameters are
    SB3's ``SAC``'s, plus ``lean_update`` (False: SB3's ``SAC.train``).
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "SharedAgentPolicy": SharedAgentPolicy,
    }

    def learn(
        self: SelfMTSAC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "MTSAC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfMTSAC:
        """Train for ``total_timesteps`` env steps (see SB3's ``learn``)."""
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)
