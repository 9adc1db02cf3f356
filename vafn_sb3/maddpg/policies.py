"""MADDPG policy: decentralised parameter-shared deterministic actors, one centralised critic ``Q(s, a_1..a_N)``."""

from __future__ import annotations

from typing import Any

from stable_baselines3.td3.policies import TD3Policy
from torch import nn

from vafn_sb3.common.agents import AgentLayoutPolicyMixin, DeterministicAgentActor

#: ``openai/maddpg:experiments/train.py``: ``--num-units 64`` in a two-hidden-layer MLP (``mlp_model``), actor and
#: critic.
DEFAULT_NET_ARCH = [64, 64]
#: With one shared team reward a single centralised Q suffices (plain MADDPG); 2 gives MATD3-style clipped double Q.
DEFAULT_N_CRITICS = 1


class MADDPGPolicy(AgentLayoutPolicyMixin, TD3Policy):
    """TD3 policy whose actor (and target actor) is :class:`DeterministicAgentActor`.

    The critic is SB3's ``ContinuousCritic`` over the joint observation and the joint action: the centralised
    ``Q(x, a_1, ..., a_N)`` of ``openai/maddpg:maddpg/trainer/maddpg.py`` (``q_train`` reads ``obs_ph_n + act_ph_n``).
    Parameters are SB3's ``TD3Policy``'s (defaults: ``net_arch=[64, 64]``, ``n_critics=1``) plus the per-agent keywords
    of :class:`~vafn_sb3.common.agents.AgentLayoutPolicyMixin`.
    """

    actor: DeterministicAgentActor
    actor_target: DeterministicAgentActor

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("net_arch", DEFAULT_NET_ARCH)
        kwargs.setdefault("n_critics", DEFAULT_N_CRITICS)
        super().__init__(*args, **kwargs)

    def make_actor(self, features_extractor: nn.Module | None = None) -> DeterministicAgentActor:
        """Build the shared per-agent deterministic actor."""
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return DeterministicAgentActor(**self._agent_actor_kwargs(actor_kwargs)).to(self.device)


MlpPolicy = MADDPGPolicy
