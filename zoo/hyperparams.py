"""Read one algorithm's hyperparameters for one env from ``hyperparams/<algo>.yml``, as rl_zoo3 reads them.

Scripts outside the zoo (the learning benchmark, the pretrained-policy builder) use this so that the YAML files stay
the one source of every training setting.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from torch import nn

HYPERPARAMS_DIR = Path(__file__).resolve().parents[1] / "hyperparams"
#: Keys rl_zoo3 consumes itself (not constructor arguments of the algorithm).
ZOO_ONLY_KEYS = (
    "n_timesteps", "n_envs", "normalize", "env_wrapper", "callback", "frame_stack", "policy", "env_kwargs"
)
#: Names a ``policy_kwargs`` string may use (rl_zoo3 evaluates these strings; here only these names exist).
POLICY_KWARGS_NAMES = {"dict": dict, "nn": nn, "True": True, "False": False, "None": None}


def load_entry(algo: str, env_id: str) -> dict[str, Any]:
    """The raw YAML entry of ``algo`` on ``env_id`` in ``hyperparams/<algo>.yml`` (``ValueError`` if none)."""
    path = HYPERPARAMS_DIR / f"{algo}.yml"
    if not path.is_file():
        raise ValueError(
            f"no hyperparameter file {path.name}; known: {sorted(p.stem for p in HYPERPARAMS_DIR.glob('*.yml'))}"
        )
    table = yaml.safe_load(path.read_text()) or {}
    if env_id not in table:
        raise ValueError(f"{path.name} has no entry for {env_id!r}; entries: {sorted(k for k in table if '/' in k)}")
    return dict(table[env_id])


def load_hyperparams(algo: str, env_id: str) -> tuple[dict[str, Any], int, str]:
    """``(constructor kwargs, n_timesteps, policy)`` of ``algo`` on ``env_id`` from ``hyperparams/<algo>.yml``."""
    params = load_entry(algo, env_id)
    n_timesteps, policy = int(float(params.get("n_timesteps", 0))), params.get("policy", "MlpPolicy")
    kwargs = {key: value for key, value in params.items() if key not in ZOO_ONLY_KEYS}
    if isinstance(kwargs.get("policy_kwargs"), str):
        kwargs["policy_kwargs"] = eval(kwargs["policy_kwargs"], {"__builtins__": {}}, POLICY_KWARGS_NAMES)  # noqa: S307
    return kwargs, n_timesteps, policy


def load_training_env_kwargs(algo: str, env_id: str) -> dict[str, Any]:
    """The YAML's ``env_kwargs``: as in rl_zoo3, they configure the training env only, never the evaluation env."""
    return dict(load_entry(algo, env_id).get("env_kwargs") or {})
