"""MAPPO policy: one Gaussian actor shared by the agents over (local obs[, one-hot id]), a centralised V(s), ValueNorm.

Follows ``marlbenchmark/on-policy``: ``onpolicy/algorithms/r_mappo/algorithm/r_actor_critic.py`` (``R_Actor`` on each
agent's obs, ``R_Critic`` on the shared obs), ``onpolicy/algorithms/utils/mlp.py`` (LayerNorm on the input and after
every hidden ReLU), ``onpolicy/algorithms/utils/act.py`` + ``distributions.py`` (``DiagGaussian``: orthogonal init with
gain 0.01 on the mean, a state-independent log-std initialised to 0, shared by the agents because the actor is) and
``onpolicy/utils/valuenorm.py`` (the critic predicts *normalised* values).
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import numpy as np
import torch as th
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.distributions import DiagGaussianDistribution
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.type_aliases import PyTorchObs
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from vafn_sb3.common.agents import (
    AgentHead,
    AgentLayout,
    AgentLayoutPolicyMixin,
    SharedAgentMLP,
    merge_agents,
    mlp_layers,
    per_agent_sum,
)

#: ``onpolicy/config.py``: ``--hidden_size 64``, ``--layer_N 1`` (an input layer plus one hidden layer: two of
#: width 64).
DEFAULT_NET_ARCH = [64, 64]
#: ``onpolicy/utils/valuenorm.py`` defaults.
VALUE_NORM_BETA = 0.99999
VALUE_NORM_EPS = 1e-5
VALUE_NORM_MIN_VAR = 1e-2
#: ``onpolicy/algorithms/utils/act.py``: ``DiagGaussian(..., gain=0.01)`` on the action mean.
ACTION_GAIN = 0.01


class ValueNorm(nn.Module):
    """Debiased running mean/variance of the value targets (``onpolicy/utils/valuenorm.py``, scalar values).

    Stored as buffers, so it is saved and loaded with the policy. ``update`` is an exponential moving average with
    ``beta`` and a debiasing term (``per_element_update=False``); the variance is floored at ``1e-2``.

    :param beta: EMA factor.
    :param epsilon: floor of the debiasing term.
    """

    def __init__(self, beta: float = VALUE_NORM_BETA, epsilon: float = VALUE_NORM_EPS) -> None:
        super().__init__()
        self.beta = beta
        self.epsilon = epsilon
        self.register_buffer("running_mean", th.zeros(()))
        self.register_buffer("running_mean_sq", th.zeros(()))
        self.register_buffer("debiasing_term", th.zeros(()))

    def mean_var(self) -> tuple[th.Tensor, th.Tensor]:
        """Debiased mean and variance."""
        debias = self.debiasing_term.clamp(min=self.epsilon)
        mean = self.running_mean / debias
        var = (self.running_mean_sq / debias - mean**2).clamp(min=VALUE_NORM_MIN_VAR)
        return mean, var

    @th.no_grad()
    def update(self, values: th.Tensor) -> None:
        """Fold a batch of value targets into the running statistics."""
        self.running_mean.mul_(self.beta).add_(values.mean() * (1.0 - self.beta))
        self.running_mean_sq.mul_(self.beta).add_((values**2).mean() * (1.0 - self.beta))
        self.debiasing_term.mul_(self.beta).add_(1.0 - self.beta)

    def normalize(self, values: th.Tensor) -> th.Tensor:
        """Map raw values to the normalised scale the critic predicts."""
        mean, var = self.mean_var()
        return (values - mean) / var.sqrt()

    def denormalize(self, values: th.Tensor) -> th.Tensor:
        """Map critic outputs back to raw returns."""
        mean, var = self.mean_var()
        return values * var.sqrt() + mean


class MAPPOExtractor(nn.Module):
    """SB3 ``mlp_extractor`` with a decentralised shared actor trunk and a centralised critic trunk.

    :param layout: the per-agent layout.
    :param pi_arch: hidden widths of the shared per-agent actor MLP.
    :param vf_arch: hidden widths of the critic MLP on the joint observation (the global state).
    :param activation_fn: activation class.
    :param layer_norm: on-policy LayerNorms on inputs and hidden layers.
    :param agent_ids: append a one-hot agent id to every agent's actor input.
    :param neighbours: append where the nearest other agent is to every agent's actor input.
    """

    def __init__(
        self,
        layout: AgentLayout,
        pi_arch: list[int],
        vf_arch: list[int],
        activation_fn: type[nn.Module],
        layer_norm: bool,
        agent_ids: bool = True,
        neighbours: bool = False,
    ) -> None:
        super().__init__()
        n_agent_ids = layout.n_agents if agent_ids else 0
        self.policy_net = SharedAgentMLP(
            layout.obs_per_agent, pi_arch, activation_fn, layer_norm, n_agent_ids, neighbours
        )
        self.value_net, self.latent_dim_vf = mlp_layers(layout.obs_dim, vf_arch, activation_fn, layer_norm)
        self.agent_latent_dim = self.policy_net.latent_dim
        self.latent_dim_pi = layout.n_agents * self.agent_latent_dim

    def forward(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Actor latent ``(B, N * h)`` and critic latent ``(B, h_v)``."""
        return self.forward_actor(features), self.forward_critic(features)

    def forward_actor(self, features: th.Tensor) -> th.Tensor:
        """Flattened per-agent latents (agent ``i``'s block depends on agent ``i``'s local observation only)."""
        return merge_agents(self.policy_net(features))

    def forward_critic(self, features: th.Tensor) -> th.Tensor:
        """Latent of the centralised critic on the global state."""
        return self.value_net(features)


class MAPPOPolicy(AgentLayoutPolicyMixin, ActorCriticPolicy):
    """MAPPO actor-critic; ``forward``/``predict_values`` return *denormalised* values so SB3's GAE is unchanged.

    Parameters are SB3's ``ActorCriticPolicy``'s (defaults: ``net_arch=[64, 64]``, ReLU, ``log_std_init=0``), the
    per-agent keywords of :class:`~vafn_sb3.common.agents.AgentLayoutPolicyMixin`, plus:

    :param layer_norm: on-policy LayerNorms (``use_feature_normalization`` and ``MLPLayer``).
    """

    def __init__(self, *args: Any, layer_norm: bool = True, **kwargs: Any) -> None:
        kwargs.setdefault("net_arch", DEFAULT_NET_ARCH)
        kwargs.setdefault("activation_fn", nn.ReLU)
        if kwargs.get("use_sde", False):
            raise ValueError("MAPPO uses a state-independent Gaussian; gSDE is not supported")
        if not kwargs.get("share_features_extractor", True):
            raise ValueError(
                "MAPPO's actor and critic split the raw observation themselves; keep share_features_extractor"
            )
        self.layer_norm = layer_norm  # read by _build_mlp_extractor, which ActorCriticPolicy.__init__ calls
        super().__init__(*args, **kwargs)

    def _build_mlp_extractor(self) -> None:
        if isinstance(self.net_arch, dict):
            pi_arch, vf_arch = self.net_arch.get("pi", []), self.net_arch.get("vf", [])
        else:
            pi_arch = vf_arch = list(self.net_arch)
        self.mlp_extractor = MAPPOExtractor(
            self.agent_layout, pi_arch, vf_arch, self.activation_fn, self.layer_norm, self.agent_ids, self.neighbours
        )

    def _build(self, lr_schedule: Any) -> None:
        super()._build(lr_schedule)
        if not isinstance(self.action_dist, DiagGaussianDistribution):
            raise ValueError(f"MAPPO needs a Box action space (Gaussian actions), got {self.action_space}")
        # Replace SB3's joint head and joint log-std by the per-agent shared head and one per-agent log-std.
        del self.log_std
        layout, agent_latent_dim = self.agent_layout, self.mlp_extractor.agent_latent_dim
        self.action_net = nn.Sequential(
            nn.Unflatten(-1, (layout.n_agents, agent_latent_dim)), AgentHead(agent_latent_dim, layout.action_per_agent)
        )
        self.agent_log_std = nn.Parameter(th.full((layout.action_per_agent,), float(self.log_std_init)))
        if self.ortho_init:
            self.action_net.apply(partial(self.init_weights, gain=ACTION_GAIN))
        self.value_norm = ValueNorm()
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data["layer_norm"] = self.layer_norm
        return data

    def _get_action_dist_from_latent(self, latent_pi: th.Tensor) -> DiagGaussianDistribution:
        log_std = self.agent_log_std.repeat(self.agent_layout.n_agents)
        return self.action_dist.proba_distribution(self.action_net(latent_pi), log_std)

    def actor_parameters(self) -> list[nn.Parameter]:
        """Parameters of the shared actor (clipped separately, as on-policy's ``actor_optimizer`` group)."""
        return [*self.mlp_extractor.policy_net.parameters(), *self.action_net.parameters(), self.agent_log_std]

    def critic_parameters(self) -> list[nn.Parameter]:
        """Parameters of the centralised critic."""
        return [*self.mlp_extractor.value_net.parameters(), *self.value_net.parameters()]

    def forward(self, obs: th.Tensor, deterministic: bool = False) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Actions, denormalised values and joint log-probabilities (SB3's rollout interface)."""
        actions, values, log_prob = super().forward(obs, deterministic)
        return actions, self.value_norm.denormalize(values), log_prob

    def predict_values(self, obs: PyTorchObs) -> th.Tensor:
        """Denormalised ``V(s)`` (SB3 bootstraps GAE and truncated episodes with it)."""
        return self.value_norm.denormalize(super().predict_values(obs))

    def evaluate_actions(self, obs: PyTorchObs, actions: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor | None]:
        """Denormalised values, joint log-probabilities and joint entropies (SB3's interface)."""
        values, log_prob, entropy = super().evaluate_actions(obs, actions)
        return self.value_norm.denormalize(values), log_prob, entropy

    def evaluate_agent_actions(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Normalised values ``(B,)``, per-agent log-probabilities ``(B, N)`` and entropies ``(B, N)``."""
        features = self.extract_features(obs)
        latent_pi, latent_vf = self.mlp_extractor(features)
        distribution = self._get_action_dist_from_latent(latent_pi).distribution
        action_per_agent = self.agent_layout.action_per_agent
        log_prob = per_agent_sum(distribution.log_prob(actions), action_per_agent)
        entropy = per_agent_sum(distribution.entropy(), action_per_agent)
        return self.value_net(latent_vf).flatten(), log_prob, entropy


class AgentRolloutBufferSamples(NamedTuple):
    """SB3's ``RolloutBufferSamples`` plus each agent's old log-probability and the old *normalised* value."""

    observations: th.Tensor
    actions: th.Tensor
    old_values: th.Tensor
    old_log_prob: th.Tensor
    advantages: th.Tensor
    returns: th.Tensor
    old_agent_log_prob: th.Tensor
    old_normalized_values: th.Tensor


class AgentRolloutBuffer(RolloutBuffer):
    """Rollout buffer that also serves per-agent old log-probabilities and old normalised values.

    SB3 stores joint log-probabilities only; MAPPO fills :attr:`old_agent_log_prob` ``(buffer_size, n_envs, N)`` and
    :attr:`old_normalized_values` once per rollout (before the first update, when the policy still equals the behaviour
    policy) with :meth:`set_agent_statistics`; the buffer itself does not need to know ``N``.
    """

    def reset(self) -> None:
        """Empty the buffer (and the per-agent arrays)."""
        super().reset()
        self.old_agent_log_prob = np.zeros((self.buffer_size, self.n_envs, 0), dtype=np.float32)
        self.old_normalized_values = np.zeros((self.buffer_size, self.n_envs), dtype=np.float32)

    def set_agent_statistics(self, agent_log_prob: np.ndarray, normalized_values: np.ndarray) -> None:
        """Store the behaviour policy's per-agent log-probabilities and normalised values, rows in buffer order.

        :param agent_log_prob: ``(buffer_size * n_envs, N)``.
        :param normalized_values: ``(buffer_size * n_envs,)``.
        """
        self.old_agent_log_prob = agent_log_prob.reshape(self.buffer_size, self.n_envs, -1)
        self.old_normalized_values = normalized_values.reshape(self.buffer_size, self.n_envs)

    def get(self, batch_size: int | None = None):  # type: ignore[override]
        """Minibatches of :class:`AgentRolloutBufferSamples` (see SB3's ``RolloutBuffer.get``)."""
        if not self.generator_ready:
            self.old_agent_log_prob = self.swap_and_flatten(self.old_agent_log_prob)
            self.old_normalized_values = self.swap_and_flatten(self.old_normalized_values)
        yield from super().get(batch_size)

    def _get_samples(  # type: ignore[override]
        self, batch_inds: np.ndarray, env: VecNormalize | None = None
    ) -> AgentRolloutBufferSamples:
        return AgentRolloutBufferSamples(
            *super()._get_samples(batch_inds, env),
            self.to_torch(self.old_agent_log_prob[batch_inds]),
            self.to_torch(self.old_normalized_values[batch_inds].flatten()),
        )


MlpPolicy = MAPPOPolicy
