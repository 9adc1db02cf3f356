"""The lean SAC update: SB3's ``SAC.train`` step, same losses and order, with fewer and larger tensor operations.

One gradient step does what SB3's does, in the same order and with the same random draws: sample a minibatch, sample
``a ~ pi(s)``, step the entropy coefficient, build the soft target from the target critics and ``a' ~ pi(s')``, step
the critics on ``0.5 * sum_k MSE(Q_k(s, a), y)``, step the actor on ``mean(alpha log pi(a|s) - min_k Q_k(s, a))`` with
the updated critics, Polyak-average the target critics every ``target_update_interval`` steps. What differs is how:

- all critics (and all target critics) run as one batched MLP (first layer one ``addmm``, the others ``baddbmm``) on
  weights stacked at every call, so gradients still land on SB3's own per-critic parameters;
- the actor loss reads the critics through detached weights (SB3 computes, then discards, their gradients);
- the entropy coefficient's gradient ``-mean(log pi + target entropy)`` is written directly, without autograd;
- Adam optimisers step with PyTorch's fused kernel (``fused=True`` for the step only; their state is unchanged);
- the target update is one ``torch._foreach_lerp_``;
- the minibatch is gathered from the replay arrays into tensors without a second copy;
- the logged losses stay tensors until one host transfer per ``train()`` call.

The numbers differ from SB3's only in float rounding (summation order of the batched products, ``lerp`` versus
``(1 - tau) * target + tau * online``, the fused Adam kernel); ``tests/test_lean_update.py`` checks one step against
SB3's ``SAC.train``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.utils import polyak_update
from stable_baselines3.common.vec_env import VecNormalize
from stable_baselines3.sac.policies import Actor
from torch import nn

#: ``log(sqrt(2 pi))``, the constant of a Gaussian log-density (as in ``torch.distributions.Normal.log_prob``).
LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))
#: SB3's ``TanhBijector`` epsilon of the squashing correction ``log(1 - tanh(u)^2 + eps)``.
TANH_EPS = 1e-6


def stacked_critic_layers(q_networks: list[nn.Module]) -> list[nn.Module] | None:
    """The first critic's layers if all critics are one stack of ``Linear`` and parameter-free layers, else None."""
    first = list(q_networks[0]) if isinstance(q_networks[0], nn.Sequential) else []
    for net in q_networks:
        layers = list(net) if isinstance(net, nn.Sequential) else []
        if [type(layer) for layer in layers] != [type(layer) for layer in first] or not layers:
            return None
        for layer in layers:
            if not isinstance(layer, nn.Linear) and any(True for _ in layer.parameters()):
                return None
    if not isinstance(first[-1], nn.Linear) or not isinstance(first[0], nn.Linear):
        return None
    return first


def supports_lean_update(model: Any) -> bool:
    """Whether the lean update reproduces ``model``'s SAC step: SB3's squashed-Gaussian actor without gSDE, and critics
    that are plain MLPs (``Linear`` layers and parameter-free activations; no BatchNorm, no dropout)."""
    return (
        isinstance(model.actor, Actor)
        and not model.use_sde
        and stacked_critic_layers(model.critic.q_networks) is not None
        and stacked_critic_layers(model.critic_target.q_networks) is not None
    )


def batched_q_values(critic: nn.Module, obs: th.Tensor, actions: th.Tensor, detach: bool = False) -> th.Tensor:
    """Every Q-network of an SB3 ``ContinuousCritic`` at once: ``(n_critics, B, 1)``.

    :param critic: the critic (its ``q_networks`` pass :func:`stacked_critic_layers`).
    :param obs: observations ``(B, ...)``.
    :param actions: actions ``(B, action_dim)``.
    :param detach: use the critic's weights as constants (gradients flow to ``actions`` only).
    """
    with th.set_grad_enabled(th.is_grad_enabled() and not critic.share_features_extractor and not detach):
        features = critic.extract_features(obs, critic.features_extractor)
    x = th.cat([features, actions], dim=1)
    nets = [list(net) for net in critic.q_networks]
    n_critics = len(nets)
    for index, layer in enumerate(nets[0]):
        if not isinstance(layer, nn.Linear):
            x = layer(x)
            continue
        weight = th.stack([net[index].weight for net in nets])  # (K, out, in)
        bias = th.stack([net[index].bias for net in nets])  # (K, out)
        if detach:
            weight, bias = weight.detach(), bias.detach()
        if x.dim() == 2:  # first layer: one input shared by every critic
            x = th.addmm(bias.reshape(-1), x, weight.reshape(-1, weight.shape[-1]).t())
            x = x.reshape(x.shape[0], n_critics, -1).transpose(0, 1)
        else:
            x = th.baddbmm(bias.unsqueeze(1), x, weight.transpose(1, 2))
    return x


def squashed_sample(actor: Actor, obs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """SB3's ``actor.action_log_prob`` without the distribution objects: reparameterised tanh-Gaussian actions
    ``(B, A)`` and their log-probabilities ``(B, 1)`` (the same noise draw and formulas)."""
    mean, log_std, _ = actor.get_action_dist_params(obs)
    std = log_std.exp()
    gaussian = mean + th.empty_like(mean).normal_() * std
    actions = th.tanh(gaussian)
    log_density = -((gaussian - mean) ** 2) / (2 * std**2) - std.log() - LOG_SQRT_2PI
    log_prob = (log_density - th.log(1 - actions**2 + TANH_EPS)).sum(dim=1, keepdim=True)
    return actions, log_prob


def sample_replay(buffer: ReplayBuffer, batch_size: int, env: VecNormalize | None) -> ReplayBufferSamples:
    """``buffer.sample`` with the same random draws, wrapping the gathered arrays instead of copying them again.

    Only a plain SB3 ``ReplayBuffer`` without ``optimize_memory_usage`` and without normalisation; anything else goes
    to its own ``sample``.
    """
    if type(buffer) is not ReplayBuffer or buffer.optimize_memory_usage or env is not None:
        return buffer.sample(batch_size, env=env)
    upper_bound = buffer.buffer_size if buffer.full else buffer.pos
    batch_inds = np.random.randint(0, upper_bound, size=batch_size)
    env_inds = np.random.randint(0, high=buffer.n_envs, size=(batch_size,))
    dones = buffer.dones[batch_inds, env_inds] * (1 - buffer.timeouts[batch_inds, env_inds])
    arrays = (
        buffer.observations[batch_inds, env_inds, :],
        buffer.actions[batch_inds, env_inds, :],
        buffer.next_observations[batch_inds, env_inds, :],
        dones.reshape(-1, 1),
        buffer.rewards[batch_inds, env_inds].reshape(-1, 1),
    )
    return ReplayBufferSamples(*(th.from_numpy(array).to(buffer.device) for array in arrays))


def adam_step(optimizer: th.optim.Optimizer) -> None:
    """``optimizer.step()``; a plain ``torch.optim.Adam`` whose state exists steps in one call of the fused kernel
    (what ``Adam(fused=True).step()`` runs, without its per-call bookkeeping)."""
    params = [p for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
    states = [optimizer.state.get(p) for p in params]
    group = optimizer.param_groups[0]
    plain = (
        type(optimizer) is th.optim.Adam
        and len(optimizer.param_groups) == 1
        and not any(group[flag] for flag in ("amsgrad", "capturable", "differentiable", "decoupled_weight_decay"))
        and not isinstance(group["lr"], th.Tensor)
        and all(states)
    )
    if not plain:
        with fused_adam([optimizer]):
            optimizer.step()
        return
    steps = [state["step"] for state in states]
    th._foreach_add_(steps, 1)
    beta1, beta2 = group["betas"]
    th._fused_adam_(
        params, [p.grad for p in params], [state["exp_avg"] for state in states],
        [state["exp_avg_sq"] for state in states], [], steps, amsgrad=False, lr=group["lr"], beta1=beta1,
        beta2=beta2, weight_decay=group["weight_decay"], eps=group["eps"], maximize=group["maximize"],
    )


@contextmanager
def fused_adam(optimizers: list[th.optim.Optimizer]) -> Iterator[None]:
    """Within the block, every ``torch.optim.Adam`` among ``optimizers`` steps with the fused kernel."""
    groups = [group for opt in optimizers if type(opt) is th.optim.Adam for group in opt.param_groups]
    saved = [(group.get("fused"), group.get("foreach")) for group in groups]
    for group in groups:
        group["fused"], group["foreach"] = True, None
    try:
        yield
    finally:
        for group, (fused, foreach) in zip(groups, saved):
            group["fused"], group["foreach"] = fused, foreach


def zero_grad(parameters: list[th.Tensor]) -> None:
    """``optimizer.zero_grad()`` (set to None) for ``parameters``."""
    for parameter in parameters:
        parameter.grad = None


@dataclass
class LeanLosses:
    """The per-step scalars SB3's ``SAC.train`` logs, kept as tensors until :meth:`record`."""

    actor: list[th.Tensor]
    critic: list[th.Tensor]
    ent_coef: list[th.Tensor]
    ent_coef_loss: list[th.Tensor]

    def means(self) -> dict[str, float]:
        """Each logged key's mean over the steps, in one host transfer."""
        columns = {"actor_loss": self.actor, "critic_loss": self.critic, "ent_coef": self.ent_coef,
                   "ent_coef_loss": self.ent_coef_loss}
        present = {key: th.stack(values).reshape(len(values), -1)[:, 0] for key, values in columns.items() if values}
        stacked = th.stack([values.mean() for values in present.values()]).tolist()
        return dict(zip(present, stacked))


def lean_train(model: Any, gradient_steps: int, batch_size: int) -> None:
    """``gradient_steps`` SAC updates of an SB3 ``SAC`` ``model``, as its ``train`` does (see the module docstring)."""
    model.policy.set_training_mode(True)
    actor, critic, critic_target = model.actor, model.critic, model.critic_target
    optimizers = [actor.optimizer, critic.optimizer]
    if model.ent_coef_optimizer is not None:
        optimizers.append(model.ent_coef_optimizer)
    model._update_learning_rate(optimizers)
    online, target = list(critic.parameters()), list(critic_target.parameters())
    critic_params = [p for group in critic.optimizer.param_groups for p in group["params"]]
    actor_params = [p for group in actor.optimizer.param_groups for p in group["params"]]
    losses = LeanLosses([], [], [], [])

    for gradient_step in range(gradient_steps):
        data = sample_replay(model.replay_buffer, batch_size, model._vec_normalize_env)
        discounts = data.discounts if getattr(data, "discounts", None) is not None else model.gamma
        actions_pi, log_prob = squashed_sample(actor, data.observations)
        ent_coef = entropy_step(model, log_prob, losses)

        with th.no_grad():
            next_actions, next_log_prob = squashed_sample(actor, data.next_observations)
            next_q = batched_q_values(critic_target, data.next_observations, next_actions).min(dim=0).values
            next_q = next_q - ent_coef * next_log_prob
            target_q = data.rewards + (1 - data.dones) * discounts * next_q

        current_q = batched_q_values(critic, data.observations, data.actions)
        # 0.5 * sum_k MSE(Q_k, y): the mean over all critics times their number
        n_critics = current_q.shape[0]
        critic_loss = 0.5 * n_critics * th.nn.functional.mse_loss(current_q, target_q.expand_as(current_q))
        zero_grad(critic_params)
        critic_loss.backward()
        adam_step(critic.optimizer)

        min_q_pi = batched_q_values(critic, data.observations, actions_pi, detach=True).min(dim=0).values
        actor_loss = (ent_coef * log_prob - min_q_pi).mean()
        zero_grad(actor_params)
        actor_loss.backward()
        adam_step(actor.optimizer)

        if gradient_step % model.target_update_interval == 0:
            with th.no_grad():
                th._foreach_lerp_(target, online, model.tau)
            polyak_update(model.batch_norm_stats, model.batch_norm_stats_target, 1.0)
        losses.critic.append(critic_loss.detach())
        losses.actor.append(actor_loss.detach())

    model._n_updates += gradient_steps
    model.logger.record("train/n_updates", model._n_updates, exclude="tensorboard")
    for key, value in losses.means().items():
        model.logger.record(f"train/{key}", value)


def entropy_step(model: Any, log_prob: th.Tensor, losses: LeanLosses) -> th.Tensor:
    """SB3's temperature step (when learned); returns the coefficient of this step, before the step."""
    if model.ent_coef_optimizer is None or model.log_ent_coef is None:
        losses.ent_coef.append(model.ent_coef_tensor.detach())
        return model.ent_coef_tensor
    log_ent_coef = model.log_ent_coef
    ent_coef = log_ent_coef.detach().exp()
    # d/dx of -(x * (log_prob + target_entropy)).mean() is -(log_prob + target_entropy).mean()
    gradient = -(log_prob.detach() + model.target_entropy).mean().reshape(log_ent_coef.shape)
    log_ent_coef.grad = gradient
    losses.ent_coef_loss.append(log_ent_coef.detach() * gradient)
    losses.ent_coef.append(ent_coef)
    adam_step(model.ent_coef_optimizer)
    return ent_coef


class LeanSACMixin:
    """``train`` takes the lean update (:func:`lean_train`) when ``lean_update`` is set and the model supports it
    (:func:`supports_lean_update`), SB3's ``SAC.train`` otherwise. Put it before SB3's ``SAC`` in the bases.

    :param lean_update: take the lean update (False: SB3's own ``SAC.train``, unchanged).
    """

    lean_update: bool

    def __init__(self, *args: Any, lean_update: bool = True, **kwargs: Any) -> None:
        self.lean_update = bool(lean_update)
        super().__init__(*args, **kwargs)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """``gradient_steps`` SAC updates on minibatches of ``batch_size`` (lean or SB3's, see ``lean_update``)."""
        if getattr(self, "lean_update", False) and supports_lean_update(self):
            lean_train(self, gradient_steps, batch_size)
        else:
            super().train(gradient_steps, batch_size)  # type: ignore[misc]
