"""Dynamics variants: the Dynamics spec, the fixed train/test family, the env's dynamics kwarg and DynamicsTasks."""

from __future__ import annotations

import csv
import json
import os
import runpy
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import vafn_gym  # noqa: F401
from vafn_gym import Dynamics, DynamicsTasks, MultiArmEnv
from vafn_gym.dynamics import DYNAMICS_FAMILY, DYNAMICS_VARIANTS, DYNAMICS_VERSION, NOMINAL

ROOT = Path(__file__).resolve().parents[1]


def test_bad_fields_are_refused_by_name():
    with pytest.raises(ValueError, match="action_gain"):
        Dynamics(action_gain=-1.0)
    with pytest.raises(TypeError, match="action_delay"):
        Dynamics(action_delay=1.5)
    with pytest.raises(ValueError, match="action_rotation"):
        Dynamics(action_rotation=200.0)
    with pytest.raises(ValueError, match="speed_limit"):
        Dynamics(speed_limit=0.0)
    with pytest.raises(ValueError, match=r"unknown dynamics field\(s\) \['gain'\]"):
        Dynamics.coerce({"gain": 2.0})
    with pytest.raises(TypeError, match="dynamics must be"):
        Dynamics.coerce(3)
    with pytest.raises(ValueError, match="dynamics split"):
        MultiArmEnv(dynamics="validation")


def test_velocity_is_rotated_scaled_and_capped():
    assert np.allclose(Dynamics(action_rotation=90.0).velocity(np.array([1.0, 0.0, 0.5])), [0.0, 1.0, 0.5])
    assert np.allclose(Dynamics(action_gain=2.0).velocity(np.array([0.1, -0.2, 0.3])), [0.2, -0.4, 0.6])
    capped = Dynamics(action_gain=2.0, speed_limit=0.3).velocity(np.array([0.1, -0.2, 0.3]))
    assert np.allclose(capped, [0.2, -0.3, 0.3])
    assert np.array_equal(NOMINAL.velocity(np.array([0.1, 0.2, 0.3])), [0.1, 0.2, 0.3])
    assert Dynamics.coerce(NOMINAL.as_dict()) == NOMINAL and Dynamics.coerce(None) == NOMINAL


def test_family_is_fixed_versioned_and_its_splits_disjoint():
    assert DYNAMICS_VERSION == "dynamics-v1"
    train, test = DYNAMICS_VARIANTS["train"], DYNAMICS_VARIANTS["test"]
    assert len(train) == 40 and len(test) == 12 and not set(train) & set(test)
    assert tuple(DYNAMICS_FAMILY.fixed_set(12, seed=1)) == test  # a pure function of the seed
    # the lists span the family's ranges, not one corner of it
    assert min(v.action_gain for v in train) < 0.6 and max(v.action_gain for v in train) > 2.0
    assert {v.action_delay for v in train} == {0, 1, 2, 3}
    assert min(v.action_rotation for v in train) < -100 and max(v.action_rotation for v in train) > 100


def _first_move(env: MultiArmEnv, action: np.ndarray, steps: int) -> list[float]:
    """How far the active arm's commanded point moved at each of ``steps`` steps of ``action``."""
    moves = []
    for _ in range(steps):
        arm = env.arms[env.active_arm]
        before = arm.commanded.copy()
        env.step(action)
        moves.append(float(np.linalg.norm(arm.commanded - before)))
    return moves


def test_delay_holds_the_first_commands_back():
    env = MultiArmEnv(instruction=[1], dynamics={"action_delay": 2})
    env.reset(seed=0)
    action = np.zeros(9, dtype=np.float32)
    action[0:3] = [0.0, 0.0, 1.0]
    moves = _first_move(env, action, 4)
    assert moves[0] == moves[1] == 0.0 and moves[2] > 0.0 and moves[3] > 0.0
    env.reset(seed=0)  # a reset forgets the commands of the last episode
    assert _first_move(env, np.zeros(9, dtype=np.float32), 3) == [0.0, 0.0, 0.0]
    env.close()


def test_rotation_turns_the_arm_s_motion():
    moved = {}
    for rotation in (0.0, 90.0):
        env = MultiArmEnv(instruction=[1], dynamics={"action_rotation": rotation})
        env.reset(seed=0)
        arm = env.arms[1]
        start = arm.commanded.copy()
        action = np.zeros(9, dtype=np.float32)
        action[0] = 0.5  # +x only
        for _ in range(3):
            env.step(action)
        moved[rotation] = arm.commanded - start
        env.close()
    assert abs(moved[0.0][0]) > 0.01 and abs(moved[0.0][1]) < 1e-6
    assert abs(moved[90.0][1]) > 0.01 and abs(moved[90.0][0]) < 1e-6


def test_a_split_draws_a_variant_per_reset_reproducibly_and_set_dynamics_overrides_it():
    env = gym.make("VAFN/ThreeArmReach-v1", dynamics="train")
    base = env.unwrapped
    drawn = []
    for seed in (0, 0, 1):
        _, info = env.reset(seed=seed)
        drawn.append(info["dynamics"])
    assert drawn[0] == drawn[1] and all(v in DYNAMICS_VARIANTS["train"] for v in drawn)
    seen = {env.reset()[1]["dynamics"] for _ in range(10)}
    assert len(seen) > 1
    mass = base.sim.link_mass(base.arms[1].body, base.robot.ee_link)
    base.set_dynamics({"payload": 1.5})  # takes effect at once, and stays over resets
    assert base.sim.link_mass(base.arms[1].body, base.robot.ee_link) == pytest.approx(base._base_masses[1] + 1.5)
    assert env.reset()[1]["dynamics"] == Dynamics(payload=1.5)
    base.set_dynamics(None)  # back to drawing train variants
    assert env.reset()[1]["dynamics"] in DYNAMICS_VARIANTS["train"]
    assert np.isfinite(mass)
    env.close()


def test_maml_sac_meta_trains_over_variants_through_dynamics_tasks():
    from vafn_sb3 import MAMLSAC

    env = DynamicsTasks(gym.make("VAFN/ThreeArmReach-v1", max_length=1, dynamics="train"))
    assert env.sampler.fixed_set(3) == list(DYNAMICS_VARIANTS["train"][:3])
    model = MAMLSAC("SharedAgentPolicy", env, warmup_steps=20, learning_starts=10, batch_size=8, n_support=10,
                    n_query=10, meta_batch_size=2, outer_steps=1, n_train_tasks=4, policy_kwargs={"net_arch": [8]},
                    seed=0)
    model.learn(80)
    assert model.train_tasks == list(DYNAMICS_VARIANTS["train"][:4]) and model.meta_iterations >= 1
    assert env.unwrapped._fixed_dynamics is None  # learn() hands the env back to its own setting
    with pytest.raises(TypeError, match="needs a MultiArmEnv"):
        DynamicsTasks(gym.make("CartPole-v1"))
    env.close()


def test_adaptation_study_runs_every_task_under_every_held_out_variant(tmp_path):
    from vafn_sb3 import MTSAC, save_weights

    env = gym.make("VAFN/ThreeArmReach-v1", max_length=1)
    model = MTSAC("SharedAgentPolicy", env, learning_starts=10, batch_size=8, policy_kwargs={"net_arch": [8]}, seed=0)
    model.learn(20)
    save_weights(model, tmp_path / "mtsac_seed0.zip")
    env.close()
    study = runpy.run_path(str(ROOT / "benchmarks" / "adaptation.py"), run_name="adaptation_study")
    out = tmp_path / "out"
    study["main"](["--env", "VAFN/ThreeArmReach-v1", "--dynamics", "test", "--max-length", "1", "--n-tasks", "1",
                   "--k", "0", "1", "--n-support", "8", "--method", "mtsac", "mtsac", str(tmp_path / "mtsac_seed*.zip"),
                   "--method", "identify", "mtsac", str(tmp_path / "mtsac_seed*.zip"), "identify",
                   "--method", "online", "mtsac", str(tmp_path / "mtsac_seed*.zip"), "identify-online",
                   "--out", str(out)])
    with (out / "adaptation.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    labels = {v.label for v in DYNAMICS_VARIANTS["test"]}
    assert {r["variant"] for r in rows if r["method"] == "mtsac"} == labels
    counts = {m: sum(r["method"] == m for r in rows) for m in ("mtsac", "identify", "online")}
    assert counts == {"mtsac": 2 * len(labels), "identify": 2 * len(labels), "online": len(labels)}
    meta = json.loads((out / "adaptation.json").read_text())
    assert [m["compensation"] for m in meta["methods"]] == [None, "identify", "identify-online"]
    assert {(r["method"], r["k"]) for r in meta["by_variant"]} >= {("mtsac", 0), ("identify", 1)}
    assert meta["dynamics"]["version"] == DYNAMICS_VERSION and len(meta["dynamics"]["variants"]) == len(labels)
    with (out / "adaptation_by_variant.csv").open() as handle:
        assert {(r["method"], r["k"]) for r in csv.DictReader(handle)} >= {("mtsac", "0"), ("mtsac", "1")}
    with pytest.raises(SystemExit, match="another --dynamics"):  # nominal rows would mix with the variants'
        study["main"](["--env", "VAFN/ThreeArmReach-v1", "--max-length", "1", "--n-tasks", "1", "--k", "0", "1",
                       "--n-support", "8", "--method", "mtsac", "mtsac", str(tmp_path / "mtsac_seed*.zip"),
                       "--append", "--out", str(out)])


def _pairs(rotation: float, n: int, noise: float, seed: int = 0):
    """Observations of arm 1 executing whose moves are its commands turned by ``rotation`` (3 arms, 5 numbers each)."""
    from vafn_gym.constants import CONTROL_DT, V_MAX

    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, size=(n, 9)).astype(np.float32)
    observations = np.zeros((n + 1, 15), dtype=np.float32)
    observations[:, 4] = 1.0  # arm 1 executes, the others wait
    angle = np.radians(rotation)
    for t in range(n):
        x, y = actions[t, :2] * V_MAX * CONTROL_DT
        move = np.array([np.cos(angle) * x - np.sin(angle) * y, np.sin(angle) * x + np.cos(angle) * y])
        observations[t + 1, :2] = observations[t, :2] + move + rng.normal(0, noise, 2)
    return observations[:-1], actions, observations[1:], np.zeros(n)


def test_fit_response_recovers_a_turn_and_refuses_noise():
    from vafn_sb3.inference import fit_response

    fit = fit_response(*_pairs(120.0, 50, noise=0.001), n_arms=3)
    assert fit.rotation == pytest.approx(120.0, abs=3.0) and fit.lag == 0 and fit.usable
    action = np.array([1.0, 0.0, 0.2] * 3, dtype=np.float32)
    corrected = fit.correct(action, 3)  # turned back: the arm then moves along +x
    assert corrected[0] == pytest.approx(np.cos(np.radians(-fit.rotation)), abs=1e-5) and corrected[2] == 0.2
    noise = fit_response(*_pairs(0.0, 50, noise=0.5), n_arms=3)  # the moves have nothing to do with the commands
    assert not noise.usable and np.array_equal(noise.correct(action, 3), action)
    assert not fit_response(*_pairs(0.0, 5, noise=0.0), n_arms=3).usable  # too few pairs


@pytest.mark.parametrize("online", [False, True])
def test_compensation_lets_a_nominal_controller_reach_on_a_turned_robot(online):
    from vafn_gym import ScriptedController, run_episode
    from vafn_sb3.inference import DynamicsCompensation

    env = gym.make("VAFN/ThreeArmReach-v1", instruction=[1, 2], dynamics={"action_rotation": 130.0})
    scripted = ScriptedController.for_env(env)
    assert run_episode(scripted, env, seed=0)["success"] == 0.0  # turned 130°, the nominal controller fails
    policy = DynamicsCompensation(scripted, 3, online=online)
    if not online:
        policy = policy.adapt(env, n_support=150, seed=0)
        assert policy.response.rotation == pytest.approx(130.0, abs=20.0) and len(policy.support) == 150
    row = run_episode(policy, env, seed=0)
    assert row["success"] == 1.0 and row["collision"] == 0.0
    env.close()


def test_online_controller_adapts_when_a_new_robot_is_announced():
    from vafn_gym import ScriptedController
    from vafn_sb3 import OnlineController
    from vafn_sb3.inference import DynamicsCompensation

    stream = gym.make("VAFN/ThreeArmStream-v1", arrivals={0: ["1,2", "3"]}, auto_dequeue=False, horizon=1000)
    controller = OnlineController(DynamicsCompensation(ScriptedController.for_env(stream), 3), stream, k=1,
                                  n_support=25)
    for _ in range(10):
        controller.step()
    with pytest.raises(ValueError, match="action_rotation"):
        controller.announce_dynamics({"action_rotation": 400.0})
    assert controller.dynamics_events == []  # refused before anything changed
    turned = Dynamics(action_rotation=-120.0)
    stream.unwrapped.set_dynamics(turned)
    controller.announce_dynamics(turned)
    assert controller.twin.dynamics == turned
    while len(controller.log) < 2 or controller.log[-1].outcome == "running":
        controller.step()
    assert [entry.success for entry in controller.log] == [True, True]
    event = controller.dynamics_events[0]
    assert event["sequence"] == controller.log[0].sequence and 0 < event["first_action_s"] < 1.0
    controller.close()
    stream.close()


def test_embodiment_variants_build_three_arm_envs_and_damping_reaches_every_controlled_joint(monkeypatch):
    from dataclasses import replace

    from vafn_gym import EMBODIMENT_VARIANTS, KUKA_IIWA, RobotSpec
    from vafn_gym.sim.bullet import BulletSim

    with pytest.raises(ValueError, match="joint_force"):
        replace(KUKA_IIWA, joint_force=0.0)
    with pytest.raises(ValueError, match="joint_damping"):
        replace(KUKA_IIWA, joint_damping=-1.0)
    damped: list[tuple[int, int, float]] = []
    monkeypatch.setattr(BulletSim, "set_joint_damping", lambda self, body, joint, value: damped.append(
        (body, joint, value)))
    env = gym.make("VAFN/ThreeArmReach-v1", robot=replace(KUKA_IIWA, joint_damping=5.0))
    assert sorted({joint for _, joint, _ in damped}) == list(KUKA_IIWA.joints) and {v for *_, v in damped} == {5.0}
    assert len({body for body, _, _ in damped}) == 3
    env.close()
    monkeypatch.undo()
    assert "xArm6 arms" in EMBODIMENT_VARIANTS and any(
        isinstance(kwargs.get("robot"), RobotSpec) for kwargs in EMBODIMENT_VARIANTS.values())
    for label, kwargs in EMBODIMENT_VARIANTS.items():
        env = gym.make("VAFN/MultiArmReach-v1", n_arms=3, **kwargs)
        observation, _ = env.reset(seed=0)
        assert observation.shape == (15,) and env.action_space.shape == (9,), label
        env.step(np.zeros(9, dtype=np.float32))
        env.close()


def test_transfer_embodiment_table_has_every_variant_beside_the_scripted_controller(tmp_path):
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "transfer.py"), "--algo", "sac", "--n-test", "1",
                             "--embodiment", "--tag", "_e", "--out", str(tmp_path)], capture_output=True, text=True,
                            timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 0, result.stderr[-2000:]
    from vafn_gym import EMBODIMENT_VARIANTS

    rows = [line for line in (tmp_path / "transfer_sac_e.md").read_text().splitlines() if line.startswith("| ")]
    assert rows[0].startswith("| variant |") and "scripted controller's success" in rows[0]
    assert [row.split(" | ")[0][2:] for row in rows[1:]] == list(EMBODIMENT_VARIANTS)
    assert all(len(row.strip("|").split("|")) == 5 for row in rows[1:])
