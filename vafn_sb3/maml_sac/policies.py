"""MAML-SAC's actor and critic as functions of parameter dicts, and the adapted policy :meth:`MAMLSAC.adapt` returns.

Parameters are plain ``{name: tensor}`` dicts applied with :func:`torch.func.functional_call`; they are never written
into the modules, so one SB3 SAC policy serves the meta-policy and any number of adapted ones.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.sac.policies import Actor
from torch import nn
from torch.func import functional_call

from vafn_sb3.common.adaptation import SupportSet

#: Added inside ``log(1 - tanh(u)^2 + eps)``, as in SB3's squashed Gaussian.
SQUASH_EPS = 1e-6
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)

Params = dict[str, torch.Tensor]


class ActorDistribution(nn.Module):
    """``forward(obs) -> (mean, log_std)`` of an SB3 SAC :class:`Actor`, for ``functional_call`` to re-parametrise.

    Its parameter names are the actor's, prefixed with ``"actor."``.

    :param actor: the SB3 SAC actor (not copied).
    """

    def __init__(self, actor: Actor) -> None:
        super().__init__()
        if actor.use_sde:
            raise ValueError("MAML-SAC does not support gSDE actors (use_sde=True)")
        self.actor = actor

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and clamped log-std of the pre-squash Gaussian."""
        mean, log_std, _ = self.actor.get_action_dist_params(obs)
        return mean, log_std


def parameters_of(module: nn.Module, detach: bool = False) -> Params:
    """``{name: parameter}`` of ``module`` (detached clones when ``detach``)."""
    if detach:
        return {name: p.detach().clone() for name, p in module.named_parameters()}
    return dict(module.named_parameters())


def detached(params: Params) -> Params:
    """The same dict with every tensor detached (shares storage)."""
    return {name: p.detach() for name, p in params.items()}


def sample_action(
    actor: ActorDistribution, params: Params, obs: torch.Tensor, deterministic: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """Squashed-Gaussian action in [-1, 1] and its log-probability, reparameterised (SB3's formula, no distributions).

    :param actor: the functional actor wrapper.
    :param params: its parameters.
    :param obs: ``(batch, obs_dim)`` observations.
    :param deterministic: use the mean instead of a sample.
    :return: ``(actions, log_prob)`` of shapes ``(batch, act_dim)`` and ``(batch,)``.
    """
    mean, log_std = functional_call(actor, params, (obs,))
    noise = torch.zeros_like(mean) if deterministic else torch.randn_like(mean)
    actions = torch.tanh(mean + log_std.exp() * noise)
    log_prob = (-0.5 * noise.pow(2) - log_std - _HALF_LOG_2PI).sum(-1)
    log_prob = log_prob - torch.log(1.0 - actions.pow(2) + SQUASH_EPS).sum(-1)
    return actions, log_prob


def min_q(critic: nn.Module, params: Params, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Minimum over the critic's Q-heads, shape ``(batch,)``."""
    q_values = functional_call(critic, params, (obs, actions))
    return torch.min(torch.cat(q_values, dim=-1), dim=-1).values


class AdaptedSACPolicy:
    """A SAC actor with adapted parameters, usable like ``model.predict`` (returned by :meth:`MAMLSAC.adapt`).

    The modules are re-parametrised only for the duration of a call, so do not call ``model.predict`` concurrently
    from another thread.

    :param policy: the model's SB3 policy (observation preprocessing, action unscaling).
    :param actor: functional wrapper of the model's actor.
    :param actor_params: adapted actor parameters.
    :param critic_params: adapted critic parameters (kept for inspection).
    :param support: the support set it was adapted on (kept for inspection).
    """

    def __init__(
        self, policy: BasePolicy, actor: ActorDistribution, actor_params: Params, critic_params: Params,
        support: SupportSet | None = None,
    ) -> None:
        self.policy = policy
        self.actor = actor
        self.actor_params = actor_params
        self.critic_params = critic_params
        self.support = support

    def predict(
        self,
        observation: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """Action(s) of the adapted policy for one observation or a batch (``state``/``episode_start`` are ignored)."""
        obs_tensor, vectorized = self.policy.obs_to_tensor(observation)
        with torch.no_grad():
            actions, _ = sample_action(self.actor, self.actor_params, obs_tensor, deterministic=deterministic)
        actions = self.policy.unscale_action(actions.cpu().numpy().reshape((-1, *self.policy.action_space.shape)))
        return (actions if vectorized else actions[0]), None
