"""Model files: atomic saves, clear errors for broken zips, and a weights-only format that never unpickles."""

import io
import json
import os
import pickle
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import A2C, SAC
from stable_baselines3.common import base_class
from torch import nn

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_sb3.common.serialization import (
    CONFIG_ENTRY,
    POLICY_ENTRY,
    VARIABLES_ENTRY,
    atomic_write,
    load_weights,
    save_weights,
)
from vafn_sb3.maac import MAAC
from vafn_sb3.maddpg import MADDPG
from vafn_sb3.maml_sac import MAMLSAC
from vafn_sb3.mappo import MAPPO
from vafn_sb3.mtsac import MTSAC

ENV_ID = "VAFN/ThreeArmReach-v1"
TINY = [16]
SEED = 0

#: Untrained models of every algorithm the weights format supports (predictions depend on the weights only).
MODELS = {
    "SAC": lambda env: SAC("MlpPolicy", env, policy_kwargs=dict(net_arch=TINY), seed=SEED),
    "MAAC": lambda env: MAAC(env=env, policy_kwargs=dict(net_arch=dict(pi=TINY, qf=[16]), agent_ids=False), seed=SEED),
    "MADDPG": lambda env: MADDPG(env=env, policy_kwargs=dict(net_arch=TINY), seed=SEED),
    "MAPPO": lambda env: MAPPO(env=env, n_steps=64, policy_kwargs=dict(net_arch=TINY), seed=SEED),
    "MTSAC": lambda env: MTSAC(
        "SharedAgentPolicy", env, policy_kwargs=dict(net_arch=TINY, activation_fn=nn.Tanh), ent_coef="auto_0.1",
        seed=SEED,
    ),
    "MAMLSAC": lambda env: MAMLSAC("MlpPolicy", env, policy_kwargs=dict(net_arch=TINY), seed=SEED),
}
VAFN_ALGORITHMS = [name for name in MODELS if name != "SAC"]


@pytest.fixture(scope="module")
def env():
    env = gym.make(ENV_ID)
    yield env
    env.close()


def observations(env):
    return np.stack([env.reset(seed=seed)[0] for seed in range(4)])


def perturb(model):
    with th.no_grad():
        for parameter in model.policy.parameters():
            parameter.add_(0.5)


def rewrite_entry(path, entry, content):
    with zipfile.ZipFile(path) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    entries[entry] = content
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in entries.items():
            archive.writestr(name, data)


# --- atomic writes ---------------------------------------------------------------------------------------------------


def test_atomic_write_replaces_the_file_or_keeps_the_old_one(tmp_path):
    target = tmp_path / "file.bin"
    atomic_write(target, lambda tmp: tmp.write_bytes(b"old"))

    def fail_half_way(tmp):
        tmp.write_bytes(b"ne")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, fail_half_way)
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["file.bin"]
    atomic_write(target, lambda tmp: tmp.write_bytes(b"new"))
    assert target.read_bytes() == b"new" and os.listdir(tmp_path) == ["file.bin"]


def test_csv_rows_take_every_column_and_fill_the_missing_ones(tmp_path):
    import csv

    from vafn_gym.files import write_csv_rows

    path = write_csv_rows([{"a": 1, "b": 2}, {"a": 3, "c": 4}], tmp_path / "sub" / "rows.csv", missing="nan")
    assert list(csv.DictReader(path.open())) == [{"a": "1", "b": "2", "c": "nan"}, {"a": "3", "b": "nan", "c": "4"}]
    with pytest.raises(ValueError, match="no rows"):
        write_csv_rows([], tmp_path / "empty.csv")
    assert not (tmp_path / "empty.csv").exists()


@pytest.mark.parametrize("name", VAFN_ALGORITHMS)
def test_a_save_that_fails_half_way_keeps_the_previous_model(name, env, tmp_path, monkeypatch):
    model = MODELS[name](env)
    model.save(tmp_path / "model")
    obs = observations(env)
    before = model.predict(obs, deterministic=True)[0]
    perturb(model)
    original = base_class.save_to_zip_file

    def crash_half_way(save_path, *args, **kwargs):
        buffer = io.BytesIO()
        original(buffer, *args, **kwargs)
        Path(save_path).write_bytes(buffer.getvalue()[: len(buffer.getvalue()) // 2])
        raise OSError("disk full")

    monkeypatch.setattr(base_class, "save_to_zip_file", crash_half_way)
    with pytest.raises(OSError, match="disk full"):
        model.save(tmp_path / "model")
    monkeypatch.undo()
    assert os.listdir(tmp_path) == ["model.zip"]
    loaded = type(model).load(tmp_path / "model", env=env)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], before)


@pytest.mark.parametrize("name", VAFN_ALGORITHMS)
def test_truncated_or_incomplete_model_zips_raise_value_error_naming_the_file(name, env, tmp_path):
    model = MODELS[name](env)
    model.save(tmp_path / "model.zip")
    data = (tmp_path / "model.zip").read_bytes()
    (tmp_path / "truncated.zip").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="truncated.zip"):
        type(model).load(tmp_path / "truncated.zip")
    with zipfile.ZipFile(tmp_path / "model.zip") as source, zipfile.ZipFile(tmp_path / "no_data.zip", "w") as target:
        for entry in source.namelist():
            if entry != "data":
                target.writestr(entry, source.read(entry))
    with pytest.raises(ValueError, match=r"no_data.zip is incomplete: no data entry"):
        type(model).load(tmp_path / "no_data")


# --- weights-only files ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(MODELS))
def test_weights_round_trip_gives_identical_predictions(name, env, tmp_path):
    model = MODELS[name](env)
    perturb(model)  # not the seed's initialisation
    path = save_weights(model, tmp_path / "weights.zip")
    with zipfile.ZipFile(path) as archive:
        assert sorted(archive.namelist()) == sorted([CONFIG_ENTRY, POLICY_ENTRY, VARIABLES_ENTRY])
        config = json.loads(archive.read(CONFIG_ENTRY))
    assert config["algorithm"] == name and config["observation_space"]["shape"] == list(env.observation_space.shape)
    obs = observations(env)
    expected = model.predict(obs, deterministic=True)[0]
    for loaded in (load_weights(path), load_weights(path, env=env)):
        # SB3 SAC loads as vafn's SAC
        assert isinstance(loaded, type(model)) and loaded.policy_kwargs == model.policy_kwargs
        np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], expected)
        for key, value in model.policy.state_dict().items():
            assert th.equal(loaded.policy.state_dict()[key], value), key
        for variable in model._get_torch_save_params()[1]:
            assert th.equal(getattr(loaded, variable), getattr(model, variable)), variable


def test_weights_keep_the_layout_keywords_and_hyperparameters(env, tmp_path):
    model = MAPPO(env=env, n_steps=32, num_mini_batch=2, huber_delta=3.0,
                  policy_kwargs=dict(net_arch=TINY, agent_ids=False, activation_fn=nn.Tanh))
    loaded = load_weights(save_weights(model, tmp_path / "mappo.zip"))
    assert loaded.policy_kwargs == dict(net_arch=TINY, agent_ids=False, activation_fn=nn.Tanh)
    assert (loaded.n_steps, loaded.batch_size, loaded.huber_delta) == (32, 16, 3.0)
    assert loaded.policy.agent_ids is False
    assert loaded.clip_range(1.0) == model.clip_range(1.0)


class _Payload:
    """Creates a directory when unpickled: the proof that a file ran code."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return os.mkdir, (self.marker,)


def test_crafted_weights_files_are_refused_without_running_code(env, tmp_path):
    marker = tmp_path / "code-ran"
    path = save_weights(MODELS["SAC"](env), tmp_path / "weights.zip")
    torch_payload = io.BytesIO()
    th.save({"actor.latent_pi.0.weight": _Payload(marker)}, torch_payload)
    for entry, content in (
        (POLICY_ENTRY, torch_payload.getvalue()),
        (POLICY_ENTRY, pickle.dumps(_Payload(marker))),
        (VARIABLES_ENTRY, pickle.dumps({"log_ent_coef": _Payload(marker)})),
    ):
        crafted = tmp_path / "crafted.zip"
        crafted.write_bytes(path.read_bytes())
        rewrite_entry(crafted, entry, content)
        with pytest.raises(ValueError, match="refused without unpickling"):
            load_weights(crafted)
        assert not marker.exists()
    pickle.loads(pickle.dumps(_Payload(marker)))  # the payload is live: plain unpickling runs it
    assert marker.exists()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda config: config.update(algorithm="os.system"), "unknown algorithm"),
        (lambda config: config.update(policy="builtins.eval"), "no policy alias"),
        (lambda config: config["policy_kwargs"].update(activation_fn="Module"), "not a Module class"),
        (lambda config: config["policy_kwargs"].update(optimizer_class="__builtins__"), "not a Optimizer class"),
        (lambda config: config["hyperparameters"].update(__class__="SAC"), "unknown SAC hyperparameters"),
        (lambda config: config["observation_space"].update(dtype="object"), "float Box space"),
        (lambda config: config.update(format="sb3"), "not a vafn-weights config"),
    ],
)
def test_weights_configs_outside_the_allow_lists_are_refused(env, tmp_path, change, message):
    path = save_weights(MODELS["SAC"](env), tmp_path / "weights.zip")
    with zipfile.ZipFile(path) as archive:
        config = json.loads(archive.read(CONFIG_ENTRY))
    change(config)
    rewrite_entry(path, CONFIG_ENTRY, json.dumps(config))
    with pytest.raises(ValueError, match=message):
        load_weights(path)


def test_non_weights_files_and_non_json_models_are_refused(env, tmp_path):
    sac = MODELS["SAC"](env)
    sac.save(tmp_path / "sb3.zip")
    with pytest.raises(ValueError, match="not a weights file.*SB3 model zip"):
        load_weights(tmp_path / "sb3.zip")
    path = save_weights(sac, tmp_path / "weights.zip")
    rewrite_entry(path, CONFIG_ENTRY, b"\x80not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_weights(path)
    (tmp_path / "half.zip").write_bytes(save_weights(sac, tmp_path / "w.zip").read_bytes()[:200])
    with pytest.raises(ValueError, match="half.zip"):
        load_weights(tmp_path / "half.zip")

    class CustomReLU(nn.ReLU):
        pass

    with pytest.raises(ValueError, match="activation_fn"):
        save_weights(SAC("MlpPolicy", env, policy_kwargs=dict(activation_fn=CustomReLU)), tmp_path / "custom.zip")
    with pytest.raises(ValueError, match="weights files support"):
        save_weights(A2C("MlpPolicy", env), tmp_path / "a2c.zip")
    assert sorted(os.listdir(tmp_path)) == ["half.zip", "sb3.zip", "w.zip", "weights.zip"]
    other = gym.make("VAFN/MultiArmReach-v1", n_arms=4)
    with pytest.raises(ValueError, match="[Oo]bservation spaces do not match"):
        load_weights(tmp_path / "w.zip", env=other)
    other.close()
