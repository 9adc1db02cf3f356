"""TargetInferencePolicy: a goal-observing policy acting on hidden targets through probes and trilateration."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_gym import InstructionBenchmark, ScriptedController, run_episode, trilaterate
from vafn_sb3.target_inference import TargetInferencePolicy

HIDDEN = "VAFN/ThreeArmReachHidden-v1"
GOAL = "VAFN/ThreeArmReachGoal-v1"


def test_trilaterate_recovers_a_point_and_refuses_coplanar_readings():
    rng = np.random.default_rng(0)
    target = rng.uniform(-0.3, 0.3, 3)
    points = rng.uniform(-0.5, 0.5, (6, 3))
    distances = np.linalg.norm(points - target, axis=1)
    assert np.allclose(trilaterate(points, distances), target, atol=1e-9)
    flat = points.copy()
    flat[:, 2] = 0.1
    assert trilaterate(flat, np.linalg.norm(flat - target, axis=1)) is None
    assert trilaterate(points[:3], distances[:3]) is None


@pytest.fixture(scope="module")
def goal_oracle():
    """The scripted controller on observed targets: a goal-observing 'model' that never fails to reach a goal."""
    env = gym.make(GOAL)
    oracle = ScriptedController.for_env(env)
    oracle.observation_space = env.observation_space
    env.close()
    return oracle


def success_rate(policy, env: gym.Env, tasks: list, oracle: ScriptedController) -> float:
    outcomes = []
    for index, task in enumerate(tasks):
        env.unwrapped.set_task(task)
        oracle.reset()
        outcomes.append(run_episode(policy, env, seed=100 + index)["success"])
    return float(np.mean(outcomes))


def test_probes_make_a_goal_observing_policy_solve_hidden_targets(goal_oracle):
    env = gym.make(HIDDEN)
    tasks = InstructionBenchmark(HIDDEN, 3, 4, n_test=4).test_tasks
    probing = TargetInferencePolicy.for_env(goal_oracle, env)
    passive = TargetInferencePolicy.for_env(goal_oracle, env, inference="passive")
    blind = TargetInferencePolicy.for_env(goal_oracle, env, inference="none")
    assert success_rate(probing, env, tasks, goal_oracle) == 1.0
    assert success_rate(blind, env, tasks, goal_oracle) == 0.0
    # Without probes the readings of a near-straight approach barely constrain the target around its line: a long
    # instruction almost always has a waypoint that fails.
    assert success_rate(passive, env, tasks, goal_oracle) < 0.5
    env.close()


def test_the_estimate_is_the_hidden_target_after_the_probes(goal_oracle):
    env = gym.make(HIDDEN)
    policy = TargetInferencePolicy.for_env(goal_oracle, env)
    env.unwrapped.set_task([2])
    policy.reset()
    obs, _ = env.reset(seed=3)
    for _ in range(30):
        obs, *_ = env.step(policy.predict(obs)[0])
        if policy.estimate is not None:
            break
    base = env.unwrapped
    assert policy.estimate is not None
    assert np.allclose(policy.estimate, base.observed_point(2, base.task.current_target(2)), atol=1e-3)
    goal_obs = policy.goal_observation(obs)
    assert goal_obs.shape == goal_oracle.observation_space.shape
    env.close()


def test_bad_models_envs_and_batches_fail_clearly(goal_oracle):
    hidden = gym.make(HIDDEN)
    blind = ScriptedController.for_env(hidden)
    blind.observation_space = hidden.observation_space
    with pytest.raises(ValueError, match="observe_goal=True"):
        TargetInferencePolicy.for_env(blind, hidden)
    with pytest.raises(ValueError, match="history=1"):
        TargetInferencePolicy.for_env(goal_oracle, gym.make(HIDDEN, history=2))
    with pytest.raises(ValueError, match="history=1"):
        TargetInferencePolicy.for_env(goal_oracle, gym.make(GOAL))
    policy = TargetInferencePolicy.for_env(goal_oracle, hidden)
    obs, _ = hidden.reset(seed=0)
    with pytest.raises(ValueError, match="one observation"):
        policy.predict(np.stack([obs, obs]))
    with pytest.raises(ValueError, match="inference must be one of"):
        TargetInferencePolicy.for_env(goal_oracle, hidden, inference="guess")
    with pytest.raises(ValueError, match="arm ids"):
        TargetInferencePolicy(goal_oracle, {1: np.zeros(3)}, {2: np.zeros(3)})
    hidden.close()


def test_a_waiting_arm_gets_the_goal_the_env_would_have_shown(goal_oracle):
    for waiting_goal in ("target", "home"):
        env = gym.make(HIDDEN, waiting_goal=waiting_goal)
        policy = TargetInferencePolicy.for_env(goal_oracle, env)
        env.unwrapped.set_task([1, 2])
        obs, _ = env.reset(seed=0)
        goal = policy.goal_observation(obs)[8 + 5:8 + 8]  # arm 2 waits
        expected = policy.homes[2] if waiting_goal == "home" else policy.priors[2]
        assert np.allclose(goal, expected, atol=1e-6), waiting_goal
        env.close()
