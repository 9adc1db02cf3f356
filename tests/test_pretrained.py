"""The packaged policies: listed, loaded without unpickling, and doing on held-out tasks what their JSON says."""

from __future__ import annotations

import pytest
import torch

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_gym import InstructionBenchmark, episode_rates
from vafn_sb3 import available_pretrained, load_pretrained, pretrained_info
from vafn_sb3.pretrained import pretrained_path

torch.set_num_threads(1)
#: Held-out instructions re-scored here (the JSON's evaluation used 100; these are its first ones).
N_TASKS = 5


def test_sac_and_maml_sac_are_shipped_for_the_paper_env():
    assert {("sac", "VAFN/ThreeArmReach-v1"), ("maml_sac", "VAFN/ThreeArmReach-v1")} <= set(available_pretrained())


@pytest.mark.parametrize("algo, env_id", available_pretrained())
def test_packaged_policy_completes_held_out_instructions(algo, env_id):
    info = pretrained_info(algo, env_id)
    assert info["algo"] == algo and info["training_command"] and info["evaluation"]["success"] >= 0.95
    assert pretrained_path(algo, env_id).is_file()
    model = load_pretrained(algo, env_id)
    rates = episode_rates(InstructionBenchmark(env_id, 1, 10, n_test=N_TASKS).evaluate(model))
    assert rates["success"] == 1.0 and rates["collision"] == 0.0, f"{algo}: {rates}"


def test_unknown_pair_lists_what_is_available():
    with pytest.raises(ValueError, match=r"no pretrained 'ppo' policy .*available: .*sac on VAFN/ThreeArmReach-v1"):
        load_pretrained("ppo")


def test_packaged_goal_observing_mappo_completes_hidden_target_instructions_through_target_inference():
    import gymnasium as gym

    from vafn_gym import run_episode
    from vafn_sb3 import TargetInferencePolicy

    hidden = "VAFN/ThreeArmReachHidden-v1"
    env = gym.make(hidden)
    policy = TargetInferencePolicy.for_env(load_pretrained("mappo", "VAFN/ThreeArmReachGoal-v1"), env)
    episodes = []
    for index, task in enumerate(InstructionBenchmark(hidden, 1, 4, n_test=N_TASKS).test_tasks):
        env.unwrapped.set_task(task)
        episodes.append(run_episode(policy, env, seed=index))
    env.close()
    assert all(e["success"] and not e["collision"] for e in episodes), [e["outcome"] for e in episodes]
