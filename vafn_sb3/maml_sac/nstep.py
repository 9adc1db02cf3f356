"""n-step targets of support sets, the regression targets of MAML-SAC's inner critic step.

A target ``y_t = sum_j gamma^j r_{t+j} + c_t V(s'_{e_t})`` splits into a data-only part computed once per support set
(:meth:`~vafn_sb3.common.adaptation.SupportSet.nstep_plan`) and the value tail
``V(s') = min_j Q̄_j(s', ã) - α log π_θ(ã | s')``, ``ã ~ π_θ(· | s')``, from the target critic and the meta-actor,
recomputed at every outer step (both move).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
import torch
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from vafn_sb3.common.adaptation import SupportSet
from vafn_sb3.maml_sac.policies import ActorDistribution, Params, min_q, sample_action


def stack_supports(
    supports: Sequence[SupportSet],
    gamma: float,
    n_step: int | None,
    scale_action: Callable[[np.ndarray], np.ndarray],
    device: torch.device,
    vec_normalize_env: VecNormalize | None = None,
) -> dict[str, torch.Tensor]:
    """Stack equal-length support sets into ``(M, n, ...)`` tensors, with the data-only parts of their n-step targets.

    Support sets hold what the env returned; like SB3's replay buffer samples, observations and rewards are normalised
    here when training runs on a ``VecNormalize`` env, and actions are scaled to [-1, 1].

    :return: ``observations``, ``actions``, ``next_observations``, ``reward_sums``, ``stop_index`` (long) and
        ``bootstrap_discount``.
    """
    if vec_normalize_env is not None:
        supports = [
            dataclasses.replace(
                s,
                observations=vec_normalize_env.normalize_obs(s.observations),
                next_observations=vec_normalize_env.normalize_obs(s.next_observations),
                rewards=vec_normalize_env.normalize_reward(s.rewards),
            )
            for s in supports
        ]
    plans = [support.nstep_plan(gamma, n_step) for support in supports]

    def stacked(arrays: list[np.ndarray], dtype: torch.dtype = torch.float32) -> torch.Tensor:
        return torch.as_tensor(np.stack(arrays), dtype=dtype, device=device)

    return {
        "observations": stacked([s.observations for s in supports]),
        "actions": stacked([scale_action(s.actions) for s in supports]),
        "next_observations": stacked([s.next_observations for s in supports]),
        "reward_sums": stacked([p[0] for p in plans]),
        "stop_index": stacked([p[1] for p in plans], torch.long),
        "bootstrap_discount": stacked([p[2] for p in plans]),
    }


def nstep_targets(
    support: dict[str, torch.Tensor],
    actor: ActorDistribution,
    actor_params: Params,
    critic_target: nn.Module,
    target_params: Params,
    ent_coef: torch.Tensor,
) -> torch.Tensor:
    """n-step targets ``(M, n)`` of stacked supports, bootstrapped from the target critic and the (meta-)actor."""
    with torch.no_grad():
        next_obs = support["next_observations"].flatten(0, 1)
        next_actions, next_log_prob = sample_action(actor, actor_params, next_obs)
        values = min_q(critic_target, target_params, next_obs, next_actions) - ent_coef * next_log_prob
        values = values.view(support["reward_sums"].shape)
        return support["reward_sums"] + support["bootstrap_discount"] * values.gather(1, support["stop_index"])
