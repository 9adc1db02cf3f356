"""MAML-SAC's inner adaptation step and per-task query losses, as pure functions of parameter dicts.

Gradients of the inner losses come from :func:`torch.func.grad`, which composes with ``vmap`` over a meta-batch and with
ordinary autograd for the outer (meta) gradient:

* first order (default): the inner gradients are detached, so ``θ' = θ - lr * sg(g)`` and the meta-gradient flows
  through the identity path only (FOMAML);
* second order: the inner gradients keep their graph, so the meta-gradient includes the Hessian-vector terms.

Which parameters each loop adapts: the inner loop adapts the critic φ (both Q-heads, a regression onto n-step targets of
the support rewards, see :mod:`vafn_sb3.maml_sac.nstep`) and then the actor θ (the SAC policy loss against the adapted
critic), for ``steps`` rounds. The entropy coefficient, the target critic and the inner learning rates are meta-level
only.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.func import functional_call, grad

from vafn_sb3.maml_sac.policies import ActorDistribution, Params, detached, min_q, sample_action


def critic_regression_loss(
    critic_params: Params,
    critic: nn.Module,
    obs: torch.Tensor,
    actions: torch.Tensor,
    targets: torch.Tensor,
    centered: bool = False,
) -> torch.Tensor:
    """SB3's critic loss ``0.5 * sum_heads MSE(Q_j(s, a), y)`` for fixed targets ``y`` of shape ``(batch,)``.

    With ``centered`` both sides are centred over the batch first, so only the *relative* values are regressed: a
    task-independent offset between the critic and the n-step targets (e.g. the critic's overestimation) then neither
    dominates nor destabilises the inner step, and the actor step, which only reads ``∇_a Q``, loses nothing.
    """
    q_values = functional_call(critic, critic_params, (obs, actions))
    if centered:
        targets = targets - targets.mean()
        q_values = [q.squeeze(-1) - q.mean() for q in q_values]
    else:
        q_values = [q.squeeze(-1) for q in q_values]
    return 0.5 * sum(nn.functional.mse_loss(q, targets) for q in q_values)


def clip_gradients(grads: Params, max_norm: float | None) -> Params:
    """Scale a gradient dict to global L2 norm at most ``max_norm`` (differentiable; ``None`` leaves it unchanged)."""
    if max_norm is None:
        return grads
    norm = torch.sqrt(sum(g.pow(2).sum() for g in grads.values()))
    scale = torch.clamp(max_norm / (norm + 1e-6), max=1.0)
    return {name: g * scale for name, g in grads.items()}


def actor_loss(
    actor_params: Params,
    actor: ActorDistribution,
    critic: nn.Module,
    critic_params: Params,
    obs: torch.Tensor,
    ent_coef: torch.Tensor,
) -> torch.Tensor:
    """SAC's policy loss ``E_s[α log π(ã|s) - min_j Q_j(s, ã)]`` with ``ã ~ π(·|s)`` reparameterised."""
    actions, log_prob = sample_action(actor, actor_params, obs)
    return (ent_coef * log_prob - min_q(critic, critic_params, obs, actions)).mean()


def inner_adapt(
    actor: ActorDistribution,
    critic: nn.Module,
    actor_params: Params,
    critic_params: Params,
    obs: torch.Tensor,
    actions: torch.Tensor,
    targets: torch.Tensor,
    ent_coef: torch.Tensor,
    actor_lr: torch.Tensor,
    critic_lr: torch.Tensor,
    steps: int,
    second_order: bool,
    max_grad_norm: float | None = None,
    centered: bool = False,
) -> tuple[Params, Params]:
    """``steps`` rounds of (critic SGD step on the support targets, then actor SGD step against the adapted critic).

    :param actor: functional actor wrapper.
    :param critic: the SB3 critic module (used functionally).
    :param actor_params: starting actor parameters θ.
    :param critic_params: starting critic parameters φ.
    :param obs: support observations ``(n, obs_dim)``.
    :param actions: support actions ``(n, act_dim)`` (scaled to [-1, 1]).
    :param targets: n-step/MC targets of the support transitions ``(n,)`` (constants).
    :param ent_coef: entropy coefficient α (meta-level, detached).
    :param actor_lr: inner step size of the actor.
    :param critic_lr: inner step size of the critic.
    :param steps: number of inner rounds K (0 returns the inputs).
    :param second_order: keep the inner gradients' graph (true MAML) instead of detaching them (first-order MAML).
    :param max_grad_norm: clip each inner gradient (critic and actor separately) to this global norm.
    :param centered: regress centred values in the inner critic loss (see :func:`critic_regression_loss`).
    :return: adapted ``(actor_params, critic_params)``.
    """
    for _ in range(steps):
        critic_grads = grad(critic_regression_loss)(critic_params, critic, obs, actions, targets, centered)
        critic_grads = clip_gradients(critic_grads if second_order else detached(critic_grads), max_grad_norm)
        critic_params = {name: p - critic_lr * critic_grads[name] for name, p in critic_params.items()}
        actor_grads = grad(actor_loss)(actor_params, actor, critic, critic_params, obs, ent_coef)
        actor_grads = clip_gradients(actor_grads if second_order else detached(actor_grads), max_grad_norm)
        actor_params = {name: p - actor_lr * actor_grads[name] for name, p in actor_params.items()}
    return actor_params, critic_params


def query_losses(
    actor: ActorDistribution,
    critic: nn.Module,
    actor_params: Params,
    critic_params: Params,
    target_params: Params,
    support: dict[str, torch.Tensor],
    query: dict[str, torch.Tensor],
    ent_coef: torch.Tensor,
    actor_lr: torch.Tensor,
    critic_lr: torch.Tensor,
    steps: int,
    gamma: float,
    second_order: bool,
    max_grad_norm: float | None = None,
    centered: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One task's meta-objective: adapt on the support set, then SAC's critic and actor losses of θ', φ' on the query.

    The query critic target uses the meta-level target critic and the adapted actor (no gradient); the query actor loss
    uses the adapted critic detached, so it does not train the critic head-on.

    :param actor: functional actor wrapper.
    :param critic: the SB3 critic module.
    :param actor_params: meta actor parameters θ.
    :param critic_params: meta critic parameters φ.
    :param target_params: target critic parameters φ̄ (meta-level).
    :param support: ``observations``, ``actions``, ``targets`` of the task's support set.
    :param query: ``observations``, ``actions``, ``next_observations``, ``rewards``, ``dones`` (shape ``(b,)``) of a
        query minibatch.
    :param ent_coef: α (detached).
    :param actor_lr: inner actor step size.
    :param critic_lr: inner critic step size.
    :param steps: inner rounds K.
    :param gamma: discount factor.
    :param second_order: differentiate through the inner step.
    :param max_grad_norm: inner gradient clipping (see :func:`inner_adapt`).
    :param centered: centred inner critic loss (see :func:`critic_regression_loss`).
    :return: ``(critic_loss, actor_loss, mean log π of the adapted actor on query states (detached))``.
    """
    adapted_actor, adapted_critic = inner_adapt(
        actor, critic, actor_params, critic_params, support["observations"], support["actions"], support["targets"],
        ent_coef, actor_lr, critic_lr, steps, second_order, max_grad_norm, centered,
    )
    with torch.no_grad():
        next_actions, next_log_prob = sample_action(actor, detached(adapted_actor), query["next_observations"])
        next_value = min_q(critic, target_params, query["next_observations"], next_actions) - ent_coef * next_log_prob
        targets = query["rewards"] + (1.0 - query["dones"]) * gamma * next_value
    critic_loss = critic_regression_loss(adapted_critic, critic, query["observations"], query["actions"], targets)
    actions, log_prob = sample_action(actor, adapted_actor, query["observations"])
    policy_loss = (ent_coef * log_prob - min_q(critic, detached(adapted_critic), query["observations"], actions)).mean()
    return critic_loss, policy_loss, log_prob.detach().mean()
