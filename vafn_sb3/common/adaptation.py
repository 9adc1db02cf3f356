"""The fast-adaptation protocol every vafn algorithm implements, and one evaluation routine for all of them.

A model is :class:`Adaptable` when ``model.adapt(env, task, n_support, k, seed)`` collects ``n_support`` transitions
with its stochastic policy on ``env`` (after ``env.unwrapped.set_task(task)``), runs ``k`` gradient steps of its own
adaptation rule and returns an :class:`AdaptedPolicy`, without changing the model itself (parameters, optimisers,
replay buffers, target networks are restored in a ``finally`` block even when adaptation raises).

:func:`evaluate_adaptation` measures any such model on the same held-out tasks with the same support budget and the
same ``k``, so MAML-SAC and the baselines are compared like for like. An adapted policy that keeps its support set as
``policy.support`` (MAML-SAC's and the fine-tuning baselines' do) also gets the share of the task's arms that support
set shows executing (:func:`support_coverage`): an adaptation step can only use what its support set contains.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
import torch

from vafn_gym.benchmarks import EPISODES_PER_TASK, episode_seed, run_episode
from vafn_gym.constants import PHASE_EXECUTING, PHASE_INDEX
from vafn_gym.instructions import Instruction

__all__ = [
    "Adaptable",
    "AdaptedPolicy",
    "SUPPORT_MODES",
    "SupportSet",
    "collect_support",
    "evaluate_adaptation",
    "is_task_list",
    "per_arm_tasks",
    "run_episode",
    "seeded_torch_stream",
    "support_coverage",
]

#: What a support set holds: "episodes" of the task itself (from its first waypoint on), or "per-arm", one
#: single-waypoint instruction per arm of the task (:func:`per_arm_tasks`), the budget split between them.
SUPPORT_MODES = ("episodes", "per-arm")


@runtime_checkable
class AdaptedPolicy(Protocol):
    """What :meth:`Adaptable.adapt` returns: anything with SB3's ``predict`` signature (and, optionally, the
    :class:`SupportSet` it adapted on as ``support``)."""

    def predict(
        self,
        observation: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, Any]:
        """Action(s) for ``observation`` (a single observation or a batch), and the recurrent state (``None``)."""
        ...


@runtime_checkable
class Adaptable(Protocol):
    """A model that can adapt to one task from a small support set without changing itself."""

    def adapt(
        self,
        env: gym.Env,
        task: Instruction | None = None,
        n_support: int = ...,
        k: int = ...,
        seed: int | None = None,
    ) -> AdaptedPolicy:
        """Collect ``n_support`` stochastic transitions on ``env`` (task ``task``, or a list of tasks sharing the budget
        as :func:`collect_support` does; ``None`` keeps the env's), take ``k`` adaptation steps and return the adapted
        policy; the model's own state is left bit-identical."""
        ...


@dataclass(frozen=True)
class SupportSet:
    """Transitions collected by a stochastic policy on one task (arrays with a leading time axis of length ``n``).

    :param observations: ``(n, obs_dim)`` observations.
    :param actions: ``(n, act_dim)`` actions actually sent to the env (in the action space's bounds).
    :param rewards: ``(n,)`` rewards.
    :param next_observations: ``(n, obs_dim)`` observations after each step (the true final one at episode ends).
    :param terminated: ``(n,)`` 1.0 where the episode terminated (no bootstrap), else 0.0.
    :param episode_ends: ``(n,)`` 1.0 where an episode ended (terminated, truncated, or cut by the support budget).
    :param successes: ``(n,)`` the env's ``info["is_success"]`` after each step.
    :param collisions: ``(n,)`` the env's ``info["collision"]`` after each step (this step's contact).
    """

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_observations: np.ndarray
    terminated: np.ndarray
    episode_ends: np.ndarray
    successes: np.ndarray
    collisions: np.ndarray

    def __len__(self) -> int:
        """Number of transitions."""
        return len(self.rewards)

    def nstep_plan(self, gamma: float, n_step: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Decompose n-step targets ``y_t = sum_j gamma^j r_{t+j} + c_t * V(s'_{e_t})`` into data-only parts.

        A sum runs within the episode of ``t`` for at most ``n_step`` rewards (``None``: to the episode end, Monte
        Carlo) and stops at transition ``e_t``; it bootstraps from ``V(s'_{e_t})`` unless ``e_t`` terminated.

        :param gamma: discount factor.
        :param n_step: number of reward terms (1 = one-step TD); ``None`` sums to the episode end.
        :return: ``(reward_sums, stop_index, bootstrap_discount)``, each of shape ``(n,)``; ``bootstrap_discount`` is
            ``gamma^m`` after ``m`` summed rewards, or 0 where the sum ends in a termination.
        """
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if n_step is not None and n_step < 1:
            raise ValueError(f"n_step must be >= 1 or None, got {n_step}")
        n = len(self)
        horizon = n if n_step is None else n_step
        reward_sums = np.zeros(n, dtype=np.float32)
        stop_index = np.zeros(n, dtype=np.int64)
        bootstrap_discount = np.zeros(n, dtype=np.float32)
        for t in range(n):
            total, discount, j = 0.0, 1.0, t
            while True:
                total += discount * float(self.rewards[j])
                discount *= gamma
                if self.episode_ends[j] or j - t + 1 >= horizon:
                    break
                j += 1
            reward_sums[t], stop_index[t] = total, j
            bootstrap_discount[t] = 0.0 if self.terminated[j] else discount
        return reward_sums, stop_index, bootstrap_discount

    def discounted_returns(
        self, gamma: float, n_step: int | None = None, bootstrap: np.ndarray | None = None
    ) -> np.ndarray:
        """Per-step n-step targets (see :meth:`nstep_plan`); without ``bootstrap`` the value tail counts as 0.

        :param gamma: discount factor.
        :param n_step: number of reward terms; ``None`` sums to the episode end (Monte Carlo).
        :param bootstrap: optional ``(n,)`` value estimates ``V(s'_t)`` used where a sum stops before a termination.
        :return: ``(n,)`` float32 targets.
        """
        reward_sums, stop_index, bootstrap_discount = self.nstep_plan(gamma, n_step)
        if bootstrap is None:
            return reward_sums
        return (
            reward_sums + bootstrap_discount * np.asarray(bootstrap, dtype=np.float32)[stop_index]
        ).astype(np.float32)


@contextmanager
def seeded_torch_stream(seed: int | None) -> Iterator[None]:
    """Inside the block torch's (CPU) random stream starts from ``seed`` (``None``: carries on unseeded); the caller's
    stream is restored afterwards, so adapting with a seed is reproducible and leaves the caller's draws alone."""
    with torch.random.fork_rng(devices=[]):
        if seed is not None:
            torch.manual_seed(seed)
        yield


def collect_support(
    model: Any, env: gym.Env, task: Instruction | Sequence[Instruction] | None, n_support: int, seed: int | None
) -> SupportSet:
    """Roll out ``model``'s stochastic policy (``predict(obs, deterministic=False)``) for ``n_support`` steps on one
    task, or on several (the budget split evenly between them, the first ones taking the remainder).

    The env is reset (with ``seed``) after ``env.unwrapped.set_task(task)``, and again after every episode end. Torch's
    global random stream is forked, so the policy noise is reproducible from ``seed`` and the caller's stream is left
    untouched.

    :param model: anything with SB3's ``predict``.
    :param env: a single (non-vectorised) Gymnasium env exposing ``unwrapped.set_task``.
    :param task: the instruction to adapt to, or a list of instructions (e.g. :func:`per_arm_tasks`); ``None`` keeps
        the env's current task.
    :param n_support: number of transitions to collect (>= 1, and at least one per task).
    :param seed: seed of the env resets and the policy noise (``None``: unseeded).
    :return: the collected transitions (the tasks' in order).
    """
    tasks = list(task) if is_task_list(task) else [task]
    if n_support < max(1, len(tasks)):
        raise ValueError(f"n_support must be >= 1 and at least one per task ({len(tasks)}), got {n_support}")
    shares = [n_support // len(tasks) + (index < n_support % len(tasks)) for index in range(len(tasks))]
    columns: dict[str, list] = {name: [] for name in SupportSet.__dataclass_fields__}
    with seeded_torch_stream(seed):
        for index, (one_task, share) in enumerate(zip(tasks, shares)):
            if one_task is not None:
                env.unwrapped.set_task(one_task)
            obs, _ = env.reset(seed=None if seed is None else seed + index)
            for _ in range(share):
                action, _ = model.predict(obs, deterministic=False)
                next_obs, reward, terminated, truncated, info = env.step(action)
                columns["observations"].append(obs)
                columns["actions"].append(action)
                columns["rewards"].append(reward)
                columns["next_observations"].append(next_obs)
                columns["terminated"].append(float(terminated))
                columns["episode_ends"].append(float(terminated or truncated))
                columns["successes"].append(float(info.get("is_success", False)))
                columns["collisions"].append(float(info.get("collision", False)))
                obs = env.reset()[0] if terminated or truncated else next_obs
            columns["episode_ends"][-1] = 1.0  # the task's share of the budget cuts its last episode
    return SupportSet(**{name: np.asarray(values, dtype=np.float32) for name, values in columns.items()})


def is_task_list(task: Any) -> bool:
    """Whether ``task`` is several support tasks (a list or tuple of :class:`Instruction`), not one instruction."""
    return isinstance(task, (list, tuple)) and bool(task) and all(isinstance(one, Instruction) for one in task)


def per_arm_tasks(task: Instruction) -> list[Instruction]:
    """One single-waypoint instruction per arm of ``task`` (order of first appearance, the arm's own target).

    The support sets of :func:`evaluate_adaptation`'s ``support="per-arm"``: every arm's hidden target is in its
    support set, whether or not the unadapted policy would ever complete the waypoints before it.
    """
    task = Instruction.coerce(task)
    firsts = {waypoint.arm: waypoint for waypoint in reversed(task)}
    return [Instruction([firsts[arm]]) for arm in dict.fromkeys(task.arms)]


def support_coverage(support: SupportSet, task: Instruction, n_arms: int) -> float:
    """The share of ``task``'s arms that ``support`` shows executing a waypoint (phase 1) at least once.

    On hidden targets an arm's readings say where its target is only while it executes, and a policy that does not
    reach the first waypoint never lets the second arm start: its support set then shows the first arm alone.

    :param support: the support set (observations of ``n_arms`` equal blocks, each starting with the newest reading).
    :param task: the instruction the support set was collected on.
    :param n_arms: arms of the env (blocks per observation).
    """
    arms = set(Instruction.coerce(task).arms)
    if not arms:
        return float("nan")
    observations = np.concatenate([support.observations, support.next_observations])
    blocks = observations.reshape(len(observations), n_arms, -1)
    executing = np.round(blocks[:, :, PHASE_INDEX]) == PHASE_EXECUTING
    seen = {arm + 1 for arm in np.flatnonzero(executing.any(axis=0))}
    return len(arms & seen) / len(arms)


def evaluate_adaptation(
    model: Any,
    env_id: str,
    tasks: list[Instruction],
    n_support: int,
    k_values: Sequence[int],
    n_eval_episodes: int = 3,
    seed: int = 0,
    env_kwargs: dict | None = None,
    support: str = "episodes",
    keep_episodes: bool = False,
    at_episode_end: Callable[[gym.Env], dict] | None = None,
) -> list[dict]:
    """Adaptation curve of ``model``: deterministic evaluation after ``k`` adaptation steps, per task and ``k``.

    For each task and each ``k`` the model adapts from a support set of ``n_support`` transitions collected with the
    same seed (so every ``k`` of a task sees the same support data), then runs ``n_eval_episodes`` deterministic
    episodes. ``k = 0`` evaluates the unadapted model itself (no support is collected). The same protocol applies to
    every :class:`Adaptable`, so curves of different algorithms are comparable.

    :param model: an :class:`Adaptable` (also needs ``predict``).
    :param env_id: registered env ID (e.g. ``"VAFN/ThreeArmReachHidden-v1"``); one env is made and reused.
    :param tasks: held-out instructions (e.g. ``InstructionBenchmark(env_id).test_tasks``; ``validation_tasks`` while
        training).
    :param n_support: support transitions per adaptation.
    :param k_values: numbers of adaptation steps to evaluate (each >= 0).
    :param n_eval_episodes: deterministic evaluation episodes per (task, k).
    :param seed: base seed; task ``i`` uses support seed ``seed + i`` and evaluation seeds
        ``vafn_gym.benchmarks.episode_seed(seed, i, episode)``.
    :param env_kwargs: extra keyword arguments of ``gym.make``.
    :param support: one of :data:`SUPPORT_MODES`: what the support set of each task holds.
    :param keep_episodes: also return each row's evaluation episodes (:func:`run_episode` rows: outcome, failing arm,
        steps after the last waypoint) under ``episodes``.
    :param at_episode_end: with ``keep_episodes``: called with the env as each evaluation episode ends (before the next
        reset); its dict is added to that episode's row (e.g. where an arm came to rest).
    :return: one row per (task, k): ``task_index``, ``task`` (code), ``k``, ``n_support``, ``return_mean``,
        ``success_rate``, ``collision_rate``, ``adapt_time_s`` (wall time of ``adapt``, support collection included),
        ``support_arms`` (:func:`support_coverage` of the adapted policy's ``support``; NaN where there is none).
    """
    if not tasks:
        raise ValueError("tasks is empty")
    if not 1 <= n_eval_episodes <= EPISODES_PER_TASK:
        raise ValueError(f"n_eval_episodes must be in [1, {EPISODES_PER_TASK}], got {n_eval_episodes}")
    if any(int(k) < 0 for k in k_values):
        raise ValueError(f"k_values must be >= 0, got {list(k_values)}")
    if support not in SUPPORT_MODES:
        raise ValueError(f"support must be one of {SUPPORT_MODES}, got {support!r}")
    if any(int(k) > 0 for k in k_values) and not isinstance(model, Adaptable):
        raise TypeError(f"{type(model).__name__} has no adapt(); only k = 0 can be evaluated")
    env = gym.make(env_id, **(env_kwargs or {}))
    rows = []
    try:
        for task_index, task in enumerate(tasks):
            task = Instruction.coerce(task)
            for k in k_values:
                start = time.perf_counter()
                if int(k) == 0:
                    policy = model
                else:
                    support_task = per_arm_tasks(task) if support == "per-arm" else task
                    policy = model.adapt(env, task=support_task, n_support=n_support, k=int(k), seed=seed + task_index)
                adapt_time = time.perf_counter() - start
                support_set = getattr(policy, "support", None) if int(k) > 0 else None
                coverage = (support_coverage(support_set, task, len(env.unwrapped.arms))
                            if isinstance(support_set, SupportSet) else float("nan"))
                env.unwrapped.set_task(task)
                episodes = []
                for episode in range(n_eval_episodes):
                    episodes.append(run_episode(policy, env, seed=episode_seed(seed, task_index, episode)))
                    if at_episode_end is not None:
                        episodes[-1].update(at_episode_end(env))
                rows.append(
                    {
                        "task_index": task_index,
                        "task": task.to_code(),
                        "k": int(k),
                        "n_support": n_support,
                        "return_mean": float(np.mean([e["return"] for e in episodes])),
                        "success_rate": float(np.mean([e["success"] for e in episodes])),
                        "collision_rate": float(np.mean([e["collision"] for e in episodes])),
                        "adapt_time_s": adapt_time,
                        "support_arms": coverage,
                        **({"episodes": episodes} if keep_episodes else {}),
                    }
                )
    finally:
        env.close()
    return rows
