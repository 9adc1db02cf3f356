"""Registers the vafn algorithms and their Optuna samplers in rl_zoo3's dictionaries (the zoo's documented SBX pattern).

``rl_zoo3.train``, ``exp_manager``, ``enjoy`` and ``record_video`` all read the *same* dict objects, so updating them
in place before the zoo parses its arguments is enough; nothing of rl_zoo3 is copied or forked.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
from rl_zoo3.utils import ALGOS
from stable_baselines3 import PPO, SAC, TD3

from zoo.tuning import Sampler, make_converter, make_off_policy_sampler, make_ppo_sampler


@dataclass(frozen=True)
class AlgoSpec:
    """Where a vafn algorithm lives and which SB3 family (and so which search space) it belongs to."""

    key: str
    class_name: str
    family: type


#: Every algorithm the zoo knows, by zoo key. ``sac`` is SB3's SAC with the shared per-arm actor alias (vafn_sb3.SAC).
VAFN_ALGOS: dict[str, AlgoSpec] = {
    spec.key: spec
    for spec in (
        AlgoSpec("sac", "SAC", SAC),
        AlgoSpec("maml_sac", "MAMLSAC", SAC),
        AlgoSpec("mtsac", "MTSAC", SAC),
        AlgoSpec("maac", "MAAC", SAC),
        AlgoSpec("mappo", "MAPPO", PPO),
        AlgoSpec("maddpg", "MADDPG", TD3),
    )
}
SAMPLER_FACTORIES = {SAC: make_off_policy_sampler, PPO: make_ppo_sampler, TD3: make_off_policy_sampler}

#: algo key -> why it could not be registered (filled by :func:`register_algorithms`).
UNAVAILABLE: dict[str, str] = {}


def _load_class(spec: AlgoSpec) -> type:
    try:
        module = importlib.import_module("vafn_sb3")
    except Exception as error:  # an import error anywhere in vafn_sb3 makes every algorithm unavailable
        raise LookupError(f"importing vafn_sb3 failed: {type(error).__name__}: {error}") from error
    algo_class = getattr(module, spec.class_name, None)
    if algo_class is None:
        raise LookupError(f"vafn_sb3 does not export {spec.class_name} (not implemented yet?)")
    if not issubclass(algo_class, spec.family):
        raise LookupError(f"vafn_sb3.{spec.class_name} is not a {spec.family.__name__} subclass")
    return algo_class


def _register(key: str, algo_class: type, sampler: Sampler) -> None:
    ALGOS[key] = algo_class
    HYPERPARAMS_SAMPLER[key] = sampler
    HYPERPARAMS_CONVERTER[key] = make_converter(key)


def register_algorithms() -> list[str]:
    """Register every importable vafn algorithm; returns the registered keys (missing ones: UNAVAILABLE)."""
    registered = []
    UNAVAILABLE.clear()
    for key, spec in VAFN_ALGOS.items():
        try:
            algo_class = _load_class(spec)
        except LookupError as error:
            UNAVAILABLE[key] = str(error)
            continue
        _register(key, algo_class, SAMPLER_FACTORIES[spec.family](key, algo_class))
        registered.append(key)
    return registered


def require_algorithm(key: str) -> type:
    """The registered class of ``key``, or a clear error saying why a vafn algorithm is missing."""
    if key in UNAVAILABLE:
        raise SystemExit(f"algorithm {key!r} is not available: {UNAVAILABLE[key]}")
    if key not in ALGOS:
        raise SystemExit(f"unknown algorithm {key!r}; choose one of {sorted(ALGOS)}")
    return ALGOS[key]
