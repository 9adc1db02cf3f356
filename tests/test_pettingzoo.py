"""The PettingZoo ParallelEnv view passes PettingZoo's own API and seed tests, with 3 and 4 arms."""

import numpy as np
import pytest

pytest.importorskip("pettingzoo")
from pettingzoo.test import parallel_api_test, parallel_seed_test  # noqa: E402

from vafn_gym.pettingzoo import MultiArmParallelEnv, parallel_env  # noqa: E402


@pytest.mark.parametrize("n_arms", [3, 4])
def test_parallel_api(n_arms):
    env = parallel_env(n_arms=n_arms, instruction="1,2", inactive_arms="policy")
    assert env.possible_agents == [f"arm_{arm}" for arm in range(1, n_arms + 1)]
    parallel_api_test(env, num_cycles=200)
    env.close()


def test_parallel_seed():
    parallel_seed_test(lambda: parallel_env(n_arms=4, max_length=3))


@pytest.mark.parametrize("n_arms", [3, 4])
def test_state_is_the_global_observation_and_reward_is_shared(n_arms):
    env = MultiArmParallelEnv(n_arms=n_arms, instruction=str(n_arms))
    observations, infos = env.reset(seed=0)
    assert env.state().shape == (5 * n_arms,)
    assert all(np.array_equal(env.state(), obs) for obs in observations.values())
    assert infos[f"arm_{n_arms}"]["active_arm"] == n_arms
    assert env.action_space("arm_1").shape == (3,) and env.observation_space("arm_1").shape == (5 * n_arms,)
    _, rewards, _, _, _ = env.step({agent: np.zeros(3, dtype=np.float32) for agent in env.agents})
    assert len(set(rewards.values())) == 1 and set(rewards) == set(env.possible_agents)
    with pytest.raises(ValueError, match="not alive"):
        env.step({f"arm_{n_arms + 1}": np.zeros(3)})
    env.close()


def test_agent_actions_reach_their_own_arm():
    env = parallel_env(n_arms=4, instruction="4", inactive_arms="policy")
    env.reset(seed=0)
    base = env.env
    before = {arm: base.arms[arm].ee_position for arm in base.layout.arm_ids}
    for _ in range(10):
        env.step({"arm_3": np.array([0.0, 0.0, 1.0], dtype=np.float32)})  # missing agents' actions are zero
    moved = {arm: np.linalg.norm(base.arms[arm].ee_position - before[arm]) for arm in base.layout.arm_ids}
    assert moved[3] > 0.05 and max(moved[a] for a in (1, 2, 4)) < 5e-3


def test_agents_are_removed_when_the_instruction_ends():
    env = parallel_env(n_arms=3, instruction="")
    env.reset(seed=0)
    _, _, terminations, _, infos = env.step({})
    assert all(terminations.values()) and env.agents == [] and infos["arm_1"]["is_success"]
    env.close()
