"""Load any saved policy (SB3 zip or weights-only file) without knowing its algorithm, and say what it was trained on.

``load_model`` reads the file's own description first: a weights-only file names its algorithm; an SB3 zip of MAML-SAC
or MADDPG holds hyperparameters only that algorithm saves; an SB3 zip names its policy class, which narrows the
algorithms to those with that policy; a zoo run's folder ``<algo>/<EnvName>_<N>/`` names the algorithm. The candidates
(the registry's :data:`~vafn_sb3.registry.ALGORITHMS`) are then tried in turn, the others after them; the error lists
why each one refused the file.

No file runs code unless the caller says it trusts it: a weights-only file loads with :func:`load_weights` (nothing is
unpickled); an SB3 zip, whose ``data`` entry is a pickle that runs code when loaded, is refused with a ``ValueError``
naming the file unless ``trust_remote_code=True`` (``--trust-remote-code`` on the command lines). Either way the zip
directory's sizes are checked before anything is inflated, and a model with non-finite weights is refused.
"""

from __future__ import annotations

import argparse
import base64
import binascii
import json
import pickletools
import re
import zipfile
from pathlib import Path
from typing import Any

from stable_baselines3.common.base_class import BaseAlgorithm

from vafn_sb3.common.save import MAX_JSON_ENTRY_BYTES, check_file_size, check_zip_directory
from vafn_sb3.common.serialization import check_finite, load_weights
from vafn_sb3.registry import ALGORITHMS, algorithm

#: Env settings that define a task family: a policy trained with other values solves a different problem.
FAMILY_KEYS = ("n_arms", "targets", "observe_goal", "inactive_arms", "robot", "frame", "waiting_goal")


def _zip_entries(path: Path) -> list[str]:
    """The zip's entry names, after its file and directory sizes are checked (nothing is inflated)."""
    check_file_size(path, str(path))
    try:
        with zipfile.ZipFile(path) as archive:
            check_zip_directory(archive, str(path))
            return archive.namelist()
    except (zipfile.BadZipFile, OSError, EOFError) as error:
        raise ValueError(f"{path} is not a saved model (zip): {error}") from error


def _sb3_data(path: Path) -> dict[str, Any]:
    """The SB3 ``data`` JSON of a size-checked zip (its values are read as JSON, nothing is unpickled)."""
    try:
        with zipfile.ZipFile(path) as archive:
            data = json.loads(archive.read("data"))
    except (zipfile.BadZipFile, json.JSONDecodeError, UnicodeDecodeError, KeyError, OSError) as error:
        raise ValueError(f"{path} is not a saved model (zip): {error}") from error
    if not isinstance(data, dict):
        raise ValueError(f"{path}: its data entry is not a JSON object")
    return data


def saved_policy_class(data: dict[str, Any]) -> tuple[str, str] | None:
    """``(module, class name)`` of the policy class an SB3 ``data`` JSON names (None when it does not say).

    SB3 stores the class as a base64 pickle; a class pickled by reference is its module and qualified name, read here
    from the pickle's opcodes without unpickling it (so nothing in the file runs).
    """
    policy_class = data.get("policy_class")
    if not isinstance(policy_class, dict) or not isinstance(policy_class.get(":serialized:"), str):
        return None
    try:
        raw = base64.b64decode(policy_class[":serialized:"], validate=True)
        strings = [arg for _, arg, _ in pickletools.genops(raw) if isinstance(arg, str)]
    except (binascii.Error, ValueError):
        return None
    if len(strings) < 2 or strings[0] != policy_class.get("__module__"):
        return None  # not a by-reference class: nothing to match against
    return strings[0], strings[1]


def untrusted_sb3_zip_error(path: str | Path) -> ValueError:
    """The refusal of an SB3 zip loaded without ``trust_remote_code``: what it is and the two ways on."""
    return ValueError(f"{path} is an SB3 model zip: its data entry is a pickle, which runs code when loaded; refused. "
                      "Load it with trust_remote_code=True (--trust-remote-code) only if you made it or trust its "
                      "source, or convert it once with vafn_sb3.save_weights")


def load_model(path: str | Path, algo: str | None = None, *,
               trust_remote_code: bool = False) -> tuple[BaseAlgorithm, str]:
    """``(model, algorithm key)`` of the policy saved at ``path`` (``ValueError`` naming why it cannot load).

    :param path: a weights-only file (``vafn_sb3.save_weights``) or, trusted only, an SB3 ``.zip`` (``model.save``).
    :param algo: force an algorithm key (one of :data:`vafn_sb3.registry.ALGORITHMS`).
    :param trust_remote_code: load SB3 zips with SB3's ``load``, which unpickles the file: code in it runs. Without
        it only weights-only files load and an SB3 zip is refused.
    """
    path = Path(path)
    if not path.is_file() and path.with_suffix(".zip").is_file():
        path = path.with_suffix(".zip")
    if not path.is_file():
        raise FileNotFoundError(f"no model file at {path}")
    names = _zip_entries(path)
    if algo is not None:
        algorithm(algo)  # ValueError listing the keys when unknown
    if "data" not in names:  # weights-only format: it names its algorithm (load_weights says what a file lacks)
        model = load_weights(path)
        return model, type(model).__name__.lower()
    if not trust_remote_code:
        raise untrusted_sb3_zip_error(path)
    return _load_trusted_sb3(path, algo)


def _load_trusted_sb3(path: Path, algo: str | None) -> tuple[BaseAlgorithm, str]:
    """``(model, key)`` of an SB3 zip through SB3's unpickling ``load`` (trusted files only), weights checked finite."""
    data = _sb3_data(path)
    signed = [key for key, entry in ALGORITHMS.items() if entry.saved_keys and entry.saved_keys <= set(data)]
    if algo is not None:
        order = [algo]
    elif signed:  # hyperparameters only one algorithm saves (MAML-SAC's inner loop, MADDPG's exploration)
        order = signed
    else:
        # Algorithms whose policies include the saved one first (another class may load the file and run it wrongly:
        # PPO would load a RecurrentPPO zip without its LSTM state), the zoo run's own algorithm first among them.
        # An algorithm that saves keys of its own comes last on a zip without them (a DDPG zip is not MADDPG's).
        unsigned = [key for key, entry in ALGORITHMS.items() if not entry.saved_keys]
        saved = saved_policy_class(data)
        matching = [key for key in unsigned if saved in ALGORITHMS[key].policy_classes()]
        run_algo = path.parent.parent.name  # zoo layout <folder>/<algo>/<EnvName>_<N>/<EnvName>.zip
        first = [run_algo] if run_algo in unsigned and (not matching or run_algo in matching) else []
        order = first + matching + unsigned + [key for key in ALGORITHMS if key not in unsigned]
    failures = []
    for key in dict.fromkeys(order):
        try:
            model = ALGORITHMS[key].cls.load(path, device="cpu")
        except Exception as error:  # noqa: BLE001 - try the next algorithm; report all failures together
            failures.append(f"{key}: {type(error).__name__}: {str(error)[:120]}")
            continue
        check_finite(model.policy.state_dict(), str(path))
        return model, key
    raise ValueError(f"could not load {path} with any algorithm ({'; '.join(failures)}); pass the algorithm "
                     "explicitly if it is one of these")


def load_model_or_exit(path: str | Path, algo: str | None = None, context: str = "", *,
                       trust_remote_code: bool = False) -> tuple[BaseAlgorithm, str]:
    """:func:`load_model` for command-line tools: a file that does not load stops the program in one line.

    :param context: put before the reason (e.g. ``"--method mtsac: "``).
    :param trust_remote_code: as in :func:`load_model`.
    """
    try:
        return load_model(path, algo, trust_remote_code=trust_remote_code)
    except (ValueError, FileNotFoundError) as error:
        raise SystemExit(f"{context}{error}") from None


#: Help of every command line's ``--trust-remote-code`` (:func:`add_trust_flag`).
TRUST_HELP = ("load SB3 .zip models, whose pickled data runs code when loaded: only files you made or trust. Without "
              "it only weights-only files (vafn_sb3.save_weights, the packaged policies) load")


def add_trust_flag(parser: argparse.ArgumentParser) -> None:
    """Add ``--trust-remote-code`` (``args.trust_remote_code``) to an ``argparse`` parser that loads models."""
    parser.add_argument("--trust-remote-code", action="store_true", help=TRUST_HELP)


def training_seed(path: str | Path) -> int | None:
    """The training seed in a saved model's file name, ``..._seed<N>.zip`` as ``benchmarks/learning.py --save`` names
    it (None if the name carries none)."""
    match = re.search(r"seed(\d+)", Path(path).stem)
    return None if match is None else int(match.group(1))


def training_env(path: str | Path) -> tuple[str | None, dict[str, Any]]:
    """``(env id, env kwargs)`` the model at ``path`` was trained on, from the files saved beside it (or ``None``).

    Reads a zoo run's ``<EnvName>/config.yml`` (with a YAML ``SafeLoader`` that knows only rl_zoo3's tags) or a
    packaged policy's ``.json`` metadata; ``ValueError`` naming the file when it is too large, a Python tag outside
    that allow-list, or not a mapping.
    """
    path = Path(path)
    meta = path.with_suffix(".json")
    if meta.is_file():
        try:
            info = json.loads(_small_text(meta))
        except json.JSONDecodeError:
            info = {}
        if isinstance(info, dict) and "env_id" in info:
            return str(info["env_id"]), dict(info.get("env_kwargs") or {})
    config = path.parent / path.stem / "config.yml"
    if config.is_file():
        import yaml

        from vafn_sb3.common.run_yaml import load_run_yaml

        try:
            loaded = load_run_yaml(_small_text(config))
        except yaml.YAMLError as error:
            reason = " ".join(str(error).split())
            raise ValueError(f"{config} is not a zoo config that loads safely: {reason}") from None
        entries = dict(loaded) if isinstance(loaded, list) else (loaded or {})
        env_kwargs = entries.get("env_kwargs") if isinstance(entries, dict) else None
        if not isinstance(env_kwargs, (dict, type(None))):
            raise ValueError(f"{config}: env_kwargs is not a mapping")
        env_kwargs = env_kwargs or {}
        env_name = path.parent.name.rsplit("_", 1)[0]  # <EnvName>_<N>
        return env_name.replace("-", "/", 1) if env_name.startswith("VAFN-") else env_name, dict(env_kwargs)
    return None, {}


def _small_text(path: Path) -> str:
    """The text of a metadata file beside a model, ``ValueError`` naming it when it is larger than a config can be."""
    if path.stat().st_size > MAX_JSON_ENTRY_BYTES:
        raise ValueError(f"{path} is {path.stat().st_size:,} bytes; a config has at most {MAX_JSON_ENTRY_BYTES:,}")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(f"{path} is not UTF-8 text: {error}") from None


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
