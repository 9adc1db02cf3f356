"""``vafn_sb3.loading.load_model`` tells the algorithm of a saved SB3 zip from what the file says, not by trial."""

import base64
import json
import pickle
import zipfile
from unittest import mock

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from sb3_contrib import RecurrentPPO
from stable_baselines3 import DDPG, PPO, TD3
from stable_baselines3 import SAC as SB3SAC

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_sb3 import MAAC, MADDPG, MAMLSAC, MAPPO, MTSAC, SAC
from vafn_sb3.loading import load_model, load_model_or_exit, saved_policy_class

ENV_ID = "VAFN/ThreeArmReach-v1"
TINY = [16]
ON_POLICY = dict(n_steps=64, batch_size=64)

#: (algorithm key, how to build an untrained model, the key load_model must detect). SAC, MTSAC and SB3's SAC save
#: the same policy classes and no keys of their own, so they load as MTSAC (SAC plus fine-tuning), which runs them all;
#: likewise SB3's DDPG is TD3 with other settings and loads as TD3 (as ``ddpg`` from a zoo run's ``ddpg/`` folder).
CASES = [
    ("maml_sac", lambda env: MAMLSAC("SharedAgentPolicy", env, policy_kwargs=dict(net_arch=TINY)), "maml_sac"),
    ("mtsac", lambda env: MTSAC("SharedAgentPolicy", env, policy_kwargs=dict(net_arch=TINY)), "mtsac"),
    ("sac", lambda env: SAC("SharedAgentPolicy", env, policy_kwargs=dict(net_arch=TINY)), "mtsac"),
    ("sb3_sac", lambda env: SB3SAC("MlpPolicy", env, policy_kwargs=dict(net_arch=TINY)), "mtsac"),
    ("maac", lambda env: MAAC(env=env, policy_kwargs=dict(net_arch=dict(pi=TINY, qf=[16]))), "maac"),
    ("maddpg", lambda env: MADDPG(env=env, policy_kwargs=dict(net_arch=TINY)), "maddpg"),
    ("td3", lambda env: TD3("MlpPolicy", env, policy_kwargs=dict(net_arch=TINY)), "td3"),
    # the upstream zoo's ddpg with our shared actor: MADDPG's policy, but not MADDPG's own hyperparameters
    ("ddpg", lambda env: DDPG("SharedAgentPolicy", env, policy_kwargs=dict(net_arch=TINY)), "td3"),
    ("mappo", lambda env: MAPPO(env=env, policy_kwargs=dict(net_arch=TINY), **ON_POLICY), "mappo"),
    ("ppo", lambda env: PPO("MlpPolicy", env, policy_kwargs=dict(net_arch=TINY), **ON_POLICY), "ppo"),
    ("ppo_lstm", lambda env: RecurrentPPO("MlpLstmPolicy", env, policy_kwargs=dict(net_arch=TINY, lstm_hidden_size=8),
                                          **ON_POLICY), "ppo_lstm"),
]


@pytest.fixture(scope="module")
def env():
    environment = gym.make(ENV_ID)
    yield environment
    environment.close()


@pytest.mark.parametrize("key, build, detected", CASES, ids=[case[0] for case in CASES])
def test_a_saved_zip_loads_as_the_algorithm_that_saved_it(key, build, detected, env, tmp_path):
    model = build(env)
    model.save(tmp_path / f"{key}.zip")
    loaded, found = load_model(tmp_path / f"{key}.zip", trust_remote_code=True)
    assert found == detected
    assert isinstance(loaded, type(model)) or (detected == "mtsac" and isinstance(loaded, MTSAC)) or (
        detected == "td3" and type(loaded) is TD3)
    assert type(loaded.policy) is type(model.policy)


@pytest.mark.parametrize("key, build, detected", CASES, ids=[case[0] for case in CASES])
def test_a_saved_zip_loads_without_unpickling_and_acts_as_sb3s_load(key, build, detected, env, tmp_path):
    model = build(env)
    model.save(tmp_path / f"{key}.zip")
    trusted, trusted_key = load_model(tmp_path / f"{key}.zip", trust_remote_code=True)
    with mock.patch("stable_baselines3.common.save_util.json_to_data", side_effect=AssertionError("unpickled")):
        safe, found = load_model(tmp_path / f"{key}.zip")  # SB3's deserialisation is never reached
    assert found == trusted_key == detected and type(safe) is type(trusted) and type(safe.policy) is type(model.policy)
    observations = np.stack([env.observation_space.sample() for _ in range(16)])
    np.testing.assert_array_equal(safe.predict(observations, deterministic=True)[0],
                                  trusted.predict(observations, deterministic=True)[0])
    for name, tensor in trusted.policy.state_dict().items():
        assert th.equal(safe.policy.state_dict()[name], tensor), name


def test_a_zoo_run_folder_names_the_algorithm_among_those_sharing_a_policy(env, tmp_path):
    run = tmp_path / "sac" / "VAFN-ThreeArmReach-v1_1"
    run.mkdir(parents=True)
    SAC("SharedAgentPolicy", env, policy_kwargs=dict(net_arch=TINY)).save(run / "VAFN-ThreeArmReach-v1.zip")
    model, key = load_model(run / "VAFN-ThreeArmReach-v1.zip", trust_remote_code=True)
    assert key == "sac" and type(model) is SAC
    model, key = load_model(run / "VAFN-ThreeArmReach-v1.zip")  # the same choice without unpickling
    assert key == "sac" and type(model) is SAC


def test_an_upstream_zoo_ddpg_run_loads_as_ddpg_not_maddpg(env, tmp_path):
    run = tmp_path / "ddpg" / "VAFN-ThreeArmReach-v1_1"
    run.mkdir(parents=True)
    DDPG("SharedAgentPolicy", env, policy_kwargs=dict(net_arch=TINY)).save(run / "VAFN-ThreeArmReach-v1.zip")
    model, key = load_model(run / "VAFN-ThreeArmReach-v1.zip", trust_remote_code=True)
    assert key == "ddpg" and type(model) is DDPG


def test_a_zoo_run_folder_does_not_override_the_policy_the_file_names(env, tmp_path):
    run = tmp_path / "mtsac" / "VAFN-ThreeArmReach-v1_1"  # a MAAC zip misplaced under another algorithm's folder
    run.mkdir(parents=True)
    MAAC(env=env, policy_kwargs=dict(net_arch=dict(pi=TINY, qf=[16]))).save(run / "VAFN-ThreeArmReach-v1.zip")
    assert load_model(run / "VAFN-ThreeArmReach-v1.zip", trust_remote_code=True)[1] == "maac"


def _data_with_policy(serialized: str, module: str) -> dict:
    return {"policy_class": {":type:": "<class 'abc.ABCMeta'>", ":serialized:": serialized, "__module__": module}}


def test_the_policy_class_is_read_without_unpickling_and_unreadable_ones_are_none():
    by_reference = base64.b64encode(pickle.dumps(PPO.policy_aliases["MlpPolicy"])).decode()
    module = "stable_baselines3.common.policies"
    assert saved_policy_class(_data_with_policy(by_reference, module)) == (module, "ActorCriticPolicy")
    assert saved_policy_class(_data_with_policy(by_reference, "elsewhere")) is None  # the pickle names another module
    assert saved_policy_class(_data_with_policy("not base64!", module)) is None
    assert saved_policy_class(_data_with_policy(base64.b64encode(b"\x80\x05junk").decode(), module)) is None
    assert saved_policy_class({}) is None and saved_policy_class({"policy_class": "MlpPolicy"}) is None


def test_a_zip_naming_no_known_policy_is_still_tried_with_every_algorithm(env, tmp_path):
    path = tmp_path / "ppo.zip"
    PPO("MlpPolicy", env, policy_kwargs=dict(net_arch=TINY), **ON_POLICY).save(path)
    with zipfile.ZipFile(path) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(entries["data"])
    data["policy_class"][":serialized:"] = base64.b64encode(b"\x80\x05junk").decode()
    entries["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(path, "w") as archive:
        for name, content in entries.items():
            archive.writestr(name, content)
    with pytest.raises(ValueError, match="could not load .* with any algorithm") as error:
        load_model(path, trust_remote_code=True)  # every candidate fails on the broken class; the error lists them all
    assert all(f"{key}: " in str(error.value) for key in ("mtsac", "sac", "maac", "maddpg", "mappo", "td3", "ppo"))


def test_a_command_line_tool_stops_in_one_line_naming_the_file(tmp_path):
    broken = tmp_path / "broken.zip"
    broken.write_text("not a model")
    with pytest.raises(SystemExit, match=r"^--method m: .*broken.zip"):
        load_model_or_exit(broken, None, "--method m: ")
    with pytest.raises(SystemExit, match="no model file at"):
        load_model_or_exit(tmp_path / "missing.zip")
