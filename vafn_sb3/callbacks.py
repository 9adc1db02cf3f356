"""Training callbacks: success / collision rates during evaluation and rollouts, and meta-evaluation after adaptation.

Training-time evaluations score the *validation* suite (:func:`vafn_gym.benchmarks.suite_tasks`), never the held-out
test suite, through the one protocol of :mod:`vafn_gym.benchmarks` (its runner, seed function and collision key).

* :class:`SuccessCollisionEvalCallback` is SB3's ``EvalCallback`` (same arguments, logs, best model and
  ``evaluations.npz``) whose episodes run through :func:`vafn_gym.benchmarks.evaluate_tasks`; it also logs
  ``eval/collision_rate`` and stores ``collisions`` in ``evaluations.npz``.
* :class:`RolloutCollisionCallback` logs ``rollout/collision_rate`` over the last training episodes.
* :class:`MetaEvalCallback` measures post-adaptation return / success / collision on validation instructions through
  :func:`vafn_sb3.common.adaptation.evaluate_adaptation`, for MAML-SAC and the baselines alike.
"""

from __future__ import annotations

import csv
import os
from collections import deque
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
from stable_baselines3.common.vec_env import sync_envs_normalization, unwrap_vec_normalize

from vafn_gym.benchmarks import COLLISION_KEY, episode_collided, evaluate_tasks, run_episode, episode_seed, suite_tasks
from vafn_sb3.common.adaptation import evaluate_adaptation

#: Episodes averaged by the rollout collision rate (SB3's own rollout buffers hold 100 episodes).
ROLLOUT_WINDOW = 100


def _episode_collided(info: dict[str, Any]) -> bool | None:
    return episode_collided(info) if COLLISION_KEY in info else None


class SuccessCollisionEvalCallback(EvalCallback):
    """``EvalCallback`` whose episodes are the one protocol's, and which also reports the collision rate.

    On a VAFN env evaluation ``j`` runs the first ``n_eval_episodes`` instructions of the env's validation suite (task
    ``i`` resets with ``episode_seed(seed, i)``, every evaluation the same), on a single env made from the evaluation
    env's spec; on any other env, ``n_eval_episodes`` episodes seeded the same way. With ``VecNormalize`` the
    observations are normalised by the evaluation env's statistics (synchronised with the training env's first).

    :param seed: seed of the episode resets (and hidden targets) of every evaluation.
    """

    def __init__(self, *args: Any, seed: int = 0, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.seed = seed
        self.evaluations_collisions: list[list[bool]] = []
        self._env: gym.Env | None = None
        self._tasks: list[Any] | None = None

    def _single_env(self) -> gym.Env:
        """One (non-vectorised) env like the evaluation env's, made once from its spec."""
        if self._env is None:
            spec = self.eval_env.get_attr("spec")[0]
            if spec is None:
                raise ValueError("SuccessCollisionEvalCallback needs an evaluation env made from a registered ID")
            # the env itself, without the wrappers (e.g. Monitor) that the evaluation env's spec lists
            self._env = gym.make(spec.id, max_episode_steps=spec.max_episode_steps, **spec.kwargs)
            if callable(getattr(self._env.unwrapped, "set_task", None)):
                self._tasks = suite_tasks(self._env, "validation", self.seed, n=self.n_eval_episodes)
        return self._env

    def _episodes(self) -> list[dict[str, Any]]:
        """This evaluation's :func:`~vafn_gym.benchmarks.run_episode` rows."""
        env = self._single_env()
        transform = None
        if self.model.get_vec_normalize_env() is not None:
            sync_envs_normalization(self.training_env, self.eval_env)
            normalizer = unwrap_vec_normalize(self.eval_env)
            transform = None if normalizer is None else normalizer.normalize_obs
        if self._tasks is not None:
            return evaluate_tasks(self.model, env, self._tasks, self.seed, self.deterministic, transform)
        return [run_episode(self.model, env, episode_seed(self.seed, index), self.deterministic, transform)
                for index in range(self.n_eval_episodes)]

    def _on_step(self) -> bool:
        if not (self.eval_freq > 0 and self.n_calls % self.eval_freq == 0):
            return True
        rows = self._episodes()
        rewards, lengths = [row["return"] for row in rows], [row["steps"] for row in rows]
        vafn = self._tasks is not None
        successes, collisions = [bool(row["success"]) for row in rows], [bool(row["collision"]) for row in rows]
        if self.log_path is not None:
            self.evaluations_timesteps.append(self.num_timesteps)
            self.evaluations_results.append(rewards)
            self.evaluations_length.append(lengths)
            extra: dict[str, Any] = {}
            if vafn:
                self.evaluations_successes.append(successes)
                self.evaluations_collisions.append(collisions)
                extra = {"successes": self.evaluations_successes, "collisions": self.evaluations_collisions}
            np.savez(self.log_path, timesteps=self.evaluations_timesteps, results=self.evaluations_results,
                     ep_lengths=self.evaluations_length, **extra)
        mean_reward = float(np.mean(rewards))
        self.last_mean_reward = mean_reward
        if self.verbose >= 1:
            print(f"Eval num_timesteps={self.num_timesteps}, "
                  f"episode_reward={mean_reward:.2f} +/- {np.std(rewards):.2f}")
            print(f"Episode length: {np.mean(lengths):.2f} +/- {np.std(lengths):.2f}")
        self.logger.record("eval/mean_reward", mean_reward)
        self.logger.record("eval/mean_ep_length", float(np.mean(lengths)))
        if vafn:
            self.logger.record("eval/success_rate", float(np.mean(successes)))
            self.logger.record("eval/collision_rate", float(np.mean(collisions)))
            if self.verbose >= 1:
                print(f"Success rate: {100 * np.mean(successes):.2f}%")
                print(f"Collision rate: {100 * np.mean(collisions):.2f}%")
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        self.logger.dump(self.num_timesteps)
        continue_training = True
        if mean_reward > self.best_mean_reward:
            if self.verbose >= 1:
                print("New best mean reward!")
            if self.best_model_save_path is not None:
                self.model.save(os.path.join(self.best_model_save_path, "best_model"))
            self.best_mean_reward = mean_reward
            if self.callback_on_new_best is not None:
                continue_training = self.callback_on_new_best.on_step()
        if self.callback is not None:
            continue_training = continue_training and self._on_event()
        return continue_training

    def _on_training_end(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None


class RolloutCollisionCallback(BaseCallback):
    """Logs ``rollout/collision_rate``: the fraction of the last training episodes in which two arms touched."""

    def __init__(self, window: int = ROLLOUT_WINDOW, verbose: int = 0) -> None:
        super().__init__(verbose)
        self.episodes: deque[bool] = deque(maxlen=window)

    def _on_step(self) -> bool:
        for done, info in zip(self.locals.get("dones", ()), self.locals.get("infos", ())):
            collided = _episode_collided(info) if done else None
            if collided is not None:
                self.episodes.append(collided)
                self.logger.record("rollout/collision_rate", float(np.mean(self.episodes)))
        return True


def _training_env_id(callback: BaseCallback) -> str:
    specs = callback.training_env.get_attr("spec")
    if not specs or specs[0] is None:
        raise ValueError("MetaEvalCallback needs env_id: the training env has no registered spec")
    return specs[0].id


class MetaEvalCallback(BaseCallback):
    """Every ``eval_freq`` calls, adapt to held-out instructions and log post-adaptation performance per K.

    The instructions are the first ``n_tasks`` of the env's validation suite in the length range (never the held-out
    test suite). Logs ``meta/return_k{K}``, ``meta/success_k{K}`` and ``meta/collision_k{K}`` and appends rows to
    ``<log_path>/meta_evaluations.csv``. Works for any model with ``adapt(env, task, n_support, k, seed)``.

    :param eval_freq: callback calls (env steps / n_envs) between meta-evaluations.
    :param k_values: adaptation-step counts to evaluate (0 = unadapted).
    :param n_tasks: validation instructions per meta-evaluation (a fixed set, the same every time).
    :param n_support: support transitions collected before adapting.
    :param min_length: shortest validation instruction.
    :param max_length: longest validation instruction.
    :param n_eval_episodes: evaluation episodes per task and K.
    :param env_id: env to evaluate on (default: the training env's ID).
    :param env_kwargs: extra kwargs for the evaluation envs.
    :param seed: seed of the hidden targets, the episode resets and adaptation.
    :param log_path: folder of ``meta_evaluations.csv`` (default: the logger's folder, if any).
    """

    def __init__(
        self,
        eval_freq: int = 10_000,
        k_values: Sequence[int] = (0, 1, 5),
        n_tasks: int = 3,
        n_support: int = 200,
        min_length: int = 1,
        max_length: int = 3,
        n_eval_episodes: int = 1,
        env_id: str | None = None,
        env_kwargs: dict[str, Any] | None = None,
        seed: int = 0,
        log_path: str | None = None,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        if eval_freq < 1 or n_tasks < 1 or n_support < 1 or n_eval_episodes < 1:
            raise ValueError("eval_freq, n_tasks, n_support and n_eval_episodes must all be >= 1")
        if not k_values or min(k_values) < 0:
            raise ValueError(f"k_values must be non-empty and >= 0, got {k_values}")
        self.eval_freq = eval_freq
        self.k_values = sorted(int(k) for k in k_values)
        self.n_tasks = n_tasks
        self.n_support = n_support
        self.min_length = min_length
        self.max_length = max_length
        self.n_eval_episodes = n_eval_episodes
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs or {})
        self.seed = seed
        self.log_path = log_path
        self.tasks: list[Any] = []
        self.rows: list[dict[str, Any]] = []

    def _init_callback(self) -> None:
        self.env_id = self.env_id or _training_env_id(self)
        env = gym.make(self.env_id, **self.env_kwargs)
        try:
            self.tasks = suite_tasks(env, "validation", self.seed, self.min_length, self.max_length, self.n_tasks)
        finally:
            env.close()
        if self.log_path is None and self.logger is not None and self.logger.dir:
            self.log_path = self.logger.dir

    def _on_step(self) -> bool:
        if self.n_calls % self.eval_freq == 0:
            self.evaluate()
        return True

    def evaluate(self) -> list[dict[str, Any]]:
        """Run one meta-evaluation now; returns the per-K summary rows."""
        assert self.env_id is not None
        results = evaluate_adaptation(
            self.model, self.env_id, self.tasks, n_support=self.n_support, k_values=self.k_values,
            n_eval_episodes=self.n_eval_episodes, seed=self.seed, env_kwargs=self.env_kwargs or None,
        )
        summary = summarise_adaptation(results, self.k_values)
        for row in summary:
            k = row["k"]
            self.logger.record(f"meta/return_k{k}", row["return"])
            self.logger.record(f"meta/success_k{k}", row["success"])
            self.logger.record(f"meta/collision_k{k}", row["collision"])
            row["timesteps"] = self.num_timesteps
            if self.verbose >= 1:
                print(f"meta-eval K={k}: return {row['return']:.2f}, success {row['success']:.2f}, "
                      f"collision {row['collision']:.2f}")
        # Dumped now (like EvalCallback) so the values are written at this timestep.
        self.logger.dump(self.num_timesteps)
        self.rows.extend(summary)
        if self.log_path:
            self._append_csv(summary)
        return summary

    def _append_csv(self, rows: list[dict[str, Any]]) -> None:
        assert self.log_path is not None
        os.makedirs(self.log_path, exist_ok=True)
        path = os.path.join(self.log_path, "meta_evaluations.csv")
        new_file = not os.path.exists(path)
        with open(path, "a", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=["timesteps", "k", "return", "success", "collision"])
            if new_file:
                writer.writeheader()
            writer.writerows(rows)


def summarise_adaptation(results: list[dict[str, Any]], k_values: Sequence[int]) -> list[dict[str, Any]]:
    """Mean return / success / collision per K over the per-task rows ``evaluate_adaptation`` returns."""
    summary = []
    for k in k_values:
        rows = [r for r in results if int(r["k"]) == int(k)]
        if not rows:
            raise ValueError(f"evaluate_adaptation returned no rows for k={k}")
        summary.append({
            "k": int(k),
            "return": float(np.mean([r["return_mean"] for r in rows])),
            "success": float(np.mean([r["success_rate"] for r in rows])),
            "collision": float(np.mean([r["collision_rate"] for r in rows])),
        })
    return summary
