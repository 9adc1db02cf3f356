"""MAPPO (Yu et al., NeurIPS 2022 Datasets & Benchmarks) as an SB3 ``PPO`` subclass."""

from __future__ import annotations

from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
import torch.nn.functional as F
from stable_baselines3 import PPO
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import MaybeCallback

from vafn_sb3.common.adaptation import SupportSet
from vafn_sb3.common.finetune import FineTuneAdaptation
from vafn_sb3.common.save import AtomicSaveMixin
from vafn_sb3.mappo.policies import AgentRolloutBuffer, MAPPOPolicy

SelfMAPPO = TypeVar("SelfMAPPO", bound="MAPPO")

#: ``onpolicy/config.py`` defaults: ``--huber_delta 10.0``, ``--ppo_epoch 15`` (MPE scripts use 10),
#: ``--num_mini_batch 1``, ``--lr 5e-4``, ``--entropy_coef 0.01``, ``--value_loss_coef 1``, ``--max_grad_norm 10.0``,
#: ``--clip_param 0.2``.
HUBER_DELTA = 10.0
N_EPOCHS = 10
NUM_MINI_BATCH = 1
LEARNING_RATE = 5e-4
ENT_COEF = 0.01
VF_COEF = 1.0
MAX_GRAD_NORM = 10.0
CLIP_RANGE = 0.2
#: ``onpolicy/algorithms/r_mappo/r_mappo.py``: ``(advantages - mean) / (std + 1e-5)`` over the whole buffer.
ADVANTAGE_EPS = 1e-5


class MAPPO(AtomicSaveMixin, FineTuneAdaptation, PPO):
    """Multi-agent PPO with a shared decentralised actor, a centralised critic, per-agent ratios and ValueNorm.

    Follows ``marlbenchmark/on-policy:onpolicy/algorithms/r_mappo/r_mappo.py`` (``R_MAPPO.train``/``ppo_update``):

    - every agent's step is its own PPO sample: ratios ``r_i = pi(a_i|o_i) / pi_old(a_i|o_i)`` of shape ``(B, N)``,
      each clipped separately, the (team) advantage broadcast to every agent, mean over samples and agents (SB3's PPO
      would clip the *joint* ratio ``prod_i r_i``);
    - advantages normalised once over the whole rollout with ``+1e-5``;
    - value loss on the ValueNorm scale: the normaliser is updated with each minibatch's returns, then
      ``max(huber(norm(R) - V), huber(norm(R) - V_clipped))`` with ``huber_delta=10`` and value clipping around the
      old normalised prediction (``clip_range_vf``, default = ``clip_range``, as on-policy's ``clip_param``);
    - actor and critic gradient norms clipped *separately* at ``max_grad_norm``. One Adam over both parameter groups
      equals on-policy's two Adams (Adam is per-parameter and the groups share no parameter);
    - defaults: lr 5e-4, 10 epochs, one minibatch, clip 0.2, entropy 0.01, value coef 1, grad clip 10.

    Parameters are SB3's ``PPO``'s, plus:

    :param num_mini_batch: minibatches per epoch (on-policy's name; 1 = full-batch); sets ``batch_size`` to
        ``n_steps * n_envs / num_mini_batch``.
    :param batch_size: explicit minibatch size instead of ``num_mini_batch`` (SB3's name, e.g. from zoo tuning).
    :param huber_delta: delta of the Huber value loss.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"MlpPolicy": MAPPOPolicy}
    policy: MAPPOPolicy
    rollout_buffer: AgentRolloutBuffer
    _adaptation_attributes = (*FineTuneAdaptation._adaptation_attributes, "rollout_buffer", "n_epochs", "batch_size")

    def __init__(
        self,
        policy: str | type[MAPPOPolicy] = "MlpPolicy",
        env: Any = None,
        learning_rate: float = LEARNING_RATE,
        n_epochs: int = N_EPOCHS,
        num_mini_batch: int = NUM_MINI_BATCH,
        batch_size: int | None = None,
        clip_range: float = CLIP_RANGE,
        clip_range_vf: float | None = CLIP_RANGE,
        ent_coef: float = ENT_COEF,
        vf_coef: float = VF_COEF,
        max_grad_norm: float = MAX_GRAD_NORM,
        huber_delta: float = HUBER_DELTA,
        _init_setup_model: bool = True,
        **kwargs: Any,
    ) -> None:
        if batch_size is not None and num_mini_batch != NUM_MINI_BATCH:
            raise ValueError("pass either batch_size or num_mini_batch, not both")
        if batch_size is not None and batch_size < 2:
            raise ValueError(f"batch_size must be >= 2 (advantage normalisation), got {batch_size}")
        if "rollout_buffer_class" in kwargs:
            raise ValueError("MAPPO needs its AgentRolloutBuffer; rollout_buffer_class cannot be changed")
        if num_mini_batch < 1 or huber_delta <= 0:
            raise ValueError(f"need num_mini_batch >= 1 and huber_delta > 0, got {num_mini_batch}, {huber_delta}")
        self.num_mini_batch = num_mini_batch
        self.huber_delta = huber_delta
        super().__init__(
            policy, env, learning_rate=learning_rate, n_epochs=n_epochs, clip_range=clip_range,
            clip_range_vf=clip_range_vf, ent_coef=ent_coef, vf_coef=vf_coef, max_grad_norm=max_grad_norm,
            rollout_buffer_class=AgentRolloutBuffer, _init_setup_model=False, **kwargs,
        )
        if batch_size is not None:
            self.batch_size = batch_size
        elif self.env is not None:
            rollout_size = self.n_steps * self.n_envs
            if rollout_size % num_mini_batch != 0 or rollout_size // num_mini_batch < 2:
                raise ValueError(
                    f"n_steps * n_envs ({rollout_size}) must split into {num_mini_batch} minibatches of >= 2 samples"
                )
            self.batch_size = rollout_size // num_mini_batch
        if _init_setup_model:
            self._setup_model()

    def _prepare_rollout(self) -> None:
        """Per-agent old log-probs and old normalised values (policy = behaviour policy), normalised advantages."""
        buffer = self.rollout_buffer
        with th.no_grad():
            n_samples = buffer.buffer_size * buffer.n_envs
            observations = buffer.to_torch(buffer.observations.reshape(n_samples, -1))
            actions = buffer.to_torch(buffer.actions.reshape(n_samples, -1))
            values, agent_log_prob, _ = self.policy.evaluate_agent_actions(observations, actions)
        buffer.set_agent_statistics(agent_log_prob.cpu().numpy(), values.cpu().numpy())
        if self.normalize_advantage:
            advantages = buffer.advantages
            buffer.advantages = (advantages - advantages.mean()) / (advantages.std() + ADVANTAGE_EPS)

    def _huber(self, error: th.Tensor) -> th.Tensor:
        return F.huber_loss(error, th.zeros_like(error), reduction="none", delta=self.huber_delta)

    def train(self) -> None:
        """``n_epochs`` passes over the rollout with per-agent clipped ratios and the ValueNorm Huber value loss."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        progress = self._current_progress_remaining
        clip_range = self.clip_range(progress)  # type: ignore[operator]
        clip_range_vf = None if self.clip_range_vf is None else self.clip_range_vf(progress)  # type: ignore[operator]
        self._prepare_rollout()
        actor_parameters, critic_parameters = self.policy.actor_parameters(), self.policy.critic_parameters()
        log_keys = ("policy_gradient_loss", "value_loss", "entropy", "clip_fraction")
        logs: dict[str, list[float]] = {key: [] for key in log_keys}
        approx_kl_divs: list[float] = []
        continue_training = True
        for epoch in range(self.n_epochs):
            for data in self.rollout_buffer.get(self.batch_size):
                values, agent_log_prob, entropy = self.policy.evaluate_agent_actions(data.observations, data.actions)
                log_ratio = agent_log_prob - data.old_agent_log_prob  # (B, N): one PPO sample per agent step
                ratio = th.exp(log_ratio)
                advantages = data.advantages.unsqueeze(-1)
                clipped_ratio = ratio.clamp(1 - clip_range, 1 + clip_range)
                policy_loss = -th.min(ratio * advantages, clipped_ratio * advantages).mean()

                self.policy.value_norm.update(data.returns)
                targets = self.policy.value_norm.normalize(data.returns)
                value_loss = self._huber(targets - values)
                if clip_range_vf is not None:
                    old_values = data.old_normalized_values
                    clipped = old_values + (values - old_values).clamp(-clip_range_vf, clip_range_vf)
                    value_loss = th.max(value_loss, self._huber(targets - clipped))
                value_loss = value_loss.mean()

                with th.no_grad():
                    approx_kl = th.mean(ratio - 1 - log_ratio).item()
                approx_kl_divs.append(approx_kl)
                if self.target_kl is not None and approx_kl > 1.5 * self.target_kl:
                    continue_training = False
                    if self.verbose >= 1:
                        print(f"Early stopping at step {epoch} due to reaching max kl: {approx_kl:.2f}")
                    break

                mean_entropy = entropy.mean()
                loss = policy_loss - self.ent_coef * mean_entropy + self.vf_coef * value_loss
                self.policy.optimizer.zero_grad()
                loss.backward()
                th.nn.utils.clip_grad_norm_(actor_parameters, self.max_grad_norm)
                th.nn.utils.clip_grad_norm_(critic_parameters, self.max_grad_norm)
                self.policy.optimizer.step()
                logs["policy_gradient_loss"].append(policy_loss.item())
                logs["value_loss"].append(value_loss.item())
                logs["entropy"].append(mean_entropy.item())
                logs["clip_fraction"].append(th.mean((th.abs(ratio - 1) > clip_range).float()).item())
            self._n_updates += 1
            if not continue_training:
                break

        for key, values_logged in logs.items():
            if values_logged:
                self.logger.record(f"train/{key}", float(np.mean(values_logged)))
        self.logger.record("train/approx_kl", float(np.mean(approx_kl_divs)))
        self.logger.record("train/std", th.exp(self.policy.agent_log_std).mean().item())
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/clip_range", clip_range)

    def _fine_tune(self, support: SupportSet, k: int) -> None:
        """``k`` full-batch MAPPO updates (``k`` epochs of one minibatch) on the support set, with GAE as in training.

        :param support: the support transitions (actions as sent to the env, i.e. clipped to the action bounds).
        :param k: number of gradient steps.
        """
        n = len(support)
        if n < 2:
            raise ValueError("MAPPO fine-tuning needs n_support >= 2 (advantage normalisation)")
        buffer = AgentRolloutBuffer(n, self.observation_space, self.action_space, device=self.device,
                                    gae_lambda=self.gae_lambda, gamma=self.gamma, n_envs=1)
        with th.no_grad():
            observations = buffer.to_torch(support.observations)
            values = self.policy.predict_values(observations)
            log_prob = self.policy.evaluate_actions(observations, buffer.to_torch(support.actions))[1]
            next_values = self.policy.predict_values(buffer.to_torch(support.next_observations)).cpu().numpy().ravel()
        rewards = support.rewards.copy()
        # Bootstrap episodes cut by truncation inside the support set, exactly as SB3's collect_rollouts does.
        truncated = (support.episode_ends > 0) & (support.terminated == 0)
        truncated[-1] = False  # the last step is bootstrapped through last_values below
        rewards[truncated] += self.gamma * next_values[truncated]
        episode_starts = np.concatenate([[1.0], support.episode_ends[:-1]])
        for t in range(n):
            buffer.add(support.observations[t : t + 1], support.actions[t : t + 1], rewards[t : t + 1],
                       episode_starts[t : t + 1], values[t : t + 1], log_prob[t : t + 1])
        buffer.compute_returns_and_advantage(
            last_values=buffer.to_torch(next_values[-1:]), dones=support.terminated[-1:]
        )
        self.rollout_buffer, self.n_epochs, self.batch_size = buffer, k, n
        self.train()

    def learn(
        self: SelfMAPPO,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "MAPPO",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfMAPPO:
        """Train for ``total_timesteps`` joint env steps (see SB3's ``learn``)."""
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)
