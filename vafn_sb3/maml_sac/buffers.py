"""Where a MAML-SAC task rollout stores its transitions: SB3's replay buffers, plus a record for the support set."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.buffers import ReplayBuffer

from vafn_sb3.common.adaptation import SupportSet


class TaskRolloutBuffer:
    """The ``replay_buffer`` argument of SB3's ``collect_rollouts`` for one task's support or query rollout.

    ``add`` (SB3's ``ReplayBuffer.add``, called by ``_store_transition`` with the unnormalised observations and rewards
    and the scaled action) forwards every transition to ``buffers`` and keeps it, env by env, with what a
    :class:`~vafn_sb3.common.adaptation.SupportSet` needs beyond a replay buffer (successes, collisions, episode ends);
    completed episodes are summarised in :attr:`episodes`.

    :param buffers: the main replay buffer and, for a query rollout, the task's query buffer.
    :param unscale_action: the policy's ``unscale_action`` (support sets hold the actions the env received).
    :param n_envs: number of envs stepped together.
    """

    def __init__(
        self, buffers: Sequence[ReplayBuffer], unscale_action: Callable[[np.ndarray], np.ndarray], n_envs: int
    ) -> None:
        self.buffers = buffers
        self.unscale_action = unscale_action
        self.columns: dict[str, list[np.ndarray]] = {name: [] for name in SupportSet.__dataclass_fields__}
        self.episodes: list[dict[str, float]] = []
        self._returns = np.zeros(n_envs)
        self._collided = np.zeros(n_envs, dtype=bool)

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """Store one step of every env (``next_obs`` holds the true final observation where an episode ended)."""
        for buffer in self.buffers:
            buffer.add(obs, next_obs, action, reward, done, infos)
        done = np.asarray(done, dtype=bool)
        truncated = np.array([info.get("TimeLimit.truncated", False) for info in infos], dtype=bool)
        success = np.array([info.get("is_success", False) for info in infos], dtype=bool)
        collision = np.array([info.get("collision", False) for info in infos], dtype=bool)
        step = {
            "observations": obs, "actions": self.unscale_action(action), "rewards": reward,
            "next_observations": next_obs, "terminated": done & ~truncated, "episode_ends": done,
            "successes": success, "collisions": collision,
        }
        for name, value in step.items():
            self.columns[name].append(np.array(value, dtype=np.float32))
        self._returns += reward
        self._collided |= collision
        for i in np.flatnonzero(done):
            self.episodes.append(
                {"return": float(self._returns[i]), "success": float(success[i]), "collision": float(self._collided[i])}
            )
            self._returns[i], self._collided[i] = 0.0, False

    def support_set(self) -> SupportSet:
        """The kept transitions, env by env (episodes contiguous); the budget cuts each env's last episode."""
        arrays = {name: np.swapaxes(np.stack(values), 0, 1) for name, values in self.columns.items()}
        arrays["episode_ends"][:, -1] = 1.0
        return SupportSet(**{name: a.reshape(-1, *a.shape[2:]) for name, a in arrays.items()})
