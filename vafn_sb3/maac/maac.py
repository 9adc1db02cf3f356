"""MAAC: Multi-Actor-Attention-Critic (Iqbal & Sha, ICML 2019) for continuous actions, as an SB3 ``SAC`` subclass."""

from __future__ import annotations

from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
import torch.nn.functional as F
from stable_baselines3 import SAC
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import MaybeCallback
from stable_baselines3.common.utils import polyak_update

from vafn_sb3.common.agents import clipped_step, frozen
from vafn_sb3.common.finetune import FineTuneAdaptation
from vafn_sb3.common.save import AtomicSaveMixin
from vafn_sb3.maac.policies import AttentionCritic, MAACPolicy

SelfMAAC = TypeVar("SelfMAAC", bound="MAAC")

#: ``shariqiqbal2810/MAAC:utils/critics.py``: ``attend_mag_reg = 1e-3 * sum((logit**2).mean() ...)``.
ATTENTION_REG = 1e-3
#: ``algorithms/attention_sac.py``: ``clip_grad_norm(self.critic.parameters(), 10 * self.nagents)``.
CRITIC_MAX_GRAD_NORM_PER_AGENT = 10.0
#: ``algorithms/attention_sac.py``: ``clip_grad_norm(curr_agent.policy.parameters(), 0.5)``.
ACTOR_MAX_GRAD_NORM = 0.5


class MAAC(AtomicSaveMixin, FineTuneAdaptation, SAC):
    """Multi-Actor-Attention-Critic with per-agent soft Q-values ``Q_i(o, a)`` from an attention critic.

    What follows ``shariqiqbal2810/MAAC:algorithms/attention_sac.py`` (``update_critic`` / ``update_policies``):

    - per-agent soft targets ``y_i = r + gamma (1 - d) (min_k Qbar_k,i(o', a') - alpha log pi_i(a'_i | o'_i))`` with
      ``a' ~ pi(o')`` from the current policies (MAAC samples next actions from the target policies, which are soft
      copies of the policies; SB3's SAC keeps no target actor);
    - critic loss ``sum_i MSE(Q_i, y_i)`` plus the attention-logit L2 penalty (``attention_reg``), gradients of the
      parts shared across agents scaled by ``1/n_agents`` (``scale_shared_grads``), clipped at ``10 * n_agents``;
    - per-agent actor losses ``alpha log pi_i(a_i|o_i) - Q_i(o, a)`` summed over agents, with all agents' actions
      sampled from the current policies and only agent ``i``'s own action carrying the gradient into ``Q_i``
      (MAAC's ``update_policies`` scores each agent's own log-prob; for continuous actions the reparameterised
      gradient replaces its discrete counterfactual baseline, which it does not need); actor gradients clipped at 0.5.

    MAAC's ``reward_scale=100`` is a fixed temperature ``alpha = 0.01`` (``ent_coef=0.01``); SB3's automatic
    temperature (``ent_coef="auto"``, target entropy minus the joint action size, i.e. minus ``action_per_agent`` per
    agent) is also available. The decentralised actors share parameters across agents (local obs + one-hot id, or
    local obs only with ``policy_kwargs=dict(agent_ids=False)``); the number of agents comes from the spaces (see
    :class:`~vafn_sb3.common.agents.AgentLayout`).

    Parameters are SB3's ``SAC``'s, plus:

    :param attention_reg: weight of the attention-logit L2 penalty.
    :param critic_max_grad_norm: gradient-norm clip of the critic (None: MAAC's ``10 * n_agents``).
    :param actor_max_grad_norm: gradient-norm clip of the actor.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": MAACPolicy}
    policy: MAACPolicy
    critic: AttentionCritic
    critic_target: AttentionCritic

    def __init__(
        self,
        policy: str | type[MAACPolicy] = "MlpPolicy",
        env: Any = None,
        attention_reg: float = ATTENTION_REG,
        critic_max_grad_norm: float | None = None,
        actor_max_grad_norm: float = ACTOR_MAX_GRAD_NORM,
        **kwargs: Any,
    ) -> None:
        bad_critic_clip = critic_max_grad_norm is not None and critic_max_grad_norm <= 0
        if attention_reg < 0 or bad_critic_clip or actor_max_grad_norm <= 0:
            raise ValueError("attention_reg must be >= 0 and the gradient-norm clips > 0")
        self.attention_reg = attention_reg
        self.critic_max_grad_norm = critic_max_grad_norm
        self.actor_max_grad_norm = actor_max_grad_norm
        super().__init__(policy, env, **kwargs)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """``gradient_steps`` MAAC updates (per-agent attention critics, then per-agent actors, then targets)."""
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)
        logs: dict[str, list[float]] = {"actor_loss": [], "critic_loss": [], "attention_reg": [], "ent_coef": []}
        critic_parameters, actor_parameters = list(self.critic.parameters()), list(self.actor.parameters())
        shared_parameters = self.critic.shared_parameters()
        n_agents = self.policy.agent_layout.n_agents
        critic_max_grad_norm = self.critic_max_grad_norm or CRITIC_MAX_GRAD_NORM_PER_AGENT * n_agents

        for gradient_step in range(gradient_steps):
            data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            discounts = data.discounts if data.discounts is not None else self.gamma
            actions_pi, log_prob = self.actor.agent_action_log_prob(data.observations)  # (B, N * 3), (B, N)
            ent_coef = self._update_ent_coef(log_prob.sum(-1, keepdim=True))
            logs["ent_coef"].append(ent_coef.item())

            with th.no_grad():
                next_actions, next_log_prob = self.actor.agent_action_log_prob(data.next_observations)
                next_q = th.stack(self.critic_target(data.next_observations, next_actions)).min(0).values
                target_q = data.rewards + (1 - data.dones) * discounts * (next_q - ent_coef * next_log_prob)

            critic_loss = attention_reg = data.rewards.new_zeros(())
            for q, logits in self.critic.forward_with_logits(data.observations, data.actions):
                critic_loss = critic_loss + F.mse_loss(q, target_q, reduction="none").mean(0).sum()
                attention_reg = attention_reg + (logits**2).mean(dim=(0, 3)).sum()
            critic_loss = critic_loss + self.attention_reg * attention_reg
            self.critic.optimizer.zero_grad()
            critic_loss.backward()
            for parameter in shared_parameters:
                parameter.grad.mul_(1.0 / n_agents)
            th.nn.utils.clip_grad_norm_(critic_parameters, critic_max_grad_norm)
            self.critic.optimizer.step()

            # Q_i with agent i's own sampled action live and the other agents' samples detached.
            with frozen(self.critic):
                own_q = th.stack(self.critic.own_action_q(data.observations, actions_pi)).min(0).values
                actor_loss = (ent_coef * log_prob - own_q).sum(-1).mean()
                clipped_step(actor_loss, self.actor.optimizer, actor_parameters, self.actor_max_grad_norm)

            logs["critic_loss"].append(critic_loss.item())
            logs["attention_reg"].append(attention_reg.item())
            logs["actor_loss"].append(actor_loss.item())
            if gradient_step % self.target_update_interval == 0:
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)

        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in logs.items():
            self.logger.record(f"train/{key}", float(np.mean(values)))

    def _update_ent_coef(self, log_prob: th.Tensor) -> th.Tensor:
        """SB3 SAC's temperature step on the joint log-probability ``(B, 1)``; returns the (detached) coefficient."""
        if self.ent_coef_optimizer is None or self.log_ent_coef is None:
            return self.ent_coef_tensor
        ent_coef = th.exp(self.log_ent_coef.detach())
        ent_coef_loss = -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()
        self.ent_coef_optimizer.zero_grad()
        ent_coef_loss.backward()
        self.ent_coef_optimizer.step()
        return ent_coef

    def learn(
        self: SelfMAAC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "MAAC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfMAAC:
        """Train for ``total_timesteps`` joint env steps (see SB3's ``learn``)."""
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)
