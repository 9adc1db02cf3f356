"""Safe loading of rl_zoo3 run YAML: the tags the zoo writes load, any other Python tag is refused without running."""

from __future__ import annotations

import contextlib
from collections import OrderedDict
from pathlib import Path

import pytest
import torch
import yaml

from zoo.run_config import load_run_config, load_run_yaml


def _zoo_config() -> OrderedDict:
    """What ExperimentManager._save_config dumps: a sorted OrderedDict with tuples and classes in it."""
    hyperparams = {
        "env_kwargs": {"n_arms": 3, "reward_scale": 0.5},
        "n_timesteps": 1000.0,
        "policy": "MlpPolicy",
        "policy_kwargs": "dict(net_arch=[256, 256])",
        "train_freq": (1, "episode"),
        "tuned_policy_kwargs": {"net_arch": [64], "activation_fn": torch.nn.ReLU, "optimizer_class": torch.optim.Adam},
        "normalize": False,
        "learning_starts": None,
    }
    return OrderedDict([(key, hyperparams[key]) for key in sorted(hyperparams)])


def test_a_zoo_config_round_trips(tmp_path: Path) -> None:
    config = _zoo_config()
    path = tmp_path / "config.yml"
    path.write_text(yaml.dump(config))
    loaded = load_run_config(path)
    assert loaded == config and list(loaded) == list(config)
    assert loaded["train_freq"] == (1, "episode")
    assert loaded["tuned_policy_kwargs"]["activation_fn"] is torch.nn.ReLU
    assert loaded["tuned_policy_kwargs"]["optimizer_class"] is torch.optim.Adam


def test_args_yml_loads() -> None:
    args = OrderedDict([("algo", "sac"), ("env_kwargs", None), ("hyperparams", {"gamma": 0.99}), ("seed", 3)])
    assert load_run_yaml(yaml.dump(args)) == args


def test_an_empty_config_is_an_empty_dict(tmp_path: Path) -> None:
    (tmp_path / "config.yml").write_text("")
    assert load_run_config(tmp_path / "config.yml") == {}


@pytest.mark.parametrize(
    "payload",
    [
        "!!python/object/apply:os.system [{cmd}]",
        "!!python/object/apply:subprocess.check_call [[sh, -c, {cmd}]]",
        "!!python/object/apply:subprocess.run [[sh, -c, {cmd}]]",
        "env_kwargs: !!python/object/apply:collections.OrderedDict [!!python/object/apply:os.system [{cmd}]]",
    ],
)
def test_a_crafted_config_does_not_run_code(tmp_path: Path, payload: str) -> None:
    marker = tmp_path / "pwned"
    path = tmp_path / "config.yml"
    path.write_text(payload.format(cmd=f"'touch {marker}'"))
    with pytest.raises(yaml.YAMLError):
        load_run_config(path)
    assert not marker.exists()
    # The same file really is an exploit under the loader the zoo used before.
    with contextlib.suppress(Exception):
        yaml.load(path.read_text(), Loader=yaml.UnsafeLoader)
    assert marker.exists()


@pytest.mark.parametrize(
    "name",
    [
        "os.system",
        "builtins.eval",
        "subprocess.Popen",
        "torch.load",
        "torch.nn.modules.activation.F",  # a module, not a class
        "torch.optim.sgd.sgd",  # a function, not a class
    ],
)
def test_only_allow_listed_classes_can_be_named(name: str) -> None:
    with pytest.raises(yaml.YAMLError):
        load_run_yaml(f"activation_fn: !!python/name:{name} ''")


def test_a_module_tag_is_refused() -> None:
    with pytest.raises(yaml.YAMLError):
        load_run_yaml("m: !!python/module:os")
