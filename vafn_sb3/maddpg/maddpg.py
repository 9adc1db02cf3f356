"""MADDPG (Lowe et al., NeurIPS 2017) with parameter-shared decentralised actors, as an SB3 ``TD3`` subclass."""

from __future__ import annotations

from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
import torch.nn.functional as F
from stable_baselines3 import TD3
from stable_baselines3.common.noise import ActionNoise, NormalActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import MaybeCallback
from stable_baselines3.common.utils import polyak_update

from vafn_sb3.common.agents import clipped_step, frozen, substitute_agent_actions
from vafn_sb3.common.finetune import FineTuneAdaptation, GaussianExplorationPolicy
from vafn_sb3.common.save import AtomicSaveMixin
from vafn_sb3.maddpg.policies import MADDPGPolicy

SelfMADDPG = TypeVar("SelfMADDPG", bound="MADDPG")

#: ``openai/maddpg:maddpg/trainer/maddpg.py``: ``grad_norm_clipping=0.5`` for both the actor and the critic.
MAX_GRAD_NORM = 0.5
#: ``oxwhirl/facmac:src/learners/maddpg_learner.py``: ``pg_loss = -Q.mean() + (pi**2).mean() * 1e-3``.
ACTION_REG = 1e-3
#: Gaussian exploration noise, ``facmac`` ``maddpg_mamujoco.yaml`` (``exploration_mode: gaussian``, ``sigma 0.1``).
EXPLORATION_STD = 0.1


class MADDPG(AtomicSaveMixin, FineTuneAdaptation, TD3):
    """MADDPG: deterministic decentralised actors ``mu_i(o_i)`` trained through one centralised critic ``Q(s, a)``.

    Critic: TD(0) regression onto ``r + gamma (1 - d) Qbar(s', mu'(o'_1), ..., mu'(o'_N))`` with target actors and
    target critic (``openai/maddpg:maddpg/trainer/maddpg.py``, ``q_train``). Actor: agent ``i``'s loss evaluates the
    critic on the *buffered* joint action with only agent ``i``'s block replaced by ``mu_i(o_i)``
    (``p_train``: ``act_input_n[p_index] = act_pd.sample()``; ``oxwhirl/facmac:src/learners/maddpg_learner.py``:
    ``tem_joint_act[:, idx] = agent_outs[:, idx]``), averaged over agents, plus the ``1e-3 * mean(mu^2)`` action
    regulariser; both gradient norms are clipped at 0.5. SB3's ``TD3.train`` would instead feed *all* agents' current
    actions (FACMAC-style centralised policy gradient, ``uoe-agents/epymarl#31``). Defaults give plain MADDPG
    (``policy_delay=1``, no target-policy smoothing, one critic); TD3's defaults give MATD3.

    Parameters are SB3's ``TD3``'s (with the MADDPG defaults above and Gaussian exploration noise when none is given),
    plus:

    :param action_reg: weight of the squared-action regulariser of the actor loss.
    :param max_grad_norm: gradient-norm clip of actor and critic.
    :param exploration_std: std of the default Gaussian exploration noise (used when ``action_noise`` is None).
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": MADDPGPolicy}
    policy: MADDPGPolicy

    def __init__(
        self,
        policy: str | type[MADDPGPolicy] = "MlpPolicy",
        env: Any = None,
        action_noise: ActionNoise | None = None,
        policy_delay: int = 1,
        target_policy_noise: float = 0.0,
        action_reg: float = ACTION_REG,
        max_grad_norm: float = MAX_GRAD_NORM,
        exploration_std: float = EXPLORATION_STD,
        **kwargs: Any,
    ) -> None:
        if action_reg < 0 or max_grad_norm <= 0 or exploration_std < 0:
            raise ValueError("action_reg and exploration_std must be >= 0, max_grad_norm > 0")
        self.action_reg = action_reg
        self.max_grad_norm = max_grad_norm
        self.exploration_std = exploration_std
        super().__init__(
            policy, env, action_noise=action_noise, policy_delay=policy_delay, target_policy_noise=target_policy_noise,
            **kwargs,
        )

    def _setup_model(self) -> None:
        """TD3's setup, then the default Gaussian exploration noise, sized by the action space."""
        super()._setup_model()
        if self.action_noise is None and self.exploration_std > 0:
            n_actions = self.action_space.shape[0]
            self.action_noise = NormalActionNoise(np.zeros(n_actions), self.exploration_std * np.ones(n_actions))

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        """``gradient_steps`` MADDPG updates (centralised critic, per-agent substituted actor loss, soft targets)."""
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        actor_losses, critic_losses = [], []
        critic_parameters, actor_parameters = list(self.critic.parameters()), list(self.actor.parameters())
        layout = self.policy.agent_layout
        for _ in range(gradient_steps):
            self._n_updates += 1
            data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            discounts = data.discounts if data.discounts is not None else self.gamma
            with th.no_grad():
                next_actions = self.actor_target(data.next_observations)
                if self.target_policy_noise > 0:  # MATD3 target smoothing
                    noise = th.randn_like(next_actions) * self.target_policy_noise
                    noise = noise.clamp(-self.target_noise_clip, self.target_noise_clip)
                    next_actions = (next_actions + noise).clamp(-1, 1)
                next_q = th.cat(self.critic_target(data.next_observations, next_actions), dim=1)
                next_q = next_q.min(1, keepdim=True).values
                target_q = data.rewards + (1 - data.dones) * discounts * next_q
            critic_loss = sum(F.mse_loss(q, target_q) for q in self.critic(data.observations, data.actions))
            clipped_step(critic_loss, self.critic.optimizer, critic_parameters, self.max_grad_norm)
            critic_losses.append(critic_loss.item())

            if self._n_updates % self.policy_delay == 0:
                policy_actions = self.actor(data.observations)
                # others' actions from the buffer
                joint = substitute_agent_actions(data.actions, policy_actions, layout.action_per_agent)
                with frozen(self.critic):
                    q = self.critic.q1_forward(data.observations.repeat(layout.n_agents, 1), joint)
                    actor_loss = -q.mean() + self.action_reg * (policy_actions**2).mean()
                    clipped_step(actor_loss, self.actor.optimizer, actor_parameters, self.max_grad_norm)
                actor_losses.append(actor_loss.item())
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.actor.parameters(), self.actor_target.parameters(), self.tau)

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        if actor_losses:
            self.logger.record("train/actor_loss", float(np.mean(actor_losses)))
        self.logger.record("train/critic_loss", float(np.mean(critic_losses)))

    def _support_policy(self, seed: int | None) -> GaussianExplorationPolicy:
        """Support rollouts use the same Gaussian exploration as training (SB3's ``predict`` has no noise)."""
        return GaussianExplorationPolicy(self, self.exploration_std, seed)

    def learn(
        self: SelfMADDPG,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "MADDPG",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfMADDPG:
        """Train for ``total_timesteps`` joint env steps (see SB3's ``learn``)."""
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)
