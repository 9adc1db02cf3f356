"""The PettingZoo ParallelEnv view passes PettingZoo's own API and seed tests."""

import numpy as np
import pytest

pytest.importorskip("pettingzoo")
from pettingzoo.test import parallel_api_test, parallel_seed_test  # noqa: E402

from vafn_gym.constants import OBS_DIM  # noqa: E402
from vafn_gym.pettingzoo import AGENT_NAMES, parallel_env  # noqa: E402


def test_parallel_api():
    parallel_api_test(parallel_env(instruction="1,2"), num_cycles=300)


def test_parallel_seed():
    parallel_seed_test(lambda: parallel_env(max_length=3))


def test_state_is_the_global_observation_and_reward_is_shared():
    env = parallel_env(instruction="3")
    observations, _ = env.reset(seed=0)
    assert env.state().shape == (OBS_DIM,)
    assert np.array_equal(env.state(), observations[AGENT_NAMES[0]])
    _, rewards, _, _, _ = env.step({agent: np.zeros(3, dtype=np.float32) for agent in env.agents})
    assert len(set(rewards.values())) == 1
    with pytest.raises(ValueError, match="not alive"):
        env.step({"arm_9": np.zeros(3)})
    env.close()
