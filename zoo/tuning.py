"""Optuna search spaces for every vafn algorithm, in rl_zoo3's sampler/converter format.

A *sampler* ``(trial, n_actions, n_envs, additional_args) -> hyperparams`` suggests raw values and converts them; the
matching *converter* turns the stored ``trial.params`` back into hyperparams (``--trial-id``). Ranges are narrower than
the zoo's generic ones: they cover what is sensible for the 15-D / 9-D three-arm task on a small CPU budget.

Sampled ``policy_kwargs`` are *merged into* the YAML's ``policy_kwargs`` by :mod:`zoo.experiment` (the zoo replaces
them), so a YAML ``activation_fn`` or custom policy argument survives tuning.
"""

from __future__ import annotations

import inspect
from typing import Any, Callable

import optuna
from torch import nn

Sampler = Callable[[optuna.Trial, int, int, dict], dict[str, Any]]

#: Named network sizes a trial can pick (shared by actor and critic).
NET_ARCHS: dict[str, Any] = {"small": [64, 64], "medium": [256, 256], "large": [400, 300]}
#: MAAC's attention critic takes a single hidden width (``qf=[w]``), so it has its own table.
MAAC_NET_ARCHS: dict[str, Any] = {
    "small": {"pi": [64, 64], "qf": [64]},
    "medium": {"pi": [128, 128], "qf": [128]},
    "large": {"pi": [256, 256], "qf": [256]},
}
NET_ARCHS_BY_ALGO: dict[str, dict[str, Any]] = {"maac": MAAC_NET_ARCHS}
ACTIVATIONS: dict[str, type[nn.Module]] = {"tanh": nn.Tanh, "relu": nn.ReLU}

#: Algorithm-specific constructor arguments tuned when the class accepts them: name -> (kind, low/choices, high, log).
#: The class signature decides, so a renamed argument is simply not tuned instead of crashing every trial.
EXTRA_SPACES: dict[str, dict[str, tuple]] = {
    "maml_sac": {
        "inner_actor_lr": ("float", 1e-3, 1e-1, True),
        "inner_critic_lr": ("float", 1e-3, 5e-2, True),
        "inner_steps": ("int", 1, 3, False),
        "meta_batch_size": ("categorical", [3, 5]),
        "n_support": ("categorical", [100, 200]),
    },
    "maddpg": {"exploration_std": ("float", 0.05, 0.4, False)},
    "maac": {"attention_reg": ("float", 1e-4, 1e-2, True)},
}


def _constructor_parameters(algo_class: type | None) -> set[str]:
    if algo_class is None:
        return set()
    return set(inspect.signature(algo_class.__init__).parameters)


def _suggest_extras(trial: optuna.Trial, algo: str, algo_class: type | None) -> dict[str, Any]:
    accepted = _constructor_parameters(algo_class)
    params: dict[str, Any] = {}
    for name, space in EXTRA_SPACES.get(algo, {}).items():
        if name not in accepted:
            continue
        kind = space[0]
        if kind == "float":
            params[name] = trial.suggest_float(name, space[1], space[2], log=space[3])
        elif kind == "int":
            params[name] = trial.suggest_int(name, space[1], space[2], log=space[3])
        else:
            params[name] = trial.suggest_categorical(name, space[1])
    return params


def convert_params(params: dict[str, Any], net_archs: dict[str, Any] | None = None) -> dict[str, Any]:
    """Stored trial params -> constructor hyperparams (``one_minus_*`` -> value, ``net_arch`` name -> policy_kwargs).

    :param params: the trial's parameters as stored by Optuna.
    :param net_archs: the algorithm's table of named network sizes (default :data:`NET_ARCHS`).
    """
    hyperparams = dict(params)
    for name in ("gamma", "gae_lambda"):
        if f"one_minus_{name}" in hyperparams:
            hyperparams[name] = 1.0 - hyperparams.pop(f"one_minus_{name}")
    policy_kwargs: dict[str, Any] = {}
    if "net_arch" in hyperparams:
        policy_kwargs["net_arch"] = (net_archs or NET_ARCHS)[hyperparams.pop("net_arch")]
    if "activation_fn" in hyperparams:
        policy_kwargs["activation_fn"] = ACTIVATIONS[hyperparams.pop("activation_fn")]
    if policy_kwargs:
        hyperparams["policy_kwargs"] = policy_kwargs
    return hyperparams


def _suggest_off_policy(trial: optuna.Trial) -> dict[str, Any]:
    return {
        "learning_rate": trial.suggest_float("learning_rate", 1e-4, 3e-3, log=True),
        "one_minus_gamma": trial.suggest_float("one_minus_gamma", 0.002, 0.05, log=True),
        "batch_size": trial.suggest_categorical("batch_size", [64, 128, 256]),
        "tau": trial.suggest_float("tau", 0.002, 0.05, log=True),
        "net_arch": trial.suggest_categorical("net_arch", ["small", "medium"]),
    }


def make_converter(algo: str) -> Callable[[dict[str, Any]], dict[str, Any]]:
    """The ``--trial-id`` converter of ``algo`` (its own network-size table)."""

    def convert(params: dict[str, Any]) -> dict[str, Any]:
        return convert_params(params, NET_ARCHS_BY_ALGO.get(algo))

    return convert


def make_off_policy_sampler(algo: str, algo_class: type | None) -> Sampler:
    """Sampler for SAC and TD3 subclasses (sac, maml_sac, mtsac, maac, maddpg): common space + the algo's extras."""
    convert = make_converter(algo)

    def sample(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
        params = _suggest_off_policy(trial)
        params["learning_starts"] = trial.suggest_categorical("learning_starts", [100, 500, 1000])
        params.update(_suggest_extras(trial, algo, algo_class))
        return convert(params)

    return sample


def make_ppo_sampler(algo: str, algo_class: type | None) -> Sampler:
    """Sampler for PPO subclasses (mappo)."""
    convert = make_converter(algo)

    def sample(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
        params = {
            "learning_rate": trial.suggest_float("learning_rate", 5e-5, 3e-3, log=True),
            "one_minus_gamma": trial.suggest_float("one_minus_gamma", 0.002, 0.05, log=True),
            "one_minus_gae_lambda": trial.suggest_float("one_minus_gae_lambda", 0.01, 0.1, log=True),
            "n_steps": trial.suggest_categorical("n_steps", [256, 512, 1024, 2048]),
            "batch_size": trial.suggest_categorical("batch_size", [64, 128, 256]),
            "n_epochs": trial.suggest_categorical("n_epochs", [5, 10, 20]),
            "ent_coef": trial.suggest_float("ent_coef", 1e-8, 1e-2, log=True),
            "clip_range": trial.suggest_categorical("clip_range", [0.1, 0.2, 0.3]),
            "net_arch": trial.suggest_categorical("net_arch", ["small", "medium"]),
            "activation_fn": trial.suggest_categorical("activation_fn", ["tanh", "relu"]),
        }
        params.update(_suggest_extras(trial, algo, algo_class))
        return convert(params)

    return sample
