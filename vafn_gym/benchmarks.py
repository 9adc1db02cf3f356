"""The one held-out evaluation protocol: a benchmark's train/test instructions, its env, and one episode runner.

Every curve in the project (training callbacks, the adaptation and learning benchmarks, the zoo's enjoy/reproduce, the
scripted ceiling) takes its held-out tasks from :class:`InstructionBenchmark` and scores them with :func:`run_episode`,
so two numbers from two scripts are comparable.
"""

from __future__ import annotations

import inspect
from typing import Any

import gymnasium as gym
import numpy as np

from vafn_gym.constants import MAX_INSTRUCTION_LENGTH
from vafn_gym.instructions import Instruction
from vafn_gym.tasks import TaskSampler

#: Seed of the held-out test set unless a study says otherwise.
DEFAULT_TEST_SEED = 1234
#: Seed offset of the evaluation episodes' resets (task i, episode j resets with EVAL_SEED + i * 100 + j).
EVAL_SEED = 10_000


class InstructionBenchmark:
    """Train and held-out test instructions of one registered env (Meta-World's ``Benchmark``, for instructions).

    :param env_id: registered env ID, e.g. ``"VAFN/ThreeArmReach-v1"``.
    :param min_length: shortest test instruction.
    :param max_length: longest test instruction.
    :param n_test: number of held-out test instructions.
    :param seed: seed of the test set (the same seed gives the same tasks, in every script).
    :param env_kwargs: keyword arguments of ``gym.make`` (e.g. ``n_arms``, ``robot``).
    :param n_train: number of training instructions in :attr:`train_tasks`.
    :param train_max_length: longest training instruction (defaults to ``max_length``).
    """

    def __init__(
        self,
        env_id: str,
        min_length: int = 1,
        max_length: int = MAX_INSTRUCTION_LENGTH,
        n_test: int = 100,
        seed: int = DEFAULT_TEST_SEED,
        env_kwargs: dict[str, Any] | None = None,
        n_train: int = 40,
        train_max_length: int | None = None,
    ) -> None:
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs or {})
        self.min_length, self.max_length = min_length, max_length
        self.seed = seed
        env = self.make_env()
        try:
            base = env.unwrapped
            targets, layout, split_seed = base.targets, base.layout, base.sampler.split_seed
        finally:
            env.close()
        test = TaskSampler("test", targets, min_length, max_length, split_seed=split_seed, layout=layout)
        train = TaskSampler(
            "train", targets, min_length, train_max_length or max_length, split_seed=split_seed, layout=layout
        )
        #: Held-out instructions: orders of the test split only, with their (hidden) targets drawn once.
        self.test_tasks: list[Instruction] = test.fixed_set(n_test, seed=seed)
        #: Training instructions (e.g. MAML's task pool): orders of the train split only.
        self.train_tasks: list[Instruction] = train.fixed_set(n_train, seed=seed + 1)

    def make_env(self, **overrides: Any) -> gym.Env:
        """A fresh env of this benchmark (its ``env_kwargs``, updated by ``overrides``)."""
        return gym.make(self.env_id, **{**self.env_kwargs, **overrides})

    def episode_seed(self, task_index: int, episode: int = 0) -> int:
        """Reset seed of evaluation episode ``episode`` of test task ``task_index``."""
        return EVAL_SEED + self.seed + task_index * 100 + episode

    def evaluate(self, policy: Any, n_tasks: int | None = None, deterministic: bool = True) -> list[dict[str, Any]]:
        """Run ``policy`` once on each of the first ``n_tasks`` test tasks; a row per task (see :func:`run_episode`)."""
        env = self.make_env()
        rows = []
        try:
            for index, task in enumerate(self.test_tasks[:n_tasks]):
                env.unwrapped.set_task(task)
                row = run_episode(policy, env, self.episode_seed(index), deterministic=deterministic)
                rows.append({"task_index": index, "task": task.to_code(), "length": len(task), **row})
        finally:
            env.close()
        return rows


def run_episode(policy: Any, env: gym.Env, seed: int | None, deterministic: bool = True) -> dict[str, Any]:
    """One episode of ``policy`` (anything with SB3's ``predict``) on ``env``'s current task.

    A policy with a ``reset()`` method (e.g. :class:`ScriptedController`) is reset first; a policy whose ``predict``
    takes ``state`` and ``episode_start`` (every SB3 model, e.g. RecurrentPPO) gets its recurrent state threaded
    through the episode.

    :return: ``return``, ``success`` (1.0/0.0), ``collision`` (any arm-arm contact), ``steps``, ``waypoints_reached``,
        ``return_terms`` (the return split by reward term, from ``info["reward_terms"]`` where the env reports it) and
        where the episode went wrong: ``outcome`` (``"success"``, ``"collision"`` or ``"timeout"``), ``failed_arm``
        (the active arm at the first contact or at the end; ``None`` after a success) and ``steps_after_waypoint``
        (env steps from the last reached waypoint, or the start, to the first contact or the end).
    """
    reset = getattr(policy, "reset", None)
    if callable(reset):
        reset()
    # a recurrent SB3 policy (e.g. sb3-contrib's RecurrentPPO) carries its hidden state from step to step
    recurrent = "episode_start" in inspect.signature(policy.predict).parameters
    state, episode_start = None, np.ones(1, dtype=bool)
    obs, _ = env.reset(seed=seed)
    total, steps, terms = 0.0, 0, {}
    waypoint, waypoint_step = 0, 0
    contact = None  # (active arm, steps after the last waypoint) at the first arm-arm contact
    while True:
        if recurrent:
            action, state = policy.predict(obs, state=state, episode_start=episode_start, deterministic=deterministic)
            episode_start = np.zeros(1, dtype=bool)
        else:
            action, _ = policy.predict(obs, deterministic=deterministic)
        obs, reward, terminated, truncated, info = env.step(action)
        total += float(reward)
        steps += 1
        index = int(info.get("waypoint_index", 0))
        if index != waypoint:
            waypoint, waypoint_step = index, steps
        if contact is None and info.get("collision", False):
            contact = (info.get("active_arm"), steps - waypoint_step)
        for name, value in info.get("reward_terms", {}).items():
            terms[name] = terms.get(name, 0.0) + float(value)
        if terminated or truncated:
            success = bool(info.get("is_success", False))
            if contact is not None:
                outcome, (failed_arm, after) = "collision", contact
            elif success:
                outcome, failed_arm, after = "success", None, 0
            else:
                outcome, failed_arm, after = "timeout", info.get("active_arm"), steps - waypoint_step
            return {
                "return": total,
                "success": float(success),
                "collision": float(contact is not None),
                "steps": steps,
                "waypoints_reached": waypoint,
                "return_terms": terms,
                "outcome": outcome,
                "failed_arm": failed_arm,
                "steps_after_waypoint": after,
            }


def episode_rates(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Mean success, collision, episode steps, reached-waypoint fraction, return and return per reward term of rows.

    :param rows: :meth:`InstructionBenchmark.evaluate` rows; the per-term means (``return_<term>``) cover the terms
        every row reports.
    """
    if not rows:
        raise ValueError("no evaluation rows")
    rates = {
        "success": float(np.mean([r["success"] for r in rows])),
        "collision": float(np.mean([r["collision"] for r in rows])),
        "episode_steps": float(np.mean([r["steps"] for r in rows])),
        "waypoint_fraction": float(np.mean([r["waypoints_reached"] / max(r["length"], 1) for r in rows])),
    }
    if all("return" in r for r in rows):
        rates["return"] = float(np.mean([r["return"] for r in rows]))
        terms = [r.get("return_terms", {}) for r in rows]
        for name in terms[0]:
            if all(name in t for t in terms):
                rates[f"return_{name}"] = float(np.mean([t[name] for t in terms]))
    return rates


#: Confidence level of every interval the benchmarks report.
CONFIDENCE: float = 0.95


def confidence_half_width(values: np.ndarray, confidence: float = CONFIDENCE) -> np.ndarray:
    """Student-t half width of the mean over axis 0 of ``values`` (zeros with fewer than two rows, e.g. one seed)."""
    from scipy import stats

    values = np.asarray(values, float)
    n = values.shape[0]
    if n < 2:
        return np.zeros(values.shape[1:])
    return stats.t.ppf(0.5 + confidence / 2, n - 1) * values.std(axis=0, ddof=1) / np.sqrt(n)
