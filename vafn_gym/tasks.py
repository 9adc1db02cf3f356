"""The task distribution: a seeded sampler over instructions with a deterministic train / validation / test split."""

from __future__ import annotations

import hashlib
from typing import Literal

import numpy as np

from vafn_gym.constants import MAX_INSTRUCTION_LENGTH
from vafn_gym.instructions import Instruction
from vafn_gym.layout import ArmLayout
from vafn_gym.task import TARGET_MODES, resolve_targets

SPLITS = ("train", "validation", "test")
Split = Literal["train", "validation", "test"]
#: Lengths with at most this many orders are enumerated (exact uniform draws); longer ones are drawn by rejection.
ENUMERATION_LIMIT = 20_000


class TaskSampler:
    """Seeded distribution over instructions; each arm *order* belongs to exactly one split.

    The split of an order is a pure function of (order, ``split_seed``, ``fractions``), so train, validation and test
    orders are disjoint by construction, and a train sampler can never produce a test order.

    :param split: which split to sample from.
    :param targets: "default" (waypoints name arms only; the env uses each arm's default target), "per_arm" (one
        target per arm drawn from the shared region, reused on every visit) or "per_waypoint" (one per waypoint).
    :param min_length: shortest instruction (waypoints).
    :param max_length: longest instruction (at most ``MAX_INSTRUCTION_LENGTH``).
    :param seed: seed of the sampling stream.
    :param split_seed: seed of the split assignment (keep it fixed across a study).
    :param fractions: train / validation / test shares of the order space.
    :param no_adjacent_repeats: forbid the same arm twice in a row (the paper's orders never repeat adjacently).
    :param layout: the arm layout (arm count and shared region); three arms by default.
    """

    def __init__(
        self,
        split: Split = "train",
        targets: str = "default",
        min_length: int = 1,
        max_length: int = MAX_INSTRUCTION_LENGTH,
        seed: int | None = None,
        split_seed: int = 0,
        fractions: tuple[float, float, float] = (0.7, 0.1, 0.2),
        no_adjacent_repeats: bool = True,
        layout: ArmLayout | None = None,
    ) -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if targets not in TARGET_MODES:
            raise ValueError(f"targets must be one of {TARGET_MODES}, got {targets!r}")
        if not 0 <= min_length <= max_length <= MAX_INSTRUCTION_LENGTH:
            raise ValueError(
                f"need 0 <= min_length <= max_length <= {MAX_INSTRUCTION_LENGTH}, got {min_length}, {max_length}"
            )
        if len(fractions) != 3 or min(fractions) < 0 or not np.isclose(sum(fractions), 1.0):
            raise ValueError(f"fractions must be three non-negative shares summing to 1, got {fractions}")
        self.split = split
        self.targets = targets
        self.min_length = min_length
        self.max_length = max_length
        self.split_seed = split_seed
        self.fractions = tuple(float(f) for f in fractions)
        self.no_adjacent_repeats = no_adjacent_repeats
        self.layout = layout or ArmLayout()
        self.n_arms = self.layout.n_arms
        self.rng = np.random.default_rng(seed)
        self._tables: dict[int, dict[tuple[int, ...], str]] = {}
        # Exact per-length lists where the order space is small; None marks a length drawn by rejection.
        self._orders_by_length: dict[int, list[tuple[int, ...]] | None] = {}
        for length in range(min_length, max_length + 1):
            if self._count(length) <= ENUMERATION_LIMIT:
                orders = [o for o in self._enumerate(length) if self.split_of(o) == split]
                if orders:
                    self._orders_by_length[length] = orders
            else:
                self._orders_by_length[length] = None
        self._lengths = sorted(self._orders_by_length)
        if not self._lengths:
            raise ValueError(f"no {split!r} orders of length {min_length}..{max_length}; widen the range or fractions")

    def seed(self, seed: int | None) -> None:
        """Re-seed the sampling stream."""
        self.rng = np.random.default_rng(seed)

    def _count(self, length: int) -> int:
        if length == 0:
            return 1
        return self.n_arms * (self.n_arms - 1) ** (length - 1) if self.no_adjacent_repeats else self.n_arms**length

    def _enumerate(self, length: int) -> list[tuple[int, ...]]:
        frontier: list[tuple[int, ...]] = [()]
        for _ in range(length):
            frontier = [
                prefix + (arm,)
                for prefix in frontier
                for arm in range(1, self.n_arms + 1)
                if not (self.no_adjacent_repeats and prefix and prefix[-1] == arm)
            ]
        return frontier

    def _random_order(self, length: int, rng: np.random.Generator) -> tuple[int, ...]:
        order: list[int] = []
        for _ in range(length):
            choices = [
                a for a in range(1, self.n_arms + 1) if not (self.no_adjacent_repeats and order and order[-1] == a)
            ]
            order.append(choices[rng.integers(len(choices))])
        return tuple(order)

    def split_of(self, order: tuple[int, ...] | Instruction) -> str:
        """The split an arm order belongs to: a hash of the order, rebalanced within its length (see
        :meth:`_split_table`), so independent of the sampler's length range."""
        arms = order.arms if isinstance(order, Instruction) else tuple(order)
        if 0 < len(arms) <= MAX_INSTRUCTION_LENGTH and self._count(len(arms)) <= ENUMERATION_LIMIT:
            split = self._split_table(len(arms)).get(arms)
            if split is not None:
                return split
        return self._hashed_split(self._hash(arms))

    def _hash(self, arms: tuple[int, ...]) -> float:
        digest = hashlib.sha256(f"{self.split_seed}:{','.join(map(str, arms))}".encode()).digest()
        return int.from_bytes(digest[:8], "big") / 2.0**64

    def _hashed_split(self, u: float) -> str:
        train, validation, _ = self.fractions
        return "train" if u < train else "validation" if u < train + validation else "test"

    def _split_table(self, length: int) -> dict[tuple[int, ...], str]:
        """Split of every order of ``length``: by hash, except that a split the hash leaves without an order of this
        length (and which has a positive share) takes one from the largest split, the neighbours in hash order moving.

        With three arms and ``split_seed=0`` this moves three orders (one each of lengths 1, 2 and 3; no order moves
        between train and test): every split then holds every length.
        """
        if length not in self._tables:
            orders = sorted(self._enumerate(length), key=self._hash)
            counts = [sum(self._hashed_split(self._hash(o)) == split for o in orders) for split in SPLITS]
            if len(orders) >= len(SPLITS):
                for index in range(len(SPLITS)):
                    if counts[index] == 0 and self.fractions[index] > 0:
                        donor = max((i for i in range(len(SPLITS)) if i != index), key=lambda i: (counts[i], -i))
                        counts[index], counts[donor] = 1, counts[donor] - 1
            bounds = np.cumsum(counts)
            self._tables[length] = {
                order: SPLITS[int(np.searchsorted(bounds, rank, side="right"))] for rank, order in enumerate(orders)
            }
        return self._tables[length]

    @property
    def orders(self) -> list[tuple[int, ...]]:
        """Every arm order in this sampler's split and length range (``ValueError`` where there are too many)."""
        if any(orders is None for orders in self._orders_by_length.values()):
            raise ValueError(f"more than {ENUMERATION_LIMIT} orders per length: too many to list")
        return [order for length in self._lengths for order in self._orders_by_length[length]]

    def sample(self, rng: np.random.Generator | None = None) -> Instruction:
        """One instruction: a uniform length, then a uniform order of that length from this split, then targets.

        :param rng: draw from this generator instead of the sampler's own stream.
        """
        rng = self.rng if rng is None else rng
        length = self._lengths[rng.integers(len(self._lengths))]
        candidates = self._orders_by_length[length]
        if candidates is not None:
            order = candidates[rng.integers(len(candidates))]
        else:
            order = self._random_order(length, rng)
            while self.split_of(order) != self.split:
                order = self._random_order(length, rng)
        instruction = Instruction.from_arms(order, n_arms=self.n_arms)
        if self.targets == "default":
            return instruction  # arm-only waypoints: the env uses each arm's default point
        return resolve_targets(instruction, self.targets, self.layout, rng)

    def sample_tasks(self, n: int) -> list[Instruction]:
        """``n`` independent instructions (a meta-batch)."""
        return [self.sample() for _ in range(n)]

    def stratified_orders(self, n: int, seed: int = 0) -> list[tuple[int, ...]]:
        """``n`` distinct orders of this split spread as evenly as they allow over its lengths, interleaved by length
        (the order of length 1, then 2, ... then each length's second one, ...) so every prefix is stratified too.

        A length gets an equal share of what is left (at most all of its orders); the orders of a length are drawn with
        ``seed``. ``ValueError`` where the split holds fewer than ``n`` orders in the sampler's length range.
        """
        rng = np.random.default_rng(seed)
        available = {
            length: len(orders) if orders is not None else n for length, orders in self._orders_by_length.items()
        }
        if sum(available.values()) < n:
            raise ValueError(f"the {self.split!r} split holds {sum(available.values())} orders of lengths "
                             f"{self.min_length}..{self.max_length}, fewer than {n}")
        quota, remaining = {}, n
        for index, length in enumerate(sorted(available, key=lambda length: (available[length], length))):
            left = len(available) - index
            quota[length] = min(available[length], -(-remaining // left))
            remaining -= quota[length]
        drawn: dict[int, list[tuple[int, ...]]] = {}
        for length in self._lengths:
            candidates = self._orders_by_length[length]
            if candidates is not None:
                drawn[length] = [candidates[i] for i in rng.choice(len(candidates), quota[length], replace=False)]
                continue
            picked: dict[tuple[int, ...], None] = {}
            while len(picked) < quota[length]:
                order = self._random_order(length, rng)
                if self.split_of(order) == self.split:
                    picked[order] = None
            drawn[length] = list(picked)
        return [drawn[length][r] for r in range(max(quota.values())) for length in self._lengths if r < quota[length]]

    def fixed_set(self, n: int, seed: int = 0) -> list[Instruction]:
        """A deterministic set of ``n`` instructions (e.g. the held-out evaluation set), independent of the stream."""
        rng = np.random.default_rng(seed)
        return [self.sample(rng) for _ in range(n)]
