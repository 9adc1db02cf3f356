"""ThreeArmEnv / ThreeArmStreamEnv: API conformance, semantics, determinism, collisions, the scripted ceiling."""

import threading
import time

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from stable_baselines3.common.env_util import make_vec_env

from vafn_gym import ENV_IDS, Instruction, ScriptedController
from vafn_gym.envs.three_arm import PROXIMITY_PENALTY
from vafn_gym.constants import (
    ACTION_DIM,
    OBS_DIM,
    PHASE_COMPLETED,
    PHASE_EXECUTING,
    PHASE_INDEX,
    PHASE_WAITING,
    obs_slice,
)


@pytest.fixture
def reach():
    env = gym.make("VAFN/ThreeArmReach-v0")
    yield env
    env.close()


def run_scripted(env, seed):
    return ScriptedController().run_episode(env, seed)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_check_env(env_id):
    env = gym.make(env_id)
    gym_check_env(env.unwrapped, skip_render_check=True)
    sb3_check_env(env.unwrapped)
    expected = OBS_DIM + (3 if env_id == "VAFN/ThreeArmReachGoal-v0" else 0)
    assert env.observation_space.shape == (expected,) and env.action_space.shape == (ACTION_DIM,)
    assert np.all(np.isfinite(env.observation_space.low)) and np.all(np.isfinite(env.observation_space.high))
    env.close()
    env.close()  # closing twice is allowed


def test_rgb_array_render():
    env = gym.make("VAFN/ThreeArmReach-v0", render_mode="rgb_array", render_width=96, render_height=64)
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (64, 96, 3) and frame.dtype == np.uint8
    assert frame.std() > 5  # not a blank image
    env.close()


def test_human_render_without_display_fails_clearly(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(RuntimeError, match="needs a display"):
        gym.make("VAFN/ThreeArmReach-v0", render_mode="human")


def test_bad_kwargs_fail_clearly():
    with pytest.raises(TypeError, match="colour"):
        gym.make("VAFN/ThreeArmReach-v0", colour="red")
    with pytest.raises(ValueError, match="task_family"):
        gym.make("VAFN/ThreeArmReach-v0", task_family="x")
    with pytest.raises(ValueError, match="reward_type"):
        gym.make("VAFN/ThreeArmReach-v0", reward_type="x")
    with pytest.raises(ValueError, match="arm 7"):
        gym.make("VAFN/ThreeArmReach-v0", instruction="1,7")


def test_observation_layout_and_phases():
    env = gym.make("VAFN/ThreeArmReach-v0", instruction="2,3,2")
    obs, info = env.reset(seed=0)
    phases = [obs[obs_slice(arm)][PHASE_INDEX] for arm in (1, 2, 3)]
    assert phases == [PHASE_COMPLETED, PHASE_EXECUTING, PHASE_WAITING]
    assert info["active_arm"] == 2 and info["waypoint_index"] == 0 and info["instruction"] == Instruction.parse("2,3,2")
    base = env.unwrapped
    assert np.isclose(obs[obs_slice(2)][3], np.linalg.norm(base.arms[2].ee_position - base.current_target(2)), atol=1e-5)
    controller = ScriptedController()
    while info["waypoint_index"] == 0:
        obs, _, _, _, info = env.step(controller.act(obs))
    assert info["active_arm"] == 3
    assert obs[obs_slice(2)][PHASE_INDEX] == PHASE_WAITING and obs[obs_slice(3)][PHASE_INDEX] == PHASE_EXECUTING
    env.close()


def test_bad_actions_are_rejected_without_touching_the_sim(reach):
    obs, _ = reach.reset(seed=1)
    base = reach.unwrapped
    joints_before = [base.sim.joint_angles(arm.body, list(range(7))) for arm in base.arms.values()]
    for bad, fragment in [(np.full(ACTION_DIM, np.nan), "non-finite"), (np.array([np.inf] + [0] * 8), "indices \\[0\\]"),
                          (np.zeros(4), "shape")]:
        with pytest.raises(ValueError, match=fragment):
            reach.step(bad)
    joints_after = [base.sim.joint_angles(arm.body, list(range(7))) for arm in base.arms.values()]
    assert all(np.array_equal(a, b) for a, b in zip(joints_before, joints_after))
    assert base.steps == 0
    reach.step(np.zeros(ACTION_DIM))  # still usable
    assert base.steps == 1


def test_seeded_trajectories_are_bit_identical():
    actions = np.random.default_rng(0).uniform(-1, 1, (120, ACTION_DIM)).astype(np.float32)

    def rollout():
        env = gym.make("VAFN/ThreeArmReachHidden-v0")
        observations = [env.reset(seed=42)[0]]
        for action in actions:
            obs, reward, terminated, truncated, _ = env.step(action)
            observations.append(np.append(obs, reward))
            if terminated or truncated:
                observations.append(env.reset()[0])
        env.close()
        return np.concatenate(observations)

    first, second = rollout(), rollout()
    assert first.tobytes() == second.tobytes()


def test_forced_collision_is_detected():
    env = gym.make("VAFN/ThreeArmReach-v0", instruction="1", terminate_on_collision=True)
    obs, _ = env.reset(seed=0)
    base = env.unwrapped
    collided = False
    for _ in range(200):
        # Drive every arm to the table centre.
        action = np.concatenate([np.clip((np.array([0, 0, 0.3]) - base.arms[a].ee_position) * 20, -1, 1) for a in (1, 2, 3)])
        obs, reward, terminated, truncated, info = env.step(action)
        if info["collision"]:
            collided = True
            assert terminated and not info["is_success"] and reward < 0
            break
    assert collided
    env.close()


def test_reward_types():
    dense = gym.make("VAFN/ThreeArmReach-v0", instruction="1")
    sparse = gym.make("VAFN/ThreeArmReachSparse-v0", instruction="1")
    controller = ScriptedController()
    for env in (dense, sparse):
        obs, _ = env.reset(seed=0)
        controller.reset()
        rewards = []
        done = False
        while not done:
            obs, reward, terminated, truncated, info = env.step(controller.act(obs))
            rewards.append(reward)
            done = terminated or truncated
        assert info["is_success"]
        env.rewards = rewards
    assert sum(sparse.rewards) == 1.0 and sparse.rewards[-1] == 1.0
    assert sum(dense.rewards) > 1.0  # progress toward the target plus the waypoint bonus
    dense.close()
    sparse.close()


def test_scripted_controller_solves_random_instructions():
    """The ceiling: every difficulty, both target families, zero collisions (200 episodes: benchmarks/scripted_ceiling.py)."""
    successes, episodes = 0, 0
    for env_id in ("VAFN/ThreeArmReach-v0", "VAFN/ThreeArmReachHidden-v0"):
        env = gym.make(env_id, split="test")
        for seed in range(12):
            info = run_scripted(env, seed)
            assert not info["collided"], f"{env_id} seed {seed}: collision on {info['instruction']}"
            successes += info["is_success"]
            episodes += 1
        env.close()
    assert successes == episodes


def test_empty_instruction_is_an_immediate_success():
    env = gym.make("VAFN/ThreeArmReach-v0", instruction="")
    env.reset(seed=0)
    _, _, terminated, _, info = env.step(np.zeros(ACTION_DIM))
    assert terminated and info["is_success"] and info["active_arm"] is None
    env.close()


def test_set_task_through_vec_env_method():
    vec = make_vec_env("VAFN/ThreeArmReach-v0", n_envs=2, seed=0)
    task = Instruction.parse("3,1,2")
    vec.env_method("set_task", task)
    vec.reset()
    assert vec.env_method("get_task") == [task, task]
    vec.env_method("set_task", "1", indices=[1])
    vec.reset()
    assert [t.arms for t in vec.env_method("get_task")] == [(3, 1, 2), (1,)]
    vec.close()


def test_goal_visible_appends_the_active_target():
    env = gym.make("VAFN/ThreeArmReachGoal-v0")
    obs, info = env.reset(seed=3)
    assert np.allclose(obs[OBS_DIM:], info["instruction"][0].target, atol=1e-6)
    env.close()


def test_stream_holds_then_executes_in_fifo_order_from_another_thread():
    env = gym.make("VAFN/ThreeArmStream-v0", arrivals=None, horizon=600)
    obs, info = env.reset(seed=0)
    base = env.unwrapped
    controller = ScriptedController()
    for _ in range(5):
        obs, _, _, _, info = env.step(controller.act(obs))
    assert info["holding"] and base.holding
    assert all(obs[obs_slice(a)][PHASE_INDEX] == PHASE_COMPLETED for a in (1, 2, 3))

    def produce():
        for code in ("1,2", "bad-instruction", "3"):
            base.queue.enqueue(code, source="producer-thread", validate=False)
            time.sleep(0.001)

    producer = threading.Thread(target=produce)
    producer.start()
    producer.join()
    truncated = False
    while not truncated:
        obs, _, _, truncated, info = env.step(controller.act(obs))
    assert [r["instruction"] for r in base.records] == ["1,2", "3"]
    assert all(r["success"] for r in base.records)
    assert len(base.errors) == 1 and "bad-instruction" in base.errors[0]
    assert info["is_success"] and info["total_steps"] == 600
    env.close()


def test_stream_scheduled_phases_and_timeout():
    env = gym.make("VAFN/ThreeArmStream-v0", arrivals={0: "1,2,3", 10: "2,3,1,3,2,3"}, horizon=700)
    info = run_scripted(env, seed=0)
    base = env.unwrapped
    assert [r["instruction"] for r in base.records] == ["1,2,3", "2,3,1,3,2,3"]
    assert all(r["success"] for r in base.records) and info["holding"]
    stuck = gym.make("VAFN/ThreeArmStream-v0", arrivals={0: "1"}, horizon=50, instruction_timeout=20)
    stuck.reset(seed=0)
    for _ in range(50):
        stuck.step(np.zeros(ACTION_DIM))
    assert [r["outcome"] for r in stuck.unwrapped.records] == ["timeout"]
    env.close()
    stuck.close()


def test_stream_rejects_episode_kwargs():
    with pytest.raises(ValueError, match="queue"):
        gym.make("VAFN/ThreeArmStream-v0", instruction="1")



def test_safety_margin_penalises_proximity_without_counting_a_collision():
    plain = gym.make("VAFN/ThreeArmReach-v0", instruction="1")
    margin = gym.make("VAFN/ThreeArmReach-v0", instruction="1", safety_margin=2.0)  # every pair is "too close"
    plain.reset(seed=0)
    margin.reset(seed=0)
    action = np.zeros(ACTION_DIM)
    _, r_plain, _, _, info_plain = plain.step(action)
    _, r_margin, _, _, info_margin = margin.step(action)
    assert np.isclose(r_plain - r_margin, PROXIMITY_PENALTY) and not info_margin["collision"] and not info_plain["collision"]
    with pytest.raises(ValueError, match="safety_margin"):
        gym.make("VAFN/ThreeArmReach-v0", safety_margin=-1)
    plain.close()
    margin.close()


def test_stream_reset_keeps_user_items_with_their_stamps_and_drops_its_own_arrivals():
    env = gym.make("VAFN/ThreeArmStream-v0", arrivals={0: "1", 1: "2"}, auto_dequeue=False, horizon=10)
    env.reset(seed=0)
    base = env.unwrapped
    user_item = base.queue.enqueue("3", source="user")
    env.step(np.zeros(ACTION_DIM))  # feeds the step-1 arrival
    env.reset(seed=0)
    queued = base.queue.snapshot()
    assert queued[0] == user_item  # same sequence number and arrival time
    assert [e.payload.arms for e in queued] == [(3,), (1,)]  # the old arrivals were dropped, step 0 fed again
    env.close()
