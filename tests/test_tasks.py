"""Task sampler: determinism and split disjointness."""

import pytest

from vafn_gym import TaskSampler
from vafn_gym.constants import SHARED_RADIUS, SHARED_Z_RANGE


def test_splits_are_disjoint_and_cover_the_space():
    samplers = {split: TaskSampler(split) for split in ("train", "validation", "test")}
    orders = {split: set(s.orders) for split, s in samplers.items()}
    assert not orders["train"] & orders["test"]
    assert not orders["train"] & orders["validation"]
    assert not orders["validation"] & orders["test"]
    total = sum(len(o) for o in orders.values())
    assert total == 3 * (2**10 - 1)  # lengths 1..10, no adjacent repeats


def test_train_sampler_never_produces_test_orders():
    train = TaskSampler("train", seed=0)
    test_orders = set(TaskSampler("test").orders)
    for instruction in train.sample_tasks(2000):
        assert instruction.arms not in test_orders
        assert train.split_of(instruction) == "train"


def test_same_seed_same_tasks_and_fixed_set_is_stable():
    a, b = TaskSampler("train", seed=3), TaskSampler("train", seed=3)
    assert a.sample_tasks(20) == b.sample_tasks(20)
    assert TaskSampler("train", seed=4).sample_tasks(20) != TaskSampler("train", seed=5).sample_tasks(20)
    sampler = TaskSampler("test", seed=0)
    first = sampler.fixed_set(10, seed=1)
    sampler.sample_tasks(5)
    assert sampler.fixed_set(10, seed=1) == first


def test_hidden_targets_lie_in_the_shared_region():
    for instruction in TaskSampler("train", family="hidden_targets", seed=0).sample_tasks(50):
        for waypoint in instruction:
            x, y, z = waypoint.target
            assert (x * x + y * y) ** 0.5 <= SHARED_RADIUS + 1e-9
            assert SHARED_Z_RANGE[0] <= z <= SHARED_Z_RANGE[1]


def test_length_range_and_bad_arguments():
    lengths = {len(i) for i in TaskSampler("train", min_length=2, max_length=3, seed=0).sample_tasks(200)}
    assert lengths <= {2, 3}
    with pytest.raises(ValueError, match="split"):
        TaskSampler("dev")
    with pytest.raises(ValueError, match="family"):
        TaskSampler(family="colour")
    with pytest.raises(ValueError, match="min_length"):
        TaskSampler(min_length=5, max_length=2)
    with pytest.raises(ValueError, match="no 'validation' orders"):
        TaskSampler("validation", min_length=1, max_length=1)
