"""MAML-SAC (algo key ``maml_sac``): Soft Actor-Critic meta-trained with MAML inner/outer updates over a task pool.

Not to be confused with "Meta-SAC" (arXiv 2007.01932), which meta-learns SAC's entropy temperature only.

After an optional warm-up of plain multi-task SAC, one meta-iteration (:meth:`MAMLSAC._meta_iteration`):

1. sample ``meta_batch_size`` training tasks from a fixed pool;
2. support: per task, ``env_method("set_task", task)`` on every env, reset, and ``n_support`` transitions of the
   stochastic meta-policy π_θ through SB3's ``collect_rollouts`` (the task's support set, replaced every iteration);
3. inner adaptation: per task, ``inner_steps`` graph-free rounds of critic-then-actor SGD on its support set
   (:mod:`vafn_sb3.maml_sac.functional`);
4. query: per task, ``n_query`` transitions of the adapted stochastic policy π_θ' into the task's query replay buffer
   (a FIFO kept across iterations);
5. outer steps (:meth:`MAMLSAC.meta_train`): ``outer_steps`` meta-gradient steps; per task, re-adapt on the support set
   (with the inner graph when ``second_order``), evaluate SAC's critic and actor losses of (θ'_i, φ'_i) on a query
   minibatch, average over tasks, step SB3's own actor/critic optimisers (which hold θ and φ), the entropy coefficient
   (on the adapted actors' log-probs) and, if learned, the inner step sizes; Polyak-update the target critic.

``learn`` then takes ``sac_gradient_steps`` plain SAC gradient steps on the whole replay buffer (every transition of
every task so far), so that the outer steps' narrow meta-batch data do not make the meta-policy forget the tasks it
already solves. Every env step goes to the replay buffer through SB3's ``_store_transition``.

Parameters adapted by the inner loop: the critic φ (both Q-heads) and the actor θ. Meta-level only: the entropy
coefficient α, the target critic φ̄ and the inner step sizes.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from typing import Any, ClassVar, TypeVar

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import (
    GymEnv, MaybeCallback, RolloutReturn, Schedule, TrainFreq, TrainFrequencyUnit,
)
from stable_baselines3.common.utils import polyak_update
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.sac import SAC
from stable_baselines3.sac.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, SACPolicy
from torch.func import vmap

from vafn_gym.instructions import Instruction
from vafn_sb3.common.adaptation import SupportSet, collect_support, is_task_list, seeded_torch_stream
from vafn_sb3.common.save import AtomicSaveMixin
from vafn_sb3.maml_sac.buffers import TaskRolloutBuffer
from vafn_sb3.maml_sac.functional import inner_adapt, query_losses
from vafn_sb3.maml_sac.nstep import nstep_targets, stack_supports
from vafn_sb3.sac.lean import LeanSACMixin
from vafn_sb3.maml_sac.policies import ActorDistribution, AdaptedSACPolicy, Params, detached, parameters_of
from vafn_sb3.sac.policies import SharedAgentPolicy

SelfMAMLSAC = TypeVar("SelfMAMLSAC", bound="MAMLSAC")

#: Ways of evaluating the per-task meta-objective over the meta-batch.
META_BATCH_MODES = ("vmap", "loop")
#: Completed episodes remembered for the pre/post-adaptation TensorBoard scalars.
EPISODE_STATS_WINDOW = 100


class MAMLSAC(AtomicSaveMixin, LeanSACMixin, SAC):
    """SAC meta-trained with MAML over the env's task distribution; :meth:`adapt` specialises it to one task.

    Takes SB3's :class:`~stable_baselines3.SAC` arguments (``learning_rate`` to ``device``: same names, defaults and
    meaning; they drive the warm-up, the plain SAC steps and the outer steps; ``use_sde`` must stay False), plus:

    :param policy: SAC policy (``"SharedAgentPolicy"``: one actor shared by every arm, or ``"MlpPolicy"``); no gSDE,
        no BatchNorm.
    :param env: env or VecEnv whose envs expose ``set_task`` (all envs run the same task at a time).
    :param meta_batch_size: tasks per meta-iteration (5, as in the paper).
    :param n_support: support transitions per task per iteration, collected with the stochastic meta-policy.
    :param n_query: query transitions per task per iteration, collected with the stochastic adapted policy.
    :param inner_steps: inner rounds K during meta-training (one critic then one actor SGD step per round).
    :param inner_actor_lr: initial inner step size of the actor.
    :param inner_critic_lr: initial inner step size of the critic.
    :param inner_n_step: rewards summed in the inner critic targets (1 = TD, ``None`` = Monte Carlo to the episode end);
        tails bootstrap from the target critic and the meta-actor.
    :param inner_max_grad_norm: clip every inner gradient (critic and actor separately) to this norm; ``None``: no clip.
        Unclipped, the inner critic step can explode when the critic's scale is off (measured: gradient norm ~1700).
    :param inner_centered_critic: regress centred values in the inner critic loss (only relative values adapt).
    :param learn_inner_lr: meta-learn the two inner step sizes (log-parameterised, own Adam optimiser).
    :param inner_lr_learning_rate: learning rate of that optimiser.
    :param second_order: differentiate through the inner step (``create_graph``); default first-order MAML.
    :param outer_steps: meta-gradient steps per meta-iteration (off-policy reuse of the query buffers).
    :param n_train_tasks: size of the fixed pool of training tasks drawn from the env's sampler (``train_tasks``
        overrides it).
    :param train_tasks: explicit training tasks; ``None`` draws the pool from ``env``'s own task sampler.
    :param query_buffer_size: capacity of each task's query FIFO.
    :param warmup_steps: env steps of plain multi-task SAC (env-sampled tasks) before meta-training starts.
    :param sac_gradient_steps: plain SAC gradient steps on the whole replay buffer after every meta-iteration (``-1``:
        one per env step the iteration collected, SAC's own ratio; ``0``: none, pure MAML). Measured on
        ``VAFN/ThreeArmReach-v1``: without them the outer steps, which see only the meta-batch's few hundred query
        transitions, pulled a solved policy from success 1.0 to 0.0-0.15 within a few meta-iterations.
    :param meta_batch_mode: ``"vmap"`` (the meta-batch in one ``torch.func.vmap`` call) or ``"loop"``
        (one call per task).
    :param max_grad_norm: clip the meta-gradient of actor and critic to this norm.
    :param task_seed: seed of the task pool and of the meta-batch draws.
    :param lean_update: the warm-up and plain SAC steps (``train``) take the lean update of SAC's losses
        (:mod:`vafn_sb3.sac.lean`); False runs SB3's ``SAC.train``. The meta-steps are unaffected.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "SharedAgentPolicy": SharedAgentPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }

    def __init__(
        self,
        policy: str | type[SACPolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        ent_coef: str | float = "auto",
        target_update_interval: int = 1,
        target_entropy: str | float = "auto",
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        use_sde_at_warmup: bool = False,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: torch.device | str = "auto",
        meta_batch_size: int = 5,
        n_support: int = 200,
        n_query: int = 200,
        inner_steps: int = 1,
        inner_actor_lr: float = 0.01,
        inner_critic_lr: float = 0.005,
        inner_n_step: int | None = 10,
        inner_max_grad_norm: float | None = 10.0,
        inner_centered_critic: bool = True,
        learn_inner_lr: bool = True,
        inner_lr_learning_rate: float = 1e-3,
        second_order: bool = False,
        outer_steps: int = 20,
        n_train_tasks: int = 40,
        train_tasks: Sequence[Any] | None = None,
        query_buffer_size: int = 10_000,
        warmup_steps: int = 0,
        sac_gradient_steps: int = 0,
        meta_batch_mode: str = "vmap",
        max_grad_norm: float = 10.0,
        task_seed: int = 0,
        lean_update: bool = True,
        _init_setup_model: bool = True,
    ) -> None:
        counts = {"meta_batch_size": meta_batch_size, "n_support": n_support, "n_query": n_query,
                  "outer_steps": outer_steps, "n_train_tasks": n_train_tasks, "query_buffer_size": query_buffer_size}
        for name, value in counts.items():
            if int(value) < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        if inner_steps < 0 or warmup_steps < 0:
            raise ValueError(f"inner_steps and warmup_steps must be >= 0, got {inner_steps}, {warmup_steps}")
        if int(sac_gradient_steps) < -1:
            raise ValueError(f"sac_gradient_steps must be -1 or >= 0, got {sac_gradient_steps}")
        if inner_actor_lr <= 0 or inner_critic_lr <= 0:
            raise ValueError(f"inner learning rates must be > 0, got {inner_actor_lr}, {inner_critic_lr}")
        if inner_n_step is not None and inner_n_step < 1:
            raise ValueError(f"inner_n_step must be >= 1 or None, got {inner_n_step}")
        if inner_max_grad_norm is not None and inner_max_grad_norm <= 0:
            raise ValueError(f"inner_max_grad_norm must be > 0 or None, got {inner_max_grad_norm}")
        if meta_batch_mode not in META_BATCH_MODES:
            raise ValueError(f"meta_batch_mode must be one of {META_BATCH_MODES}, got {meta_batch_mode!r}")
        if use_sde:
            raise ValueError("MAML-SAC does not support use_sde=True")
        super().__init__(
            policy, env, learning_rate=learning_rate, buffer_size=buffer_size, learning_starts=learning_starts,
            batch_size=batch_size, tau=tau, gamma=gamma, train_freq=train_freq, gradient_steps=gradient_steps,
            action_noise=action_noise, replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs, optimize_memory_usage=optimize_memory_usage, n_steps=n_steps,
            ent_coef=ent_coef, target_update_interval=target_update_interval, target_entropy=target_entropy,
            use_sde=use_sde, sde_sample_freq=sde_sample_freq, use_sde_at_warmup=use_sde_at_warmup,
            stats_window_size=stats_window_size, tensorboard_log=tensorboard_log, policy_kwargs=policy_kwargs,
            verbose=verbose, seed=seed, device=device, lean_update=lean_update, _init_setup_model=False,
        )
        self.meta_batch_size = int(meta_batch_size)
        self.n_support = int(n_support)
        self.n_query = int(n_query)
        self.inner_steps = int(inner_steps)
        self.inner_actor_lr = float(inner_actor_lr)
        self.inner_critic_lr = float(inner_critic_lr)
        self.inner_n_step = inner_n_step
        self.inner_max_grad_norm = None if inner_max_grad_norm is None else float(inner_max_grad_norm)
        self.inner_centered_critic = bool(inner_centered_critic)
        self.learn_inner_lr = bool(learn_inner_lr)
        self.inner_lr_learning_rate = float(inner_lr_learning_rate)
        self.second_order = bool(second_order)
        self.outer_steps = int(outer_steps)
        self.n_train_tasks = int(n_train_tasks)
        self.train_tasks = None if train_tasks is None else [Instruction.coerce(t) for t in train_tasks]
        self.query_buffer_size = int(query_buffer_size)
        self.warmup_steps = int(warmup_steps)
        self.sac_gradient_steps = int(sac_gradient_steps)
        self.meta_batch_mode = meta_batch_mode
        self.max_grad_norm = float(max_grad_norm)
        self.task_seed = int(task_seed)
        self.meta_iterations = 0
        self.task_rng = np.random.default_rng(task_seed)
        if _init_setup_model:
            self._setup_model()

    # --- setup, save/load ---
    def _setup_model(self) -> None:
        """SAC's setup, the functional actor, the (log) inner step sizes and their optimiser, and the per-task state."""
        super()._setup_model()
        self.actor_distribution = ActorDistribution(self.actor)
        initial = torch.tensor([self.inner_actor_lr, self.inner_critic_lr], device=self.device).log()
        self.log_inner_lrs = initial.requires_grad_(self.learn_inner_lr)
        self.inner_lr_optimizer = (
            torch.optim.Adam([self.log_inner_lrs], lr=self.inner_lr_learning_rate) if self.learn_inner_lr else None
        )
        self.support_sets: dict[int, SupportSet] = {}
        self.query_buffers: dict[int, ReplayBuffer] = {}
        self.pre_adaptation_episodes: deque[dict[str, float]] = deque(maxlen=EPISODE_STATS_WINDOW)
        self.post_adaptation_episodes: deque[dict[str, float]] = deque(maxlen=EPISODE_STATS_WINDOW)
        self.acting_policy: AdaptedSACPolicy | None = None

    def _excluded_save_params(self) -> list[str]:
        """Aliases and the per-task state (rebuilt on load) are not pickled."""
        return super()._excluded_save_params() + [
            "actor_distribution", "support_sets", "query_buffers", "pre_adaptation_episodes",
            "post_adaptation_episodes", "acting_policy",
        ]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        """SAC's state dicts and variables, plus the inner step sizes and their optimiser."""
        state_dicts, variables = super()._get_torch_save_params()
        if self.inner_lr_optimizer is not None:
            state_dicts = [*state_dicts, "inner_lr_optimizer"]
        return state_dicts, [*variables, "log_inner_lrs"]

    # --- helpers ---
    @property
    def inner_lrs(self) -> tuple[float, float]:
        """Current (actor, critic) inner step sizes."""
        actor_lr, critic_lr = self.log_inner_lrs.detach().exp().tolist()
        return actor_lr, critic_lr

    def _ent_coef(self) -> torch.Tensor:
        if self.ent_coef_optimizer is not None:
            return self.log_ent_coef.detach().exp()
        return self.ent_coef_tensor

    def _task_pool(self) -> list[Any]:
        if self.train_tasks is None:
            # An instruction TaskSampler, or any task source with fixed_set (vafn_gym.wrappers.DynamicsTasks' variants).
            sampler = self.env.get_attr("sampler", indices=0)[0]
            if not callable(getattr(sampler, "fixed_set", None)):
                raise TypeError("the env's 'sampler' has no fixed_set(n, seed); pass train_tasks= to MAMLSAC")
            self.train_tasks = sampler.fixed_set(self.n_train_tasks, seed=self.task_seed)
        return self.train_tasks

    def _query_buffer(self, task_id: int) -> ReplayBuffer:
        if task_id not in self.query_buffers:
            self.query_buffers[task_id] = ReplayBuffer(
                self.query_buffer_size, self.observation_space, self.action_space, device=self.device,
                n_envs=self.n_envs, optimize_memory_usage=False, handle_timeout_termination=True,
            )
        return self.query_buffers[task_id]

    def _support_tensors(self, supports: Sequence[SupportSet]) -> dict[str, torch.Tensor]:
        return stack_supports(supports, self.gamma, self.inner_n_step, self.policy.scale_action, self.device,
                              self._vec_normalize_env)

    def _support_targets(self, support: dict[str, torch.Tensor], ent_coef: torch.Tensor) -> torch.Tensor:
        return nstep_targets(support, self.actor_distribution, detached(parameters_of(self.actor_distribution)),
                             self.critic_target, parameters_of(self.critic_target), ent_coef)

    def adapted_parameters(self, supports: Sequence[SupportSet], steps: int) -> list[tuple[Params, Params]]:
        """First-order, graph-free adaptation of (actor, critic) parameters on each support set; the model is untouched.

        :param supports: one support set per task (equal lengths).
        :param steps: inner rounds K.
        :return: per task, detached adapted ``(actor_params, critic_params)``.
        """
        ent_coef = self._ent_coef()
        support = self._support_tensors(supports)
        targets = self._support_targets(support, ent_coef)
        actor_lr, critic_lr = self.log_inner_lrs.detach().exp()
        adapted = []
        with torch.no_grad():
            for i in range(len(supports)):
                actor_params, critic_params = inner_adapt(
                    self.actor_distribution, self.critic,
                    parameters_of(self.actor_distribution, detach=True), parameters_of(self.critic, detach=True),
                    support["observations"][i], support["actions"][i], targets[i],
                    ent_coef, actor_lr, critic_lr, steps, second_order=False,
                    max_grad_norm=self.inner_max_grad_norm, centered=self.inner_centered_critic,
                )
                adapted.append((detached(actor_params), detached(critic_params)))
        return adapted

    # --- data collection: SB3's collect_rollouts, one task at a time ---
    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """SAC's exploration action, or during a query rollout a sample of the adapted policy ``acting_policy``."""
        if self.acting_policy is None:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        action, _ = self.acting_policy.predict(self._last_obs, deterministic=False)
        return action, self.policy.scale_action(action)

    def _task_rollout(
        self,
        task: Instruction,
        n_transitions: int,
        callback: BaseCallback,
        acting_policy: AdaptedSACPolicy | None = None,
        query_buffer: ReplayBuffer | None = None,
    ) -> TaskRolloutBuffer | None:
        """``n_transitions`` (rounded up to whole vectorised steps) on ``task`` through SB3's ``collect_rollouts``.

        Every env gets ``task`` and starts a fresh episode, so that no episode straddles two tasks. Acts with
        ``acting_policy`` (the meta-policy if ``None``; never SB3's uniform warm-up actions); the transitions go to the
        replay buffer and ``query_buffer``. Returns them (with the stats of the completed episodes), or ``None`` if a
        callback stopped training.
        """
        self.env.env_method("set_task", task)
        self._last_obs = self.env.reset()
        if self._vec_normalize_env is not None:
            self._last_original_obs = self._vec_normalize_env.get_original_obs()
        buffers = [self.replay_buffer] if query_buffer is None else [self.replay_buffer, query_buffer]
        task_buffer = TaskRolloutBuffer(buffers, self.policy.unscale_action, self.n_envs)
        train_freq = TrainFreq(-(-n_transitions // self.n_envs), TrainFrequencyUnit.STEP)
        self.acting_policy = acting_policy
        try:
            rollout = self.collect_rollouts(self.env, callback, train_freq, task_buffer, learning_starts=0)
        finally:
            self.acting_policy = None
        return task_buffer if rollout.continue_training else None

    # --- meta-training ---
    def _meta_iteration(self, callback: BaseCallback) -> RolloutReturn:
        """Sample tasks → collect support → inner adapt → collect query → outer steps (returned like a rollout).

        :return: the env steps and episodes it took, and False if a callback stopped training.
        """
        steps_before, episodes_before = self.num_timesteps, self._episode_num

        def done(continue_training: bool) -> RolloutReturn:
            return RolloutReturn(self.num_timesteps - steps_before, self._episode_num - episodes_before,
                                 continue_training)

        pool = self._task_pool()
        size = self.meta_batch_size
        task_ids = [int(t) for t in self.task_rng.choice(len(pool), size=size, replace=size > len(pool))]
        supports = []
        for task_id in task_ids:
            rollout = self._task_rollout(pool[task_id], self.n_support, callback)
            if rollout is None:
                return done(False)
            supports.append(rollout.support_set())
            self.support_sets[task_id] = supports[-1]
            self.pre_adaptation_episodes.extend(rollout.episodes)
        adapted = self.adapted_parameters(supports, self.inner_steps)
        for task_id, (actor_params, critic_params) in zip(task_ids, adapted):
            policy = AdaptedSACPolicy(self.policy, self.actor_distribution, actor_params, critic_params)
            rollout = self._task_rollout(pool[task_id], self.n_query, callback, policy, self._query_buffer(task_id))
            if rollout is None:
                return done(False)
            self.post_adaptation_episodes.extend(rollout.episodes)
        self.meta_train(task_ids)
        self.meta_iterations += 1
        return done(True)

    def _query_batch(self, task_ids: Sequence[int]) -> dict[str, torch.Tensor]:
        """One query minibatch per task, stacked to ``(M, batch_size, ...)``."""
        samples = [self.query_buffers[t].sample(self.batch_size, env=self._vec_normalize_env) for t in task_ids]
        return {
            "observations": torch.stack([s.observations for s in samples]),
            "actions": torch.stack([s.actions for s in samples]),
            "next_observations": torch.stack([s.next_observations for s in samples]),
            "rewards": torch.stack([s.rewards.squeeze(-1) for s in samples]),
            "dones": torch.stack([s.dones.squeeze(-1) for s in samples]),
        }

    def _meta_losses(
        self, support: dict[str, torch.Tensor], query: dict[str, torch.Tensor], ent_coef: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Meta-batch means of the query critic and actor losses after adaptation, and the adapted log-probs."""
        actor_params, critic_params = parameters_of(self.actor_distribution), parameters_of(self.critic)
        target_params = parameters_of(self.critic_target)
        actor_lr, critic_lr = self.log_inner_lrs.exp()

        def task_objective(task_support: dict[str, torch.Tensor], task_query: dict[str, torch.Tensor]):
            return query_losses(
                self.actor_distribution, self.critic, actor_params, critic_params, target_params, task_support,
                task_query, ent_coef, actor_lr, critic_lr, self.inner_steps, self.gamma, self.second_order,
                self.inner_max_grad_norm, self.inner_centered_critic,
            )

        if self.meta_batch_mode == "vmap":
            critic_loss, actor_loss, log_prob = vmap(task_objective, randomness="different")(support, query)
        else:
            per_task = [
                task_objective({k: v[i] for k, v in support.items()}, {k: v[i] for k, v in query.items()})
                for i in range(len(query["rewards"]))
            ]
            critic_loss, actor_loss, log_prob = (torch.stack(column) for column in zip(*per_task))
        return critic_loss.mean(), actor_loss.mean(), log_prob

    def meta_train(self, task_ids: Sequence[int]) -> None:
        """``outer_steps`` meta-gradient steps on the support sets and query buffers of ``task_ids``."""
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.actor.optimizer, self.critic.optimizer])
        support = self._support_tensors([self.support_sets[t] for t in task_ids])
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.inner_lr_optimizer is not None:
            optimizers.append(self.inner_lr_optimizer)
        critic_losses, actor_losses, ent_coefs, ent_coef_losses = [], [], [], []
        for _ in range(self.outer_steps):
            ent_coef = self._ent_coef()
            inner_support = {"observations": support["observations"], "actions": support["actions"],
                             "targets": self._support_targets(support, ent_coef)}
            critic_loss, actor_loss, log_prob = self._meta_losses(inner_support, self._query_batch(task_ids), ent_coef)

            for optimizer in optimizers:
                optimizer.zero_grad()
            (critic_loss + actor_loss).backward()
            torch.nn.utils.clip_grad_norm_(self.actor.parameters(), self.max_grad_norm)
            torch.nn.utils.clip_grad_norm_(self.critic.parameters(), self.max_grad_norm)
            for optimizer in optimizers:
                optimizer.step()

            if self.ent_coef_optimizer is not None:
                ent_coef_loss = -(self.log_ent_coef * (log_prob.mean() + self.target_entropy)).mean()
                self.ent_coef_optimizer.zero_grad()
                ent_coef_loss.backward()
                self.ent_coef_optimizer.step()
                ent_coef_losses.append(ent_coef_loss.item())

            self._n_updates += 1
            if self._n_updates % self.target_update_interval == 0:
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)
            critic_losses.append(critic_loss.item())
            actor_losses.append(actor_loss.item())
            ent_coefs.append(ent_coef.item())

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/meta_critic_loss", float(np.mean(critic_losses)))
        self.logger.record("train/meta_actor_loss", float(np.mean(actor_losses)))
        self.logger.record("train/ent_coef", float(np.mean(ent_coefs)))
        if ent_coef_losses:
            self.logger.record("train/ent_coef_loss", float(np.mean(ent_coef_losses)))
        actor_lr, critic_lr = self.inner_lrs
        self.logger.record("train/inner_actor_lr", actor_lr)
        self.logger.record("train/inner_critic_lr", critic_lr)

    def _dump_meta_logs(self) -> None:
        for prefix, episodes in (("pre", self.pre_adaptation_episodes), ("post", self.post_adaptation_episodes)):
            if episodes:
                for key, name in (("return", "return"), ("success", "success_rate"), ("collision", "collision_rate")):
                    self.logger.record(f"meta/{prefix}_adaptation_{name}", float(np.mean([e[key] for e in episodes])))
        self.dump_logs()

    def learn(
        self: SelfMAMLSAC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int | None = 4,
        tb_log_name: str = "MAMLSAC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfMAMLSAC:
        """Warm-up (plain multi-task SAC for ``warmup_steps``), then meta-iterations until ``total_timesteps`` env
        steps.

        SB3's off-policy loop (``OffPolicyAlgorithm.learn``) in which, after the warm-up, a meta-iteration takes the
        place of ``collect_rollouts`` and ``sac_gradient_steps`` that of ``gradient_steps``.

        :param total_timesteps: env steps in total (support, query and warm-up interaction all count).
        :param callback: SB3 callback(s), called after every env step.
        :param log_interval: dump the logs every this many meta-iterations (warm-up: episodes, as in SAC); ``None``
            never dumps them (what the zoo passes for ``--log-interval -2``).
        :param tb_log_name: TensorBoard run name.
        :param reset_num_timesteps: start the step counter (and the TensorBoard run) anew.
        :param progress_bar: show a progress bar (needs tqdm and rich).
        :return: the trained model.
        """
        total_timesteps, callback = self._setup_learn(
            total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
        )
        callback.on_training_start(locals(), globals())
        while self.num_timesteps < total_timesteps:
            warm_up = self.num_timesteps < self.warmup_steps
            if warm_up:
                rollout = self.collect_rollouts(
                    self.env, callback, self.train_freq, self.replay_buffer, self.action_noise, self.learning_starts,
                    log_interval,
                )
                gradient_steps = self.gradient_steps if self.num_timesteps > self.learning_starts else 0
            else:
                rollout = self._meta_iteration(callback)
                gradient_steps = self.sac_gradient_steps
            if not rollout.continue_training:
                break
            gradient_steps = rollout.episode_timesteps if gradient_steps < 0 else gradient_steps
            if gradient_steps > 0:
                self.train(batch_size=self.batch_size, gradient_steps=gradient_steps)
            if not warm_up and log_interval is not None and self.meta_iterations % log_interval == 0:
                self._dump_meta_logs()
        self.env.env_method("set_task", None)
        callback.on_training_end()
        return self

    # --- fast adaptation ---
    def adapt(
        self,
        env: gym.Env,
        task: Any = None,
        n_support: int | None = None,
        k: int | None = None,
        seed: int | None = None,
    ) -> AdaptedSACPolicy:
        """Collect ``n_support`` stochastic transitions on ``env`` (task ``task``) and take ``k`` inner rounds.

        Follows :class:`vafn_sb3.common.adaptation.Adaptable`: the model's parameters, target critic, entropy
        coefficient, inner step sizes and training mode are restored in a ``finally`` block (optimisers and buffers are
        never touched), so they are bit-identical afterwards, also when adaptation raises.

        :param env: a single (non-vectorised) env of the same spaces, exposing ``unwrapped.set_task``.
        :param task: the instruction (anything ``Instruction.coerce`` accepts), or a list of them sharing the support
            budget; ``None`` keeps the env's task.
        :param n_support: support transitions (default: the meta-training ``n_support``).
        :param k: inner rounds (default: the meta-training ``inner_steps``); 0 returns the meta-policy as a dict copy.
        :param seed: seed of the support rollouts and of the inner rounds' action samples (as fine-tuning seeds its
            noise), so the same seed adapts to the same parameters; the caller's torch stream is left untouched.
        :return: the adapted policy (its support set as ``support``).
        """
        n_support = self.n_support if n_support is None else int(n_support)
        k = self.inner_steps if k is None else int(k)
        if k < 0:
            raise ValueError(f"k must be >= 0, got {k}")
        if isinstance(env, VecEnv):
            raise TypeError("adapt() takes a single gymnasium env, not a VecEnv")
        if env.observation_space.shape != self.observation_space.shape:
            raise ValueError(
                f"env observation shape {env.observation_space.shape} != model's {self.observation_space.shape}"
            )
        snapshot = {name: t.detach().clone() for name, t in self.policy.state_dict().items()}
        variables = {name: getattr(self, name).detach().clone() for name in self._get_torch_save_params()[1]}
        training = self.policy.training
        try:
            if task is not None and not is_task_list(task):
                task = Instruction.coerce(task)
            support = collect_support(self, env, task, n_support, seed)
            with seeded_torch_stream(seed):
                actor_params, critic_params = self.adapted_parameters([support], k)[0]
            return AdaptedSACPolicy(self.policy, self.actor_distribution, actor_params, critic_params, support)
        finally:
            with torch.no_grad():
                self.policy.load_state_dict(snapshot)
                for name, value in variables.items():
                    getattr(self, name).copy_(value)
            self.policy.set_training_mode(training)
