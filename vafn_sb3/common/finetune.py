"""Adaptation by fine-tuning: the ``adapt`` of every non-meta baseline (MTSAC, MADDPG, MAAC, MAPPO).

``adapt`` collects the support set with :func:`vafn_sb3.common.adaptation.collect_support` (the same routine, budget and
seeds as MAML-SAC), then runs ``k`` gradient steps of the algorithm's *own* ``train()`` on exactly that support data
(full batch: every step sees all ``n_support`` transitions), with the algorithm's own optimisers, learning rates and
target-network updates. It returns a deep copy of the fine-tuned policy and restores every parameter, optimiser state,
target network, entropy coefficient, buffer and counter of the model in a ``finally`` block. This is the "multi-task
pre-training + fine-tuning with the same support data and the same number of steps" baseline of Mandi et al., "On the
Effectiveness of Fine-tuning Versus Meta-reinforcement Learning" (NeurIPS 2022).
"""

from __future__ import annotations

import copy
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.logger import Logger, configure
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.save_util import recursive_getattr, recursive_setattr
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.utils import ConstantSchedule
from stable_baselines3.common.vec_env import VecNormalize

from vafn_gym.instructions import Instruction
from vafn_sb3.common.adaptation import SupportSet, collect_support, seeded_torch_stream

#: Support budget and number of adaptation steps used when ``adapt`` is called without them (MAML-SAC's defaults are
#: set by its own class; ``evaluate_adaptation`` always passes both explicitly).
DEFAULT_N_SUPPORT = 200
DEFAULT_K = 5


class FullBatchReplayBuffer(ReplayBuffer):
    """A replay buffer holding one support set whose ``sample`` returns every stored transition (full-batch steps)."""

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> ReplayBufferSamples:
        """All stored transitions, in order (``batch_size`` is ignored)."""
        return self._get_samples(np.arange(self.size()), env=env)


def support_replay_buffer(model: Any, support: SupportSet) -> FullBatchReplayBuffer:
    """Store a support set in a :class:`FullBatchReplayBuffer` shaped like ``model``'s replay buffer.

    Actions are stored rescaled to [-1, 1] exactly as SB3's ``_store_transition`` does, and ``done`` is the env's
    ``terminated`` flag, so truncated episodes keep their bootstrap (SB3's timeout handling).

    :param model: an SB3 off-policy algorithm.
    :param support: transitions from :func:`collect_support`.
    """
    buffer = FullBatchReplayBuffer(
        len(support), model.observation_space, model.action_space, device=model.device, n_envs=1
    )
    actions = model.policy.scale_action(support.actions)
    for t in range(len(support)):
        buffer.add(
            support.observations[t : t + 1],
            support.next_observations[t : t + 1],
            actions[t : t + 1],
            support.rewards[t : t + 1],
            support.terminated[t : t + 1],
            [{}],
        )
    return buffer


class GaussianExplorationPolicy:
    """A deterministic policy plus clipped Gaussian exploration noise, with its own seeded noise stream.

    SB3 adds a DDPG/TD3 agent's exploration noise inside ``collect_rollouts``, not in ``predict``; this wrapper gives
    the support rollouts the same behaviour policy.

    :param model: an SB3 model with a deterministic ``predict`` and a [-1, 1]-scaled Box action space.
    :param std: noise standard deviation in the scaled action space.
    :param seed: seed of the noise stream.
    """

    def __init__(self, model: Any, std: float, seed: int | None) -> None:
        self.model = model
        self.std = std
        self.rng = np.random.default_rng(seed)

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """The model's action, plus noise unless ``deterministic`` (clipped to the action space)."""
        action, _ = self.model.predict(observation, deterministic=True)
        if deterministic:
            return action, None
        scaled = self.model.policy.scale_action(action) + self.rng.normal(0.0, self.std, size=np.shape(action))
        return self.model.policy.unscale_action(np.clip(scaled, -1.0, 1.0)), None


class FineTuneAdaptation:
    """Mixin giving an SB3 algorithm the :class:`~vafn_sb3.common.adaptation.Adaptable` ``adapt`` by fine-tuning.

    Subclasses with a different data path (on-policy) override :meth:`_fine_tune`; the collection, the seeding and the
    snapshot/restore of the model are shared.
    """

    #: Plain attributes that ``_fine_tune`` may replace temporarily; restored after adaptation.
    _adaptation_attributes: tuple[str, ...] = ("_n_updates", "replay_buffer", "lr_schedule")
    #: ``None``: fine-tune with the algorithm's own optimisers (Adam) at its learning rate. A float: plain SGD with this
    #: step size for every optimiser instead, the "SGD at the inner learning rate" variant (set it on the model, e.g. to
    #: MAML-SAC's inner step size).
    finetune_sgd_lr: float | None = None

    def adapt(
        self,
        env: gym.Env,
        task: Instruction | None = None,
        n_support: int = DEFAULT_N_SUPPORT,
        k: int = DEFAULT_K,
        seed: int | None = None,
    ) -> BasePolicy:
        """Fine-tune a copy of the policy on ``n_support`` fresh transitions of ``task`` with ``k`` own gradient steps.

        :param env: a single (non-vectorised) env exposing ``unwrapped.set_task``.
        :param task: the instruction to adapt to, or a list of them sharing the support budget (``None`` keeps the
            env's task).
        :param n_support: support transitions, collected with the stochastic policy.
        :param k: number of gradient steps of the algorithm's own update on the support set (0 returns a copy).
        :param seed: seed of the support rollouts and of the fine-tuning noise.
        :return: the adapted policy (an SB3 policy in evaluation mode, its support set as ``support``); the model
            itself is unchanged.
        """
        if k < 0:
            raise ValueError(f"k must be >= 0, got {k}")
        support = collect_support(self._support_policy(seed), env, task, n_support, seed)
        saved = self._snapshot()
        try:
            with seeded_torch_stream(seed):
                self._logger = configure(folder=None, format_strings=[])
                if self.finetune_sgd_lr is not None:
                    self._use_sgd(self.finetune_sgd_lr)
                if k > 0:
                    self._fine_tune(support, k)
            adapted = _copy_policy(self.policy)
        finally:
            self._restore(saved)
        adapted.set_training_mode(False)
        adapted.support = support
        return adapted

    def _support_policy(self, seed: int | None) -> Any:
        """The behaviour policy of the support rollouts.

        The model itself (its ``predict(deterministic=False)`` samples).

        :param seed: seed of any extra exploration noise (used by deterministic-policy subclasses).
        """
        return self

    def _fine_tune(self, support: SupportSet, k: int) -> None:
        """Run ``k`` steps of the off-policy ``train()`` on the full support set.

        :param support: the support transitions.
        :param k: number of gradient steps.
        """
        self.replay_buffer = support_replay_buffer(self, support)
        self.train(gradient_steps=k, batch_size=len(support))

    def _use_sgd(self, lr: float) -> None:
        """Replace every optimiser by plain SGD over the same parameters, at a constant step size ``lr``."""
        if lr <= 0:
            raise ValueError(f"finetune_sgd_lr must be > 0, got {lr}")
        for name in self._optimizer_names():
            optimizer = recursive_getattr(self, name)
            parameters = [p for group in optimizer.param_groups for p in group["params"]]
            recursive_setattr(self, name, th.optim.SGD(parameters, lr=lr))
        self.lr_schedule = ConstantSchedule(lr)  # train() re-applies lr_schedule to every optimiser

    def _optimizer_names(self) -> list[str]:
        """Dotted names of the optimisers SB3 saves (e.g. ``actor.optimizer``, ``ent_coef_optimizer``)."""
        return [name for name in self._get_torch_save_params()[0] if name.split(".")[-1].endswith("optimizer")]

    def _snapshot(self) -> dict[str, Any]:
        """Deep copies of every torch state SB3 would save, the logger, the training mode and the swappable
        attributes."""
        state_dicts, variables = self._get_torch_save_params()
        return {
            "state_dicts": {name: copy.deepcopy(recursive_getattr(self, name).state_dict()) for name in state_dicts},
            "variables": {name: recursive_getattr(self, name).detach().clone() for name in variables},
            "attributes": {name: getattr(self, name) for name in self._adaptation_attributes if hasattr(self, name)},
            "optimizers": {name: recursive_getattr(self, name) for name in self._optimizer_names()},
            "logger": getattr(self, "_logger", None),
            "training": self.policy.training,
        }

    def _restore(self, saved: dict[str, Any]) -> None:
        """Put back everything :meth:`_snapshot` recorded (the optimiser objects first, then their states)."""
        for name, optimizer in saved["optimizers"].items():
            recursive_setattr(self, name, optimizer)
        for name, state in saved["state_dicts"].items():
            recursive_getattr(self, name).load_state_dict(state)
        for name, value in saved["variables"].items():
            recursive_getattr(self, name).data.copy_(value)
        for name, value in saved["attributes"].items():
            setattr(self, name, value)
        logger: Logger | None = saved["logger"]
        if logger is None:
            del self._logger
        else:
            self._logger = logger
        self.policy.set_training_mode(saved["training"])


def _copy_policy(policy: BasePolicy) -> BasePolicy:
    """An independent copy of an SB3 policy, rebuilt like ``BasePolicy.load`` does (constructor parameters + state).

    ``copy.deepcopy`` is not usable: SB3 distributions keep non-leaf tensors of the last forward pass.
    """
    copied = type(policy)(**policy._get_constructor_parameters()).to(policy.device)
    copied.load_state_dict(policy.state_dict())
    return copied
