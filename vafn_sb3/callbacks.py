"""Training callbacks: success / collision rates during evaluation and rollouts, and meta-evaluation after adaptation.

* :class:`SuccessCollisionEvalCallback` is SB3's ``EvalCallback`` that also logs ``eval/collision_rate`` and stores
  ``collisions`` in ``evaluations.npz`` (success comes from ``info["is_success"]`` as in SB3).
* :class:`RolloutCollisionCallback` logs ``rollout/collision_rate`` over the last training episodes.
* :class:`MetaEvalCallback` measures post-adaptation return / success / collision on held-out instructions through
  :func:`vafn_sb3.common.adaptation.evaluate_adaptation`, for MAML-SAC and the baselines alike.
"""

from __future__ import annotations

import csv
import os
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, EvalCallback

from vafn_sb3.common.adaptation import evaluate_adaptation

#: Episodes averaged by the rollout collision rate (SB3's own rollout buffers hold 100 episodes).
ROLLOUT_WINDOW = 100


def _episode_collided(info: dict[str, Any]) -> bool | None:
    value = info.get("collided")
    return None if value is None else bool(value)


class SuccessCollisionEvalCallback(EvalCallback):
    """``EvalCallback`` that also reports the fraction of evaluation episodes with any arm-arm contact."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._collision_buffer: list[bool] = []
        self.evaluations_collisions: list[list[bool]] = []

    def _log_success_callback(self, locals_: dict[str, Any], globals_: dict[str, Any]) -> None:
        """Collect success (SB3) and collision at each finished evaluation episode."""
        super()._log_success_callback(locals_, globals_)
        if not locals_["done"]:
            return
        collided = _episode_collided(locals_["info"])
        if collided is not None:
            self._collision_buffer.append(collided)
            # Recorded on every episode so the value dumped right after evaluate_policy is the full-evaluation mean.
            self.logger.record("eval/collision_rate", float(np.mean(self._collision_buffer)))

    def _on_step(self) -> bool:
        evaluating = self.eval_freq > 0 and self.n_calls % self.eval_freq == 0
        if evaluating:
            self._collision_buffer = []
        continue_training = super()._on_step()
        if evaluating and self._collision_buffer:
            self.evaluations_collisions.append(list(self._collision_buffer))
            if self.verbose >= 1:
                print(f"Collision rate: {100 * np.mean(self._collision_buffer):.2f}%")
            if self.log_path is not None:
                self._save_with_collisions()
        return continue_training

    def _save_with_collisions(self) -> None:
        assert self.log_path is not None
        extra: dict[str, Any] = {"collisions": self.evaluations_collisions}
        if self.evaluations_successes:
            extra["successes"] = self.evaluations_successes
        np.savez(
            self.log_path,
            timesteps=self.evaluations_timesteps,
            results=self.evaluations_results,
            ep_lengths=self.evaluations_length,
            **extra,
        )


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

    Logs ``meta/return_k{K}``, ``meta/success_k{K}`` and ``meta/collision_k{K}`` and appends rows to
    ``<log_path>/meta_evaluations.csv``. Works for any model with ``adapt(env, task, n_support, k, seed)``.

    :param eval_freq: callback calls (env steps / n_envs) between meta-evaluations.
    :param k_values: adaptation-step counts to evaluate (0 = unadapted).
    :param n_tasks: held-out instructions per meta-evaluation (a fixed set, the same every time).
    :param n_support: support transitions collected before adapting.
    :param min_length: shortest held-out instruction.
    :param max_length: longest held-out instruction.
    :param n_eval_episodes: evaluation episodes per task and K.
    :param env_id: env to evaluate on (default: the training env's ID).
    :param env_kwargs: extra kwargs for the evaluation envs.
    :param seed: seed of the held-out set and of adaptation.
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
        from vafn_gym.benchmarks import InstructionBenchmark

        self.env_id = self.env_id or _training_env_id(self)
        benchmark = InstructionBenchmark(
            self.env_id,
            self.min_length,
            self.max_length,
            n_test=self.n_tasks,
            seed=self.seed,
            env_kwargs=self.env_kwargs,
        )
        self.tasks = benchmark.test_tasks
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
