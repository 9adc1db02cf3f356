"""The packaged policies: listed, loaded without unpickling, and doing on held-out tasks what their JSON says."""

from __future__ import annotations

import warnings

import pytest
import torch

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_gym import InstructionBenchmark, episode_rates
from vafn_sb3 import available_pretrained, load_pretrained, pretrained_info
from vafn_sb3.pretrained import WORKING_SUCCESS, pretrained_path

torch.set_num_threads(1)
#: Held-out instructions a working policy is re-scored on: the first 30 of the versioned suite (30 distinct, every
#: length 1-10); ``benchmarks/heldout.py`` reports all 200.
N_TASKS = 30
#: Instructions of the quicker checks (a negative result, target inference on lengths 1-4).
N_QUICK = 5


def test_sac_and_maml_sac_are_shipped_for_the_paper_env():
    assert {("sac", "VAFN/ThreeArmReach-v1"), ("maml_sac", "VAFN/ThreeArmReach-v1")} <= set(available_pretrained())


WORKING = [pair for pair in available_pretrained()
           if pretrained_info(*pair)["evaluation"]["success"] >= WORKING_SUCCESS]
#: Shipped to reproduce a negative result (Fig. 3 on hidden targets), with a note saying so.
NEGATIVE = [pair for pair in available_pretrained() if pair not in WORKING]


@pytest.mark.parametrize("algo, env_id", WORKING)
def test_packaged_policy_completes_held_out_instructions(algo, env_id):
    info = pretrained_info(algo, env_id)
    assert info["algo"] == algo and info["training_command"]
    assert pretrained_path(algo, env_id).is_file()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a working policy loads silently
        model = load_pretrained(algo, env_id)
    benchmark = InstructionBenchmark(env_id, 1, 10, n_test=N_TASKS)
    assert len({task.arms for task in benchmark.test_tasks}) == N_TASKS
    rates = episode_rates(benchmark.evaluate(model))
    assert rates["success"] == 1.0 and rates["collision"] == 0.0, f"{algo}: {rates}"


@pytest.mark.parametrize("algo, env_id", NEGATIVE)
def test_a_packaged_negative_result_warns_and_fails_as_its_json_says(algo, env_id):
    info = pretrained_info(algo, env_id)
    assert info["env_id"] == "VAFN/ThreeArmReachHidden-v1" and "negative result" in info["note"]
    with pytest.warns(UserWarning, match=f"packaged {algo} policy .* completes only") as caught:
        model = load_pretrained(algo, env_id)
    assert str(caught[0].message).count("negative result") == 1  # the note says it once
    rates = episode_rates(InstructionBenchmark(env_id, 1, 10, n_test=N_QUICK).evaluate(model))
    assert rates["success"] < WORKING_SUCCESS, f"{algo} now works: re-export it without the note ({rates})"


def test_unknown_pair_lists_what_is_available():
    with pytest.raises(ValueError, match=r"no pretrained 'ppo' policy .*available: .*sac on VAFN/ThreeArmReach-v1"):
        load_pretrained("ppo")


#: The packaged policies that observe their targets: run on hidden targets through target inference.
GOAL_OBSERVING = [algo for algo, env_id in available_pretrained() if env_id == "VAFN/ThreeArmReachGoal-v1"]


@pytest.mark.parametrize("inference", ["probe", "gradient"])
@pytest.mark.parametrize("algo", GOAL_OBSERVING)
def test_packaged_goal_observing_policy_completes_hidden_target_instructions_through_target_inference(algo, inference):
    """Trilateration, and 10 gradient steps of the packaged estimator (refined at every later reading)."""
    from vafn_gym.benchmarks import evaluate_tasks
    from vafn_sb3.inference import inference_policy_for_env

    hidden = "VAFN/ThreeArmReachHidden-v1"
    benchmark = InstructionBenchmark(hidden, 1, 4, n_test=N_QUICK)
    env = benchmark.make_env()
    policy = inference_policy_for_env(load_pretrained(algo, "VAFN/ThreeArmReachGoal-v1"), env, inference, steps=10)
    episodes = evaluate_tasks(policy, env, benchmark.test_tasks, benchmark.seed)
    env.close()
    assert all(e["success"] and not e["collision"] for e in episodes), (algo, [e["outcome"] for e in episodes])
