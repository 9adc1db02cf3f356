"""``vafn_gym.wrappers.GoalDetours``: a decoy goal at some waypoints' start, everything else the env's own."""

from __future__ import annotations

import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import vafn_gym  # noqa: F401
from vafn_gym.constants import GOAL_SLICE
from vafn_gym.wrappers import GoalDetours

ROOT = Path(__file__).resolve().parents[1]
GOAL_ENV = "VAFN/ThreeArmReachGoal-v1"


def goal_error(env: gym.Env, obs: np.ndarray) -> float | None:
    """How far the active arm's observed goal is from its true target (None with no active arm)."""
    base = env.unwrapped
    arm = base.active_arm
    if arm is None:
        return None
    return float(np.linalg.norm(obs[base.obs_slice(arm)][GOAL_SLICE] - base.observed_point(arm, base.task.goal(arm))))


def run(env: gym.Env, seed: int, steps: int) -> list[tuple]:
    """(obs, reward, error of the observed goal, waypoint) of ``steps`` seeded random steps."""
    obs, _ = env.reset(seed=seed)
    rows = [(obs, 0.0, goal_error(env, obs), env.unwrapped.task.waypoint_index)]
    actions = np.random.default_rng(seed)
    for _ in range(steps):
        obs, reward, terminated, truncated, _ = env.step(actions.uniform(-1, 1, env.action_space.shape))
        rows.append((obs, reward, goal_error(env, obs), env.unwrapped.task.waypoint_index))
        if terminated or truncated:
            break
    return rows


def test_decoys_change_only_the_active_goal_within_radius_then_end():
    wrapped = GoalDetours(gym.make(GOAL_ENV, max_length=3), probability=1.0, radius=0.1, max_steps=7)
    plain = gym.make(GOAL_ENV, max_length=3)
    detoured, reference = run(wrapped, 3, 120), run(plain, 3, 120)
    assert len(detoured) == len(reference)
    decoy_steps = 0
    for (obs, reward, error, _), (obs_ref, reward_ref, _, _) in zip(detoured, reference):
        assert reward == reward_ref
        differs = np.flatnonzero(obs != obs_ref)
        # a decoy: only the active arm's three goal entries differ, by at most the radius
        if error is not None and error > 1e-5:
            decoy_steps += 1
            block = wrapped.unwrapped.obs_slice(wrapped.unwrapped.active_arm)
            assert set(differs) <= set(range(block.start + GOAL_SLICE.start, block.start + GOAL_SLICE.stop))
            assert 0 < error <= 0.1 + 1e-6
        else:
            assert differs.size == 0
    waypoints = {row[3] for row in detoured if row[2] is not None}
    assert 0 < decoy_steps <= 7 * len(waypoints)
    # every waypoint started with a decoy (probability 1) and ended on the true goal within max_steps
    for index in waypoints:
        errors = [row[2] for row in detoured if row[3] == index and row[2] is not None]
        assert errors[0] > 1e-5
        assert all(e < 1e-5 for e in errors[7:])


def test_probability_zero_is_the_env_and_a_seed_repeats_the_decoys():
    observations = [row[0] for row in run(GoalDetours(gym.make(GOAL_ENV), probability=0.0), 5, 40)]
    assert all(np.array_equal(a, b[0]) for a, b in zip(observations, run(gym.make(GOAL_ENV), 5, 40)))
    first, second = (run(GoalDetours(gym.make(GOAL_ENV), probability=0.5), 11, 60) for _ in range(2))
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(first, second))


@pytest.mark.parametrize("env_id, kwargs, fragment", [
    ("VAFN/ThreeArmReachHidden-v1", {}, "observe_goal=True"),
    (GOAL_ENV, {"probability": 1.5}, "probability"),
    (GOAL_ENV, {"radius": 0.0}, "radius"),
    (GOAL_ENV, {"max_steps": 0}, "max_steps"),
])
def test_bad_settings_are_refused(env_id, kwargs, fragment):
    with pytest.raises(ValueError, match=fragment):
        GoalDetours(gym.make(env_id), **kwargs)


def test_learning_benchmark_wraps_the_training_env(tmp_path, monkeypatch, load_benchmark):
    """``--hyperparams '{"env_wrapper": ...}'`` wraps the training env (the zoo's format), not the evaluation."""
    learning = load_benchmark("learning")
    wrapped = []
    original = GoalDetours.__init__

    def spy(self, env, **kwargs):
        wrapped.append(kwargs)
        original(self, env, **kwargs)

    monkeypatch.setattr(GoalDetours, "__init__", spy)
    monkeypatch.setattr(sys, "argv", [
        str(ROOT / "benchmarks" / "learning.py"), "--algo", "mappo", "--env", GOAL_ENV, "--seeds", "0",
        "--steps", "64", "--eval-every", "64", "--n-eval", "1", "--n-test", "1", "--out", str(tmp_path),
        "--hyperparams", '{"n_steps": 64, "batch_size": 32, "n_epochs": 1, '
        '"env_wrapper": {"vafn_gym.wrappers.GoalDetours": {"probability": 0.3}}}'])
    learning.main()
    assert wrapped == [{"probability": 0.3}]
