"""Task distribution and task semantics: sampler splits per layout, target resolution, RewardConfig, the benchmark."""

import numpy as np
import pytest

from vafn_gym import (
    ArmLayout,
    Instruction,
    InstructionBenchmark,
    InstructionTask,
    RewardConfig,
    TaskSampler,
)


def test_splits_are_disjoint_and_cover_the_space():
    samplers = {split: TaskSampler(split) for split in ("train", "validation", "test")}
    orders = {split: set(s.orders) for split, s in samplers.items()}
    assert not orders["train"] & orders["test"]
    assert not orders["train"] & orders["validation"]
    assert not orders["validation"] & orders["test"]
    total = sum(len(o) for o in orders.values())
    assert total == 3 * (2**10 - 1)  # lengths 1..10, no adjacent repeats


def test_four_arm_split_covers_its_order_space():
    layout = ArmLayout(n_arms=4)
    orders = [set(TaskSampler(split, max_length=5, layout=layout).orders) for split in ("train", "validation", "test")]
    assert sum(len(o) for o in orders) == sum(4 * 3 ** (n - 1) for n in range(1, 6))
    assert set().union(*orders) >= {(4,), (1, 4), (4, 3, 2, 1)}


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


@pytest.mark.parametrize("n_arms", [2, 4, 6, 8])
def test_sampler_takes_the_arm_count_from_the_layout(n_arms):
    sampler = TaskSampler("train", seed=0, layout=ArmLayout(n_arms=n_arms))
    arms = {arm for instruction in sampler.sample_tasks(300) for arm in instruction.arms}
    assert arms == set(range(1, n_arms + 1))


def test_long_orders_of_many_arms_are_drawn_by_rejection_within_their_split():
    sampler = TaskSampler("test", min_length=9, max_length=10, seed=0, layout=ArmLayout(n_arms=8))
    with pytest.raises(ValueError, match="too many to list"):
        _ = sampler.orders
    for instruction in sampler.sample_tasks(50):
        assert 9 <= len(instruction) <= 10 and sampler.split_of(instruction) == "test"
        assert all(a != b for a, b in zip(instruction.arms, instruction.arms[1:]))


@pytest.mark.parametrize("targets", ["per_arm", "per_waypoint"])
def test_sampled_hidden_targets_lie_in_the_layouts_shared_region(targets):
    layout = ArmLayout(n_arms=4, shared_radius=0.1, shared_z_range=(0.3, 0.35))
    for instruction in TaskSampler("train", targets=targets, seed=0, layout=layout).sample_tasks(50):
        for waypoint in instruction:
            x, y, z = waypoint.target
            assert (x * x + y * y) ** 0.5 <= 0.1 + 1e-9 and 0.3 <= z <= 0.35


def test_sampled_target_modes():
    sampler = TaskSampler("train", targets="per_arm", min_length=6, max_length=6, seed=0)
    per_waypoint = TaskSampler("train", targets="per_waypoint", min_length=6, max_length=6, seed=0)
    for same, different in zip(sampler.sample_tasks(10), per_waypoint.sample_tasks(10)):
        assert_targets_per_arm(same, shared=True)
        assert_targets_per_arm(different, shared=False)
    assert all(not w.has_target for w in TaskSampler("train", seed=0).sample())


def assert_targets_per_arm(instruction: Instruction, shared: bool) -> None:
    """Visits of one arm meet one target (``shared``) or pairwise different ones."""
    by_arm: dict[int, list[tuple[float, ...]]] = {}
    for waypoint in instruction:
        by_arm.setdefault(waypoint.arm, []).append(waypoint.target)
    repeated = [targets for targets in by_arm.values() if len(targets) > 1]
    assert repeated, f"{instruction.to_code()} visits no arm twice"
    for targets in repeated:
        assert (len(set(targets)) == 1) is shared


def test_length_range_and_bad_arguments():
    lengths = {len(i) for i in TaskSampler("train", min_length=2, max_length=3, seed=0).sample_tasks(200)}
    assert lengths == {2, 3}
    with pytest.raises(ValueError, match="split"):
        TaskSampler("dev")
    with pytest.raises(ValueError, match="targets"):
        TaskSampler(targets="colour")
    with pytest.raises(ValueError, match="min_length"):
        TaskSampler(min_length=5, max_length=2)
    with pytest.raises(ValueError, match="no 'validation' orders"):
        TaskSampler("validation", min_length=1, max_length=1, fractions=(0.5, 0.0, 0.5))


def test_every_split_holds_every_length_and_only_three_orders_left_their_hashed_split():
    samplers = {split: TaskSampler(split) for split in ("train", "validation", "test")}
    for split, sampler in samplers.items():
        assert sorted({len(order) for order in sampler.orders}) == list(range(1, 11)), split
    sampler = samplers["train"]
    moved = {o: sampler.split_of(o) for n in range(1, 11) for o in sampler._enumerate(n)
             if sampler.split_of(o) != sampler._hashed_split(sampler._hash(o))}
    assert moved == {(2,): "validation", (2, 1): "validation", (3, 1, 2): "validation", (2, 1, 2): "test"}


# --- InstructionTask: target resolution ---
def resolve(targets: str, code: str, seed: int = 0, n_arms: int = 3) -> Instruction:
    """``code`` resolved by a task of ``targets`` mode."""
    task = InstructionTask(ArmLayout(n_arms=n_arms), targets=targets)
    return task.resolve(Instruction.parse(code), np.random.default_rng(seed))


def test_resolve_default_per_arm_and_per_waypoint():
    layout = ArmLayout()
    default = resolve("default", "1,2,1")
    assert np.allclose(default.targets, [layout.default_target(a) for a in (1, 2, 1)])
    assert_targets_per_arm(resolve("per_arm", "1,2,1,3,2"), shared=True)
    assert_targets_per_arm(resolve("per_waypoint", "1,2,1,3,2"), shared=False)
    assert resolve("per_arm", "1,2,1", seed=1) != resolve("per_arm", "1,2,1", seed=2)
    assert resolve("per_arm", "1,2,1", seed=1) == resolve("per_arm", "1,2,1", seed=1)


@pytest.mark.parametrize("targets", ["default", "per_arm", "per_waypoint"])
def test_explicit_targets_always_win(targets):
    explicit = Instruction.from_arms([1, 2, 1], [[0.1, 0.0, 0.3], [0.0, 0.1, 0.3], [0.05, 0.05, 0.4]])
    task = InstructionTask(ArmLayout(), targets=targets)
    assert task.resolve(explicit, np.random.default_rng(0)) == explicit
    mixed = Instruction([explicit[0], Instruction.parse("1")[0]])
    resolved = task.resolve(mixed, np.random.default_rng(0))
    assert resolved[0] == explicit[0] and resolved[1].has_target


def test_resolve_takes_the_arm_count_from_the_layout():
    assert resolve("default", "4,1", n_arms=4).arms == (4, 1)
    with pytest.raises(ValueError, match="arm 4 is outside the allowed range 1..3"):
        resolve("default", "1,4")


def test_task_phases_and_current_targets():
    layout = ArmLayout()
    task = InstructionTask(layout)
    task.start(resolve("default", "2,3,2"))
    assert task.active_arm == 2 and [task.phase(a) for a in (1, 2, 3)] == [2, 1, 0]
    assert np.allclose(task.current_target(1), layout.home_point(1))
    here = {arm: layout.home_point(arm) for arm in layout.arm_ids}
    there = {**here, 2: layout.default_target(2)}
    reward = task.step(here, there, contact=False, too_close=False)
    assert task.waypoint_index == 1 and task.active_arm == 3
    progress = np.linalg.norm(layout.home_point(2) - layout.default_target(2))
    precision = np.log(progress + 0.01) - np.log(0.01)  # the default precision term, from `progress` to 0
    assert np.isclose(reward, 10.0 * progress + precision + 1.0)


# --- RewardConfig ---
def test_reward_config_from_kwargs():
    config = RewardConfig.from_kwargs({"progress_weight": 2.0, "collision_penalty": 0})
    assert config.progress_weight == 2.0 and config.collision_penalty == 0
    assert RewardConfig.from_kwargs(None) == RewardConfig()
    assert config.as_dict()["waypoint_bonus"] == 1.0
    with pytest.raises(ValueError, match=r"unknown reward_kwargs \['colision_penalty'\]"):
        RewardConfig.from_kwargs({"colision_penalty": 1.0})
    for bad in (float("nan"), True, "1", float("inf")):
        with pytest.raises(ValueError, match="progress_weight"):
            RewardConfig(progress_weight=bad)


def test_precision_term_rewards_the_last_centimetres_most():
    layout = ArmLayout()
    here = {arm: layout.home_point(arm) for arm in layout.arm_ids}
    target = layout.default_target(1)
    task = InstructionTask(layout, reward=RewardConfig(progress_weight=0.0, waypoint_bonus=0.0, precision_weight=1.0))
    task.start(resolve("default", "1"))
    direction = (here[1] - target) / np.linalg.norm(here[1] - target)

    def at(distance: float) -> dict:
        return {**here, 1: target + distance * direction}

    far = task.step(at(0.30), at(0.28), contact=False, too_close=False)
    near = task.step(at(0.08), at(0.06), contact=False, too_close=False)
    assert np.isclose(near, np.log(0.09 / 0.07)) and np.isclose(far, np.log(0.31 / 0.29))
    assert near > 3 * far  # the same 2 cm are worth more close to the target
    with pytest.raises(ValueError, match="precision_scale"):
        RewardConfig(precision_scale=0.0)


def test_collision_penalty_is_charged_once_and_sparse_reward():
    layout = ArmLayout()
    here = {arm: layout.home_point(arm) for arm in layout.arm_ids}
    dense = InstructionTask(layout, reward=RewardConfig(proximity_penalty=0.5))
    dense.start(resolve("default", "1"))
    rewards = [dense.step(here, here, contact=True, too_close=True) for _ in range(5)]
    assert rewards == [-5.5, -0.5, -0.5, -0.5, -0.5] and dense.collided
    sparse = InstructionTask(layout, reward_type="sparse")
    sparse.start(resolve("default", "1"))
    assert [sparse.step(here, here, contact=True, too_close=True) for _ in range(3)] == [-1.0, 0.0, 0.0]
    there = {**here, 1: layout.default_target(1)}
    assert sparse.step(here, there, contact=False, too_close=False) == 1.0
    assert sparse.complete and not sparse.info(np.zeros(3), contact=False)["is_success"]  # collided earlier


# --- InstructionBenchmark ---
def test_benchmark_test_tasks_are_held_out_and_reproducible():
    first = InstructionBenchmark("VAFN/MultiArmReach-v1", n_test=30, env_kwargs={"n_arms": 4})
    again = InstructionBenchmark("VAFN/MultiArmReach-v1", n_test=30, env_kwargs={"n_arms": 4})
    assert first.test_tasks == again.test_tasks and len(first.test_tasks) == 30
    sampler = TaskSampler(layout=ArmLayout(n_arms=4))
    assert {sampler.split_of(t) for t in first.test_tasks} == {"test"}
    assert {sampler.split_of(t) for t in first.train_tasks} == {"train"}
    assert max(a for t in first.test_tasks for a in t.arms) == 4
    hidden = InstructionBenchmark("VAFN/ThreeArmReachHidden-v1", n_test=5)
    assert all(w.has_target for t in hidden.test_tasks for w in t)
    env = first.make_env(robot="panda")
    assert env.unwrapped.n_arms == 4 and env.unwrapped.robot.name == "panda"
    env.close()
