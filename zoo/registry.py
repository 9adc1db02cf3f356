"""Registers the vafn algorithms and their Optuna samplers in rl_zoo3's dictionaries (the zoo's documented SBX pattern).

``rl_zoo3.train``, ``exp_manager``, ``enjoy`` and ``record_video`` all read the *same* dict objects, so updating them
in place before the zoo parses its arguments is enough; nothing of rl_zoo3 is copied or forked.
"""

from __future__ import annotations

from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
from rl_zoo3.utils import ALGOS
from stable_baselines3 import PPO, SAC, TD3

from vafn_sb3.registry import Algorithm, zoo_algorithms
from zoo.tuning import Sampler, make_converter, make_off_policy_sampler, make_ppo_sampler

#: Every vafn algorithm the zoo registers, by zoo key (:func:`vafn_sb3.registry.zoo_algorithms`). ``sac`` is SB3's SAC
#: with the shared per-arm actor alias (vafn_sb3.SAC).
VAFN_ALGOS: dict[str, Algorithm] = {entry.key: entry for entry in zoo_algorithms()}
SAMPLER_FACTORIES = {SAC: make_off_policy_sampler, PPO: make_ppo_sampler, TD3: make_off_policy_sampler}

#: algo key -> why it could not be registered (filled by :func:`register_algorithms`).
UNAVAILABLE: dict[str, str] = {}


def _load_class(entry: Algorithm) -> type:
    if entry.family not in SAMPLER_FACTORIES or not issubclass(entry.cls, entry.family):
        raise LookupError(f"{entry.cls.__qualname__} is not a {entry.family.__name__} subclass of a zoo family")
    return entry.cls


def _register(key: str, algo_class: type, sampler: Sampler) -> None:
    ALGOS[key] = algo_class
    HYPERPARAMS_SAMPLER[key] = sampler
    HYPERPARAMS_CONVERTER[key] = make_converter(key)


def register_algorithms() -> list[str]:
    """Register every importable vafn algorithm; returns the registered keys (missing ones: UNAVAILABLE)."""
    registered = []
    UNAVAILABLE.clear()
    for key, entry in VAFN_ALGOS.items():
        try:
            algo_class = _load_class(entry)
        except LookupError as error:
            UNAVAILABLE[key] = str(error)
            continue
        _register(key, algo_class, SAMPLER_FACTORIES[entry.family](key, algo_class))
        registered.append(key)
    return registered


def require_algorithm(key: str) -> type:
    """The registered class of ``key``, or a clear error saying why a vafn algorithm is missing."""
    if key in UNAVAILABLE:
        raise SystemExit(f"algorithm {key!r} is not available: {UNAVAILABLE[key]}")
    if key not in ALGOS:
        raise SystemExit(f"unknown algorithm {key!r}; choose one of {sorted(ALGOS)}")
    return ALGOS[key]
