"""The task distribution: a seeded sampler over instructions with a deterministic train / validation / test split."""

from __future__ import annotations

import hashlib
from typing import Literal

import gymnasium as gym
import numpy as np

from vafn_gym.constants import (
    MAX_INSTRUCTION_LENGTH,
    NUM_ARMS,
    SHARED_RADIUS,
    SHARED_Z_RANGE,
    default_target,
)
from vafn_gym.instructions import Instruction

SPLITS = ("train", "validation", "test")
#: Task families: which parts of an instruction vary between tasks (see the README, "Task families").
TASK_FAMILIES = ("order", "hidden_targets", "goal_visible")
DEFAULT_TASK_FAMILY = "order"
Split = Literal["train", "validation", "test"]


def sample_shared_target(rng: np.random.Generator) -> np.ndarray:
    """A target drawn uniformly from the shared region (a vertical cylinder around the table centre)."""
    radius = SHARED_RADIUS * np.sqrt(rng.uniform())
    angle = rng.uniform(0.0, 2.0 * np.pi)
    height = rng.uniform(*SHARED_Z_RANGE)
    return np.array([radius * np.cos(angle), radius * np.sin(angle), height])


def env_task_family(env_id: str, env_kwargs: dict | None = None) -> str:
    """The task family a registered env ID uses, with ``env_kwargs`` overriding its registered kwargs."""
    kwargs = {**gym.spec(env_id).kwargs, **(env_kwargs or {})}
    return kwargs.get("task_family", DEFAULT_TASK_FAMILY)


class TaskSampler:
    """Seeded distribution over instructions; each arm *order* belongs to exactly one split.

    The split of an order is a pure function of (order, ``split_seed``, ``fractions``), so train, validation and test
    orders are disjoint by construction, and a train sampler can never produce a test order.

    :param split: which split to sample from.
    :param family: "order" (default per-arm targets), "hidden_targets" or "goal_visible" (targets sampled per task).
    :param min_length: shortest instruction (waypoints).
    :param max_length: longest instruction (at most ``MAX_INSTRUCTION_LENGTH``).
    :param seed: seed of the sampling stream.
    :param split_seed: seed of the split assignment (keep it fixed across a study).
    :param fractions: train / validation / test shares of the order space.
    :param no_adjacent_repeats: forbid the same arm twice in a row (the paper's orders never repeat adjacently).
    """

    def __init__(
        self,
        split: Split = "train",
        family: str = DEFAULT_TASK_FAMILY,
        min_length: int = 1,
        max_length: int = MAX_INSTRUCTION_LENGTH,
        seed: int | None = None,
        split_seed: int = 0,
        fractions: tuple[float, float, float] = (0.7, 0.1, 0.2),
        no_adjacent_repeats: bool = True,
    ) -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if family not in TASK_FAMILIES:
            raise ValueError(f"family must be one of {TASK_FAMILIES}, got {family!r}")
        if not 0 <= min_length <= max_length <= MAX_INSTRUCTION_LENGTH:
            raise ValueError(f"need 0 <= min_length <= max_length <= {MAX_INSTRUCTION_LENGTH}, got {min_length}, {max_length}")
        if len(fractions) != 3 or min(fractions) < 0 or not np.isclose(sum(fractions), 1.0):
            raise ValueError(f"fractions must be three non-negative shares summing to 1, got {fractions}")
        self.split = split
        self.family = family
        self.min_length = min_length
        self.max_length = max_length
        self.split_seed = split_seed
        self.fractions = tuple(float(f) for f in fractions)
        self.no_adjacent_repeats = no_adjacent_repeats
        self.rng = np.random.default_rng(seed)
        self._orders = [o for o in self._enumerate_orders() if self.split_of(o) == split]
        self._orders_by_length: dict[int, list[tuple[int, ...]]] = {}
        for order in self._orders:  # enumeration order is kept inside each length
            self._orders_by_length.setdefault(len(order), []).append(order)
        self._lengths = sorted(self._orders_by_length)
        if not self._orders:
            raise ValueError(f"no {split!r} orders of length {min_length}..{max_length}; widen the range or fractions")

    def seed(self, seed: int | None) -> None:
        """Re-seed the sampling stream."""
        self.rng = np.random.default_rng(seed)

    def _enumerate_orders(self) -> list[tuple[int, ...]]:
        orders: list[tuple[int, ...]] = [()] if self.min_length == 0 else []
        frontier: list[tuple[int, ...]] = [()]
        for length in range(1, self.max_length + 1):
            frontier = [
                prefix + (arm,)
                for prefix in frontier
                for arm in range(1, NUM_ARMS + 1)
                if not (self.no_adjacent_repeats and prefix and prefix[-1] == arm)
            ]
            if length >= self.min_length:
                orders.extend(frontier)
        return orders

    def split_of(self, order: tuple[int, ...] | Instruction) -> str:
        """The split an arm order belongs to (a hash of the order, so independent of the sampler's length range)."""
        arms = order.arms if isinstance(order, Instruction) else tuple(order)
        digest = hashlib.sha256(f"{self.split_seed}:{','.join(map(str, arms))}".encode()).digest()
        u = int.from_bytes(digest[:8], "big") / 2.0**64
        train, validation, _ = self.fractions
        return "train" if u < train else "validation" if u < train + validation else "test"

    @property
    def orders(self) -> list[tuple[int, ...]]:
        """Every arm order in this sampler's split and length range."""
        return list(self._orders)

    def sample(self, rng: np.random.Generator | None = None) -> Instruction:
        """One instruction: a uniform length, then a uniform order of that length from this split, then targets.

        :param rng: draw from this generator instead of the sampler's own stream.
        """
        rng = self.rng if rng is None else rng
        length = self._lengths[rng.integers(len(self._lengths))]
        candidates = self._orders_by_length[length]
        order = candidates[rng.integers(len(candidates))]
        if self.family == "order":
            targets = [default_target(arm) for arm in order]
        else:
            targets = [sample_shared_target(rng) for _ in order]
        instruction = Instruction.from_arms(order, targets)
        assert self.split_of(instruction) == self.split, "sampler produced an order outside its split"
        return instruction

    def sample_tasks(self, n: int) -> list[Instruction]:
        """``n`` independent instructions (a meta-batch)."""
        return [self.sample() for _ in range(n)]

    def fixed_set(self, n: int, seed: int = 0) -> list[Instruction]:
        """A deterministic set of ``n`` instructions (e.g. the held-out evaluation set), independent of the stream."""
        saved, self.rng = self.rng, np.random.default_rng(seed)
        try:
            return self.sample_tasks(n)
        finally:
            self.rng = saved
