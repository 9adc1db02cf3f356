"""OnlineController (Algorithm 1): holding, FIFO order, malformed instructions, threads, adaptation, outputs."""

from __future__ import annotations

import csv
import threading
import time

import gymnasium as gym
import numpy as np
import pytest
import torch

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_gym import ScriptedController
from vafn_gym.constants import SUCCESS_TOLERANCE
from vafn_sb3.maml_sac import MAMLSAC
from vafn_sb3.online import OnlineController
from zoo.plot import plot_online_distances

torch.set_num_threads(1)


def make_stream(**kwargs) -> gym.Env:
    """A stream env fed only by the test (no arrival process), dequeued by the controller."""
    return gym.make("VAFN/ThreeArmStream-v1", arrivals=None, auto_dequeue=False, horizon=5000, **kwargs)


def test_holds_on_empty_queue():
    env = make_stream()
    controller = OnlineController(ScriptedController.for_env(env), env)
    controller.run(30)
    assert controller.log == [] and env.unwrapped.holding
    distances = np.asarray(controller.trace["distances"])  # to each arm's home point while holding
    assert distances.max() < SUCCESS_TOLERANCE, "arms left home while holding"


def test_fifo_order_and_malformed_instruction_is_skipped():
    env = make_stream()
    controller = OnlineController(ScriptedController.for_env(env), env)
    queue = env.unwrapped.queue
    controller.run(5)
    queue.enqueue("2,3")
    queue.enqueue("[4, 9]", validate=False)  # malformed: arm 4 does not exist
    queue.enqueue("1")
    queue.enqueue("3,1")
    controller.run(700)
    assert [entry.sequence for entry in controller.log] == [0, 2, 3]
    assert [entry.instruction for entry in controller.log] == ["2,3", "1", "3,1"]
    assert len(controller.errors) == 1 and "#1" in controller.errors[0]
    starts = [entry.start_step for entry in controller.log]
    assert starts == sorted(starts) and starts[0] == 5
    for entry, next_entry in zip(controller.log, controller.log[1:]):
        assert entry.completion_step == next_entry.start_step  # one at a time, back to back
    assert all(entry.outcome == "completed" and entry.success for entry in controller.log)
    assert env.unwrapped.holding


def test_instructions_enqueued_from_another_thread():
    env = make_stream()
    controller = OnlineController(ScriptedController.for_env(env), env)
    queue = env.unwrapped.queue

    def producer() -> None:
        for code in ("1,2", "2,1", "3"):
            time.sleep(0.05)
            queue.enqueue(code, source="thread")

    thread = threading.Thread(target=producer)
    thread.start()
    while thread.is_alive():
        controller.step()
    controller.run(600)
    assert [entry.instruction for entry in controller.log] == ["1,2", "2,1", "3"]
    assert all(entry.outcome == "completed" for entry in controller.log)


def test_adapting_controller_leaves_model_untouched_and_writes_outputs(tmp_path):
    model = MAMLSAC("MlpPolicy", gym.make("VAFN/ThreeArmReach-v1", max_length=1), policy_kwargs={"net_arch": [16, 16]},
                    n_support=16, inner_steps=2, seed=0)
    before = [t.clone() for t in model.policy.state_dict().values()]
    env = make_stream(instruction_timeout=20)
    controller = OnlineController(model, env, n_support=16)
    env.unwrapped.queue.enqueue("2,1")
    env.unwrapped.queue.enqueue("3")
    controller.run(60)
    assert [entry.outcome for entry in controller.log] == ["timeout", "timeout"]  # untrained policy, short timeout
    for entry in controller.log:
        assert entry.adaptation_time_s > 0 and entry.service_latency_s >= entry.adaptation_time_s
        assert entry.latency_s >= entry.service_latency_s and entry.completion_step - entry.start_step == 20
        assert 0 < entry.service_cpu_s <= entry.service_latency_s + 1e-3
    assert all(torch.equal(a, b) for a, b in zip(before, model.policy.state_dict().values()))

    rows = list(csv.DictReader(controller.write_csv(tmp_path / "log.csv").open()))
    assert [row["instruction"] for row in rows] == ["2,1", "3"]
    assert {
        "arrival_time", "adaptation_time_s", "first_action_time", "completion_step", "success", "collisions"
    } <= set(rows[0])
    assert plot_online_distances(controller, tmp_path / "distances.png").stat().st_size > 0
    controller.close()


def test_rejects_auto_dequeue_and_non_stream_envs():
    scripted = ScriptedController.for_env(make_stream())
    with pytest.raises(ValueError, match="auto_dequeue"):
        OnlineController(scripted, gym.make("VAFN/ThreeArmStream-v1", arrivals=None))
    with pytest.raises(TypeError, match="MultiArmStreamEnv"):
        OnlineController(scripted, gym.make("VAFN/ThreeArmReach-v1"))
    with pytest.raises(TypeError, match="adapt"):
        OnlineController(scripted, make_stream(), k=1)
