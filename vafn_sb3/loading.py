"""Load any saved policy (SB3 zip or weights-only file) without knowing its algorithm, and say what it was trained on.

``load_model`` reads the file's own description first: a weights-only file names its algorithm; an SB3 zip of MAML-SAC
holds its meta-learning hyperparameters; a zoo run's folder ``<algo>/<EnvName>_<N>/`` names the algorithm. Otherwise
every vafn and SB3 algorithm is tried in turn; the error lists why each one refused the file.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any

#: Hyperparameters only MAML-SAC saves (an SB3 zip with them is a MAML-SAC model).
MAML_KEYS = frozenset({"inner_steps", "meta_batch_size", "n_support", "n_query"})
#: Env settings that define a task family: a policy trained with other values solves a different problem.
FAMILY_KEYS = ("n_arms", "targets", "observe_goal", "inactive_arms", "robot", "frame", "waiting_goal")


def _candidates() -> dict[str, type]:
    """Algorithm key -> class, most specific first (vafn classes before SB3's)."""
    from stable_baselines3 import PPO, TD3
    from stable_baselines3 import SAC as SB3SAC

    from vafn_sb3 import MAAC, MADDPG, MAMLSAC, MAPPO, MTSAC, SAC

    candidates = {"maml_sac": MAMLSAC, "mtsac": MTSAC, "sac": SAC, "maac": MAAC, "maddpg": MADDPG, "mappo": MAPPO,
                  "sb3_sac": SB3SAC, "td3": TD3, "ppo": PPO}
    try:  # sb3-contrib comes with the [zoo] extra (rl_zoo3); its RecurrentPPO is the zoo's ppo_lstm
        from sb3_contrib import RecurrentPPO
    except ImportError:
        return candidates
    return {**candidates, "ppo_lstm": RecurrentPPO}


def _zip_entries(path: Path) -> tuple[list[str], dict[str, Any]]:
    """The zip's entry names and its SB3 ``data`` JSON (empty when absent or unreadable)."""
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            data = json.loads(archive.read("data")) if "data" in names else {}
    except (zipfile.BadZipFile, json.JSONDecodeError, KeyError) as error:
        raise ValueError(f"{path} is not a saved model (zip): {error}") from error
    return names, data


def _policy_module(data: dict[str, Any]) -> str:
    """The module of the policy class named in an SB3 ``data`` JSON ("" when absent)."""
    policy_class = data.get("policy_class")
    return str(policy_class.get("__module__", "")) if isinstance(policy_class, dict) else ""


def load_model(path: str | Path, algo: str | None = None) -> tuple[Any, str]:
    """``(model, algorithm key)`` of the policy saved at ``path`` (``ValueError`` naming why it cannot load).

    :param path: an SB3 ``.zip`` (``model.save``) or a weights-only file (``vafn_sb3.save_weights``).
    :param algo: force an algorithm key (sac, mtsac, maml_sac, maac, maddpg, mappo, td3, ppo, ppo_lstm).
    """
    path = Path(path)
    if not path.is_file() and path.with_suffix(".zip").is_file():
        path = path.with_suffix(".zip")
    if not path.is_file():
        raise FileNotFoundError(f"no model file at {path}")
    names, data = _zip_entries(path)
    candidates = _candidates()
    if algo is not None and algo not in candidates:
        raise ValueError(f"unknown algorithm {algo!r}; choose one of {sorted(candidates)}")
    if "config.json" in names and "data" not in names:  # weights-only format: it names its algorithm
        from vafn_sb3.common.serialization import load_weights

        model = load_weights(path)
        return model, type(model).__name__.lower()
    if algo is not None:
        order = [algo]
    elif MAML_KEYS <= set(data):
        order = ["maml_sac"]
    elif "ppo_lstm" in candidates and _policy_module(data).startswith("sb3_contrib.common.recurrent"):
        order = ["ppo_lstm"]  # PPO-family classes would also load it, without its LSTM state
    else:
        run_algo = path.parent.parent.name  # zoo layout <folder>/<algo>/<EnvName>_<N>/<EnvName>.zip
        order = ([run_algo] if run_algo in candidates else []) + [k for k in candidates if k != "maml_sac"]
    failures = []
    for key in dict.fromkeys(order):
        try:
            return candidates[key].load(path, device="cpu"), key
        except Exception as error:  # noqa: BLE001 - try the next algorithm; report all failures together
            failures.append(f"{key}: {type(error).__name__}: {str(error)[:120]}")
    raise ValueError(f"could not load {path} with any algorithm ({'; '.join(failures)}); pass the algorithm "
                     "explicitly if it is one of these")


def training_env(path: str | Path) -> tuple[str | None, dict[str, Any]]:
    """``(env id, env kwargs)`` the model at ``path`` was trained on, from the files saved beside it (or ``None``).

    Reads a zoo run's ``<EnvName>/config.yml`` or a packaged policy's ``.json`` metadata.
    """
    path = Path(path)
    meta = path.with_suffix(".json")
    if meta.is_file():
        try:
            info = json.loads(meta.read_text())
        except json.JSONDecodeError:
            info = {}
        if isinstance(info, dict) and "env_id" in info:
            return str(info["env_id"]), dict(info.get("env_kwargs") or {})
    config = path.parent / path.stem / "config.yml"
    if config.is_file():
        import yaml

        try:
            loaded = yaml.load(config.read_text(), Loader=yaml.UnsafeLoader)  # the zoo writes python tuples
        except yaml.YAMLError:
            loaded = None
        entries = dict(loaded) if isinstance(loaded, list) else (loaded or {})
        env_kwargs = entries.get("env_kwargs") or {}
        env_name = path.parent.name.rsplit("_", 1)[0]  # <EnvName>_<N>
        return env_name.replace("-", "/", 1) if env_name.startswith("VAFN-") else env_name, dict(env_kwargs)
    return None, {}


def task_family(env_id: str, env_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """The task-family settings (:data:`FAMILY_KEYS`) of a registered vafn env, defaults from ``MultiArmEnv``."""
    import inspect

    import gymnasium as gym

    from vafn_gym.envs import MultiArmEnv  # also registers the env IDs

    spec = gym.spec(env_id)
    kwargs = {**(spec.kwargs or {}), **(env_kwargs or {})}
    defaults = inspect.signature(MultiArmEnv.__init__).parameters
    return {key: kwargs.get(key, defaults[key].default) for key in FAMILY_KEYS}


def family_mismatch(trained_id: str | None, trained_kwargs: dict[str, Any], env_id: str,
                    env_kwargs: dict[str, Any] | None = None) -> list[str]:
    """Differences between the task family a model was trained on and the one it is about to run on."""
    if trained_id is None:
        return []
    try:
        trained, running = task_family(trained_id, trained_kwargs), task_family(env_id, env_kwargs)
    except Exception:  # noqa: BLE001 - an unknown env id: nothing to compare
        return [f"trained on {trained_id}, which is not a registered vafn env"]
    return [f"{key}: trained with {trained[key]!r}, running with {running[key]!r}"
            for key in FAMILY_KEYS if str(trained[key]) != str(running[key])]
