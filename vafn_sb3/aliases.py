"""vafn's shared per-arm policies as aliases of the stock SB3 algorithms, so the upstream RL Zoo trains them.

``python -m rl_zoo3.train --algo sac --gym-packages vafn_sb3 --conf-file hyperparams/sac.yml ...`` builds stock
``stable_baselines3.SAC`` with the YAML's ``policy: 'SharedAgentPolicy'``; SB3 looks that name up in
``SAC.policy_aliases``. Importing :mod:`vafn_sb3` calls :func:`register_stock_aliases`, which adds our names to those
tables in place: no stock name is replaced, nothing of SB3 or rl_zoo3 is copied, and calling it again changes nothing.
``vafn_gym`` stays torch-free, so it registers no policy: name ``vafn_sb3`` in ``--gym-packages`` (it also imports
``vafn_gym``, which registers the ``VAFN/*`` env IDs).

Only stock algorithms whose training loop runs our policy as designed get an alias: ``SAC`` (hence the zoo's ``sac``)
and ``TD3`` (whose table ``DDPG`` inherits), with the parameter-shared deterministic actor and centralised critic of
MADDPG trained by TD3's/DDPG's own update. Not ``PPO``: ``MAPPOPolicy``'s value normalisation is updated only by
``MAPPO.train``. See docs/zoo.md, "The upstream RL Zoo".
"""

from __future__ import annotations

import warnings

from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy

import vafn_gym  # noqa: F401  (registers the VAFN/* env IDs: `--gym-packages vafn_sb3` is enough)
from vafn_sb3.registry import STOCK_POLICY_ALIASES

#: Stock algorithm class -> the aliases it gains (DDPG inherits TD3's ``policy_aliases`` dict, so it gains them too):
#: the registry's :data:`~vafn_sb3.registry.STOCK_POLICY_ALIASES`.
STOCK_ALIASES: dict[type[BaseAlgorithm], dict[str, type[BasePolicy]]] = STOCK_POLICY_ALIASES


def register_stock_aliases() -> list[str]:
    """Add :data:`STOCK_ALIASES` to the stock ``policy_aliases`` tables; returns the ``Algo.alias`` names added now.

    A name the table already maps to another class is left alone, with a warning (nothing stock is overwritten).
    """
    added = []
    for algo, aliases in STOCK_ALIASES.items():
        table = vars(algo)["policy_aliases"]  # the class's own dict, never one it inherits
        for name, policy in aliases.items():
            if name not in table:
                table[name] = policy
                added.append(f"{algo.__name__}.{name}")
            elif table[name] is not policy:
                warnings.warn(f"{algo.__name__}.policy_aliases[{name!r}] is already {table[name].__qualname__}; "
                              f"vafn's {policy.__qualname__} is not registered under that name", RuntimeWarning,
                              stacklevel=2)
    return added
