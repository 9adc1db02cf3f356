"""The one evaluation protocol: the held-out suite, one seed function, one collision key, one episode runner.

Every number that scores a policy (training callbacks, the adaptation and learning benchmarks, the zoo's enjoy, the
scripted ceiling) takes its tasks from :func:`suite_tasks` (through :class:`InstructionBenchmark`), seeds its episodes
with :func:`episode_seed`, reads contacts through :data:`COLLISION_KEY` and runs its episodes with :func:`run_episode`,
so two numbers from two scripts are comparable. Held-out numbers use the *test* suite (:data:`HELDOUT_ORDERS`,
versioned); anything that chooses while training (evaluation callbacks, intermediate learning curves) the *validation*
suite.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from vafn_gym.constants import MAX_INSTRUCTION_LENGTH
from vafn_gym.heldout import HELDOUT_ORDERS, HELDOUT_SIZE, HELDOUT_VERSION  # noqa: F401  (re-exported)
from vafn_gym.instructions import Instruction
from vafn_gym.task import resolve_targets
from vafn_gym.tasks import TaskSampler

#: Seed of the held-out hidden targets and episode resets unless a study says otherwise.
DEFAULT_TEST_SEED = 1234
#: Offset of every evaluation episode's reset seed (see :func:`episode_seed`).
EVAL_SEED = 10_000
#: Evaluation episodes of one task with distinct reset seeds.
EPISODES_PER_TASK = 100
#: Size of the validation suite (distinct validation-split orders, stratified like the test suite).
VALIDATION_SIZE = 100
#: Seed that picks the suites' orders within a length (part of the suite's definition: see :mod:`vafn_gym.heldout`).
SUITE_SEED = 0
#: The ``info`` key that says an episode has had an arm-arm contact so far (the env's ``"collision"`` is this step's).
COLLISION_KEY = "collided"


def episode_seed(seed: int, task_index: int, episode: int = 0) -> int:
    """Reset seed of evaluation episode ``episode`` of task ``task_index`` in a study seeded ``seed`` (the only one)."""
    if not 0 <= episode < EPISODES_PER_TASK:
        raise ValueError(f"episode must be in [0, {EPISODES_PER_TASK}), got {episode}")
    return EVAL_SEED + seed + task_index * EPISODES_PER_TASK + episode


def episode_collided(info: dict[str, Any]) -> bool:
    """Whether the episode behind this step's ``info`` has had an arm-arm contact (False where the env does not say)."""
    return bool(info.get(COLLISION_KEY, False))


def heldout_orders(sampler: TaskSampler) -> list[tuple[int, ...]]:
    """The held-out test suite of ``sampler``'s layout: :data:`HELDOUT_ORDERS` for three arms and the default split,
    else the same generator (``stratified_orders(HELDOUT_SIZE, SUITE_SEED)``, or all test orders where fewer)."""
    if sampler.split != "test":
        raise ValueError(f"the held-out suite comes from the test split, not {sampler.split!r}")
    settings = ("n_arms", "split_seed", "fractions", "no_adjacent_repeats", "min_length", "max_length")
    default = TaskSampler("test")
    if all(getattr(sampler, name) == getattr(default, name) for name in settings):
        return [Instruction.coerce(code).arms for code in HELDOUT_ORDERS]
    return _stratified(sampler, HELDOUT_SIZE)


def _stratified(sampler: TaskSampler, n: int) -> list[tuple[int, ...]]:
    try:
        return sampler.stratified_orders(n, seed=SUITE_SEED)
    except ValueError:  # a small order space (e.g. two arms): all of its orders
        return sampler.stratified_orders(len(sampler.orders), seed=SUITE_SEED)


def suite_tasks(
    env: gym.Env,
    split: str = "test",
    seed: int = DEFAULT_TEST_SEED,
    min_length: int = 1,
    max_length: int = MAX_INSTRUCTION_LENGTH,
    n: int | None = None,
) -> list[Instruction]:
    """The first ``n`` instructions of ``env``'s test (held-out) or validation suite within the length range.

    The suite's distinct orders come first; a larger ``n`` repeats them. Where the env hides targets, each instruction
    gets targets drawn from ``(seed, split, index)``.

    :param env: an env of the benchmark (its layout, target mode and ``split_seed`` define the suite).
    :param split: "test" (:func:`heldout_orders`) or "validation" (:data:`VALIDATION_SIZE` stratified orders).
    :param seed: seed of the hidden targets.
    :param min_length: shortest instruction.
    :param max_length: longest instruction.
    :param n: number of instructions (``None``: the suite's distinct orders in the range, once each).
    """
    if split not in ("test", "validation"):
        raise ValueError(f"split must be 'test' or 'validation', got {split!r}")
    base = env.unwrapped
    sampler = TaskSampler(split, "default", split_seed=base.sampler.split_seed, layout=base.layout)
    orders = heldout_orders(sampler) if split == "test" else _stratified(sampler, VALIDATION_SIZE)
    orders = [order for order in orders if min_length <= len(order) <= max_length]
    if not orders:
        raise ValueError(f"the {split} suite has no instruction of lengths {min_length}..{max_length}")
    n = len(orders) if n is None else n
    tasks = []
    for index in range(n):
        task = Instruction.from_arms(orders[index % len(orders)], n_arms=base.layout.n_arms)
        if base.targets != "default":
            rng = np.random.default_rng([seed, ("test", "validation").index(split), index])
            task = resolve_targets(task, base.targets, base.layout, rng)
        tasks.append(task)
    return tasks


def evaluate_tasks(
    policy: Any,
    env: gym.Env,
    tasks: list[Instruction],
    seed: int,
    deterministic: bool = True,
    transform: Callable[[np.ndarray], np.ndarray] | None = None,
) -> list[dict[str, Any]]:
    """Run ``policy`` once on each of ``tasks`` (task ``i`` resets with ``episode_seed(seed, i)``); a row per task."""
    rows = []
    for index, task in enumerate(tasks):
        env.unwrapped.set_task(task)
        row = run_episode(policy, env, episode_seed(seed, index), deterministic=deterministic, transform=transform)
        rows.append({"task_index": index, "task": task.to_code(), "length": len(task), **row})
    return rows


class InstructionBenchmark:
    """Train, validation and held-out test instructions of one registered env (Meta-World's ``Benchmark``).

    :param env_id: registered env ID, e.g. ``"VAFN/ThreeArmReach-v1"``.
    :param min_length: shortest test (and validation) instruction.
    :param max_length: longest test (and validation) instruction.
    :param n_test: number of held-out test instructions (``None``: every suite instruction in the length range; more
        than the suite holds repeats it).
    :param seed: seed of the hidden targets and of the episode resets (the same seed gives the same tasks and episodes
        in every script); the test orders are the versioned suite whatever the seed.
    :param env_kwargs: keyword arguments of ``gym.make`` (e.g. ``n_arms``, ``robot``).
    :param n_train: number of training instructions in :attr:`train_tasks`.
    :param train_max_length: longest training instruction (defaults to ``max_length``).
    """

    def __init__(
        self,
        env_id: str,
        min_length: int = 1,
        max_length: int = MAX_INSTRUCTION_LENGTH,
        n_test: int | None = None,
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
            #: Held-out instructions: the test suite (:func:`suite_tasks`), with their (hidden) targets.
            self.test_tasks: list[Instruction] = suite_tasks(env, "test", seed, min_length, max_length, n_test)
            #: Validation instructions (what training-time evaluations score): the validation suite.
            self.validation_tasks: list[Instruction] = suite_tasks(env, "validation", seed, min_length, max_length)
            base = env.unwrapped
            train = TaskSampler("train", base.targets, min_length, train_max_length or max_length,
                                split_seed=base.sampler.split_seed, layout=base.layout)
        finally:
            env.close()
        #: Training instructions (e.g. MAML's task pool): orders of the train split only.
        self.train_tasks: list[Instruction] = train.fixed_set(n_train, seed=seed + 1)

    def make_env(self, **overrides: Any) -> gym.Env:
        """A fresh env of this benchmark (its ``env_kwargs``, updated by ``overrides``)."""
        return gym.make(self.env_id, **{**self.env_kwargs, **overrides})

    def episode_seed(self, task_index: int, episode: int = 0) -> int:
        """Reset seed of evaluation episode ``episode`` of task ``task_index`` (:func:`episode_seed`)."""
        return episode_seed(self.seed, task_index, episode)

    def evaluate(
        self, policy: Any, n_tasks: int | None = None, deterministic: bool = True, split: str = "test"
    ) -> list[dict[str, Any]]:
        """Run ``policy`` once on each of the first ``n_tasks`` test (or validation) tasks; a row per task (see
        :func:`run_episode`)."""
        tasks = self.test_tasks if split == "test" else self.validation_tasks if split == "validation" else None
        if tasks is None:
            raise ValueError(f"split must be 'test' or 'validation', got {split!r}")
        env = self.make_env()
        try:
            return evaluate_tasks(policy, env, tasks[:n_tasks], self.seed, deterministic)
        finally:
            env.close()


def run_episode(
    policy: Any,
    env: gym.Env,
    seed: int | None,
    deterministic: bool = True,
    transform: Callable[[np.ndarray], np.ndarray] | None = None,
    max_steps: int | None = None,
) -> dict[str, Any]:
    """One episode of ``policy`` (anything with SB3's ``predict``) on ``env``'s current task: the one episode runner.

    A policy with a ``reset()`` method (e.g. :class:`ScriptedController`) is reset first; a policy whose ``predict``
    takes ``state`` and ``episode_start`` (every SB3 model, e.g. RecurrentPPO) gets its recurrent state threaded
    through the episode. ``transform`` maps each observation before the policy sees it (e.g. a ``VecNormalize``'s
    ``normalize_obs``); ``max_steps`` stops the episode early (its ``outcome`` is then ``"unfinished"``).

    :return: ``return``, ``success`` (1.0/0.0), ``collision`` (any arm-arm contact, :data:`COLLISION_KEY`),
        ``steps``, ``waypoints_reached``, ``return_terms`` (the return split by reward term, from
        ``info["reward_terms"]`` where the env reports it) and where the episode went wrong: ``outcome``
        (``"success"``, ``"collision"``, ``"timeout"`` or ``"unfinished"``), ``failed_arm`` (the active arm at the
        first contact or at the end; ``None`` after a success) and ``steps_after_waypoint`` (env steps from the last
        reached waypoint, or the start, to the first contact or the end).
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
        seen = obs if transform is None else transform(obs)
        if recurrent:
            action, state = policy.predict(seen, state=state, episode_start=episode_start, deterministic=deterministic)
            episode_start = np.zeros(1, dtype=bool)
        else:
            action, _ = policy.predict(seen, deterministic=deterministic)
        obs, reward, terminated, truncated, info = env.step(action)
        total += float(reward)
        steps += 1
        index = int(info.get("waypoint_index", 0))
        if index != waypoint:
            waypoint, waypoint_step = index, steps
        if contact is None and episode_collided(info):
            contact = (info.get("active_arm"), steps - waypoint_step)
        for name, value in info.get("reward_terms", {}).items():
            terms[name] = terms.get(name, 0.0) + float(value)
        unfinished = max_steps is not None and steps >= max_steps
        if terminated or truncated or unfinished:
            success = bool(info.get("is_success", False))
            if unfinished and not (terminated or truncated):
                outcome, failed_arm, after = "unfinished", info.get("active_arm"), steps - waypoint_step
            elif contact is not None:
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
