"""The one list of algorithms: key -> class, what each supports, and the policy aliases we lend to stock SB3.

:mod:`vafn_sb3.common.serialization` (weights-only files), :mod:`vafn_sb3.loading` (``load_model``),
:mod:`vafn_sb3.aliases` (stock SB3 tables for the upstream RL Zoo) and ``zoo/registry.py`` (rl_zoo3's tables) all read
:data:`ALGORITHMS`; none keeps a list of its own.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from stable_baselines3 import DDPG, PPO, TD3
from stable_baselines3 import SAC as SB3SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy

from vafn_sb3.maac import MAAC
from vafn_sb3.maddpg import MADDPG, MADDPGPolicy
from vafn_sb3.maml_sac import MAMLSAC
from vafn_sb3.mappo import MAPPO
from vafn_sb3.mtsac import MTSAC
from vafn_sb3.sac import SAC, SharedAgentPolicy

__all__ = ["ALGORITHMS", "STOCK_POLICY_ALIASES", "Algorithm", "algorithm", "algorithm_keys", "weights_classes",
           "zoo_algorithms"]


@dataclass(frozen=True)
class Algorithm:
    """One algorithm a model file or the zoo may name."""

    #: Key on command lines, in ``load_model`` and in the zoo's ``--algo``.
    key: str
    cls: type[BaseAlgorithm]
    #: Stock SB3 family (the zoo's hyperparameter search space).
    family: type[BaseAlgorithm]
    #: Registered in rl_zoo3's ``ALGOS`` by ``zoo/registry.py`` (the vafn algorithms).
    zoo: bool = False
    #: ``save_weights`` / ``load_weights`` support it (stored under the class name).
    weights: bool = False
    #: Hyperparameters only this algorithm saves in an SB3 zip: a zip that has them all is this algorithm's.
    saved_keys: frozenset[str] = frozenset()

    def policy_classes(self) -> set[tuple[str, str]]:
        """``(module, class name)`` of every policy the class accepts by alias."""
        return {(policy.__module__, policy.__qualname__) for policy in self.cls.policy_aliases.values()}


def _optional() -> tuple[Algorithm, ...]:
    """Algorithms of optional packages: sb3-contrib's RecurrentPPO (the zoo's ``ppo_lstm``, the ``[zoo]`` extra)."""
    try:
        from sb3_contrib import RecurrentPPO
    except ImportError:
        return ()
    return (Algorithm("ppo_lstm", RecurrentPPO, PPO),)


#: Every algorithm by key, most specific first (vafn classes before SB3's, ``load_model`` tries them in this order).
#: ``sac`` is SB3's SAC plus the shared per-arm actor alias (it reads SB3 SAC files too); ``sb3_sac`` is stock SAC.
#: ``ddpg``: SB3's DDPG (TD3 with one critic update per actor update), which the upstream zoo trains with our
#: ``SharedAgentPolicy``; its zips lack MADDPG's own hyperparameters, so they never load as ``maddpg``.
ALGORITHMS: dict[str, Algorithm] = {
    entry.key: entry
    for entry in (
        Algorithm("maml_sac", MAMLSAC, SB3SAC, zoo=True, weights=True,
                  saved_keys=frozenset({"inner_steps", "meta_batch_size", "n_support", "n_query"})),
        Algorithm("mtsac", MTSAC, SB3SAC, zoo=True, weights=True),
        Algorithm("sac", SAC, SB3SAC, zoo=True, weights=True),
        Algorithm("maac", MAAC, SB3SAC, zoo=True, weights=True),
        Algorithm("maddpg", MADDPG, TD3, zoo=True, weights=True,
                  saved_keys=frozenset({"action_reg", "exploration_std", "max_grad_norm"})),
        Algorithm("mappo", MAPPO, PPO, zoo=True, weights=True),
        Algorithm("sb3_sac", SB3SAC, SB3SAC),
        Algorithm("td3", TD3, TD3, weights=True),
        Algorithm("ddpg", DDPG, TD3),
        Algorithm("ppo", PPO, PPO, weights=True),
        *_optional(),
    )
}

#: Stock SB3 algorithm -> the aliases of our policies it gains (``vafn_sb3.aliases``; DDPG inherits TD3's table):
#: SAC trains the shared per-arm actor, TD3/DDPG MADDPG's parameter-shared deterministic actor and centralised critic.
STOCK_POLICY_ALIASES: dict[type[BaseAlgorithm], dict[str, type[BasePolicy]]] = {
    SB3SAC: {"SharedAgentPolicy": SharedAgentPolicy},
    TD3: {"SharedAgentPolicy": MADDPGPolicy},
}


def algorithm(key: str) -> Algorithm:
    """The algorithm of ``key`` (``ValueError`` listing the keys when unknown)."""
    if key not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {key!r}; choose one of {sorted(ALGORITHMS)}")
    return ALGORITHMS[key]


def algorithm_keys() -> list[str]:
    """Every key, in :data:`ALGORITHMS` order."""
    return list(ALGORITHMS)


def zoo_algorithms() -> Iterator[Algorithm]:
    """The algorithms ``zoo/registry.py`` registers in rl_zoo3."""
    return (entry for entry in ALGORITHMS.values() if entry.zoo)


def weights_classes() -> dict[str, type[BaseAlgorithm]]:
    """Class name -> class of the algorithms weights-only files support (a file names its class)."""
    return {entry.cls.__name__: entry.cls for entry in ALGORITHMS.values() if entry.weights}
