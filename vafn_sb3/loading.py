"""Load any saved policy (SB3 zip or weights-only file) without knowing its algorithm, and say what it was trained on.

``load_model`` reads the file's own description first: a weights-only file names its algorithm; an SB3 zip of MAML-SAC
or MADDPG holds hyperparameters only that algorithm saves; an SB3 zip names its policy class, which narrows the
algorithms to those with that policy; a zoo run's folder ``<algo>/<EnvName>_<N>/`` names the algorithm. The candidates
(the registry's :data:`~vafn_sb3.registry.ALGORITHMS`) are then tried in turn, the others after them; the error lists
why each one refused the file.

No file runs code unless the caller says it trusts it: a weights-only file loads with :func:`load_weights`; an SB3 zip
(``model.save``, the zoo's runs) loads with :func:`load_sb3_zip`, which reads its ``data`` entry as JSON and never
unpickles the ``:serialized:`` values SB3 stores there: the algorithm and policy class come from the registry (the
class's name is read from the pickle's opcodes), spaces, ``policy_kwargs`` and hyperparameters from the plain JSON
(checked against the bounds of weights-only files first), and every ``.pth`` entry with
``torch.load(weights_only=True)``. A zip it cannot rebuild that way is refused with a ``ValueError`` naming the file;
SB3's own, unpickling ``load`` runs only with ``trust_remote_code=True`` (``--trust-remote-code`` on the command
lines). Either way the zip directory's sizes are checked before anything is inflated, and a model with non-finite
weights is refused.
"""

from __future__ import annotations

import argparse
import base64
import binascii
import io
import json
import math
import pickletools
import re
import zipfile
from pathlib import Path
from typing import Any

import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.save_util import recursive_setattr
from stable_baselines3.common.utils import check_for_correct_spaces

from vafn_sb3.common.save import MAX_JSON_ENTRY_BYTES, check_file_size, check_zip_directory
from vafn_sb3.common.serialization import (
    _CLASS_KWARGS,
    MAX_LAYERS,
    MAX_SPACE_SIZE,
    _decode_policy_kwargs,
    _decode_space,
    _hyperparameter_names,
    _read_tensors,
    check_config_bounds,
    check_finite,
    load_weights,
)
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


def untrusted_sb3_zip_error(path: str | Path, reason: str = "its data entry is a pickle, which runs code when "
                            "loaded") -> ValueError:
    """The refusal of an SB3 zip that cannot load without unpickling: why, and the two ways on."""
    return ValueError(f"{path} is an SB3 model zip that cannot be loaded without unpickling ({reason}); refused. "
                      "Load it with trust_remote_code=True (--trust-remote-code) only if you made it or trust its "
                      "source, or convert it once with vafn_sb3.save_weights")


def load_model(path: str | Path, algo: str | None = None, *, trust_remote_code: bool = False,
               env: Any = None) -> tuple[BaseAlgorithm, str]:
    """``(model, algorithm key)`` of the policy saved at ``path`` (``ValueError`` naming why it cannot load).

    :param path: a weights-only file (``vafn_sb3.save_weights``) or an SB3 ``.zip`` (``model.save``, a zoo run).
    :param algo: force an algorithm key (one of :data:`vafn_sb3.registry.ALGORITHMS`).
    :param trust_remote_code: load SB3 zips with SB3's ``load``, which unpickles the file: code in it runs. Without
        it an SB3 zip loads with :func:`load_sb3_zip` (nothing is unpickled) or is refused.
    :param env: optional env for the model (its spaces must match the saved ones).
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
        model = load_weights(path, env)
        return model, type(model).__name__.lower()
    data = _sb3_data(path)
    if not trust_remote_code:
        return load_sb3_zip(path, algo, env=env, data=data)
    return _load_trusted_sb3(path, algo, data, env)


def _candidates(path: Path, data: dict[str, Any], algo: str | None) -> list[str]:
    """Algorithm keys to try on an SB3 zip's ``data``, most likely first."""
    signed = [key for key, entry in ALGORITHMS.items() if entry.saved_keys and entry.saved_keys <= set(data)]
    if algo is not None:
        return [algo]
    if signed:  # hyperparameters only one algorithm saves (MAML-SAC's inner loop, MADDPG's exploration)
        return signed
    # Algorithms whose policies include the saved one first (another class may load the file and run it wrongly:
    # PPO would load a RecurrentPPO zip without its LSTM state), the zoo run's own algorithm first among them.
    # An algorithm that saves keys of its own comes last on a zip without them (a DDPG zip is not MADDPG's).
    unsigned = [key for key, entry in ALGORITHMS.items() if not entry.saved_keys]
    saved = saved_policy_class(data)
    matching = [key for key in unsigned if saved in ALGORITHMS[key].policy_classes()]
    run_algo = path.parent.parent.name  # zoo layout <folder>/<algo>/<EnvName>_<N>/<EnvName>.zip
    first = [run_algo] if run_algo in unsigned and (not matching or run_algo in matching) else []
    return list(dict.fromkeys(first + matching + unsigned + [key for key in ALGORITHMS if key not in unsigned]))


def _load_trusted_sb3(path: Path, algo: str | None, data: dict[str, Any], env: Any) -> tuple[BaseAlgorithm, str]:
    """``(model, key)`` of an SB3 zip through SB3's unpickling ``load`` (trusted files only), weights checked finite."""
    failures = []
    for key in _candidates(path, data, algo):
        try:
            model = ALGORITHMS[key].cls.load(path, env=env, device="cpu")
        except Exception as error:  # noqa: BLE001 - try the next algorithm; report all failures together
            failures.append(f"{key}: {type(error).__name__}: {str(error)[:120]}")
            continue
        check_finite(model.policy.state_dict(), str(path))
        return model, key
    raise ValueError(f"could not load {path} with any algorithm ({'; '.join(failures)}); pass the algorithm "
                     "explicitly if it is one of these")


# --- SB3 zips without unpickling -------------------------------------------------------------------------------------

#: Attributes SB3 saves beside the constructor's parameters that :func:`load_sb3_zip` restores (training counters).
_COUNTERS = ("num_timesteps", "_total_timesteps", "_num_timesteps_at_start", "_episode_num", "_n_updates")
#: A constant schedule as SB3 describes it in the JSON beside its pickle (``FloatSchedule.value_schedule``).
_CONSTANT_SCHEDULE = re.compile(r"ConstantSchedule\(val=([-+0-9.eE]+)\)")
#: A class as ``str(cls)`` writes it.
_CLASS_REPR = re.compile(r"<class '([\w.]+)\.(\w+)'>")


def _is_serialized(value: Any) -> bool:
    return isinstance(value, dict) and ":serialized:" in value


def _json_space(value: Any, key: str) -> dict[str, Any]:
    """A float Box space SB3 described in the JSON beside its pickle, in the weights format's form (``ValueError``
    when it is another space or its bounds were abbreviated)."""
    if not _is_serialized(value) or value.get(":type:") != "<class 'gymnasium.spaces.box.Box'>":
        raise ValueError(f"its {key} is not a Box space described in plain JSON")
    shape, dtype = value.get("_shape"), value.get("dtype")
    if not isinstance(shape, list) or not all(isinstance(size, int) and size >= 0 for size in shape):
        raise ValueError(f"its {key} has no plain shape")
    size = math.prod(shape[:MAX_LAYERS])
    if size > MAX_SPACE_SIZE:
        raise ValueError(f"its {key} has {size:,} elements (at most {MAX_SPACE_SIZE})")
    bounds = []
    for bound in ("low", "high"):
        text = value.get(bound)
        if not isinstance(text, str) or "..." in text or len(text) > 64 * MAX_SPACE_SIZE:
            raise ValueError(f"its {key}.{bound} is not written out in full")
        try:
            numbers = [float(item) for item in text.replace("[", " ").replace("]", " ").split()]
        except ValueError:
            raise ValueError(f"its {key}.{bound} is not a list of numbers") from None
        if len(numbers) != size:
            raise ValueError(f"its {key}.{bound} has {len(numbers)} numbers for shape {shape}")
        bounds.append(numbers)
    return {"type": "Box", "shape": shape, "dtype": dtype, "low": bounds[0], "high": bounds[1]}


def _json_policy_kwargs(value: Any) -> dict[str, Any]:
    """``policy_kwargs`` from the JSON: plain, or the plain items SB3 wrote beside its pickle with the classes the
    weights format allows (activation, optimiser, features extractor) by name (``ValueError`` for any other class)."""
    if value is None:
        return {}
    if not _is_serialized(value):
        if not isinstance(value, dict):
            raise ValueError("its policy_kwargs is not a JSON object")
        return value
    kwargs: dict[str, Any] = {}
    for key, item in value.items():
        if key in (":type:", ":serialized:"):
            continue
        match = _CLASS_REPR.fullmatch(item) if isinstance(item, str) else None
        if key in _CLASS_KWARGS:
            allowed = _CLASS_KWARGS[key]
            try:
                resolved = allowed.resolve(match.group(2) if match else None)
            except ValueError:
                resolved = None
            if match is None or resolved is None or resolved.__module__ != match.group(1):
                raise ValueError(f"its policy_kwargs[{key!r}] = {str(item)[:80]} is not a class the weights format "
                                 f"allows (a {allowed.base.__name__} of {allowed.module.__name__})")
            kwargs[key] = match.group(2)
        elif match is not None or (isinstance(item, str) and item.startswith("<")):
            raise ValueError(f"its policy_kwargs[{key!r}] = {item[:80]} is a Python object")
        else:
            kwargs[key] = item
    return kwargs


def _constant(value: Any) -> float | None:
    """The value of a constant learning rate / clip range: a plain number, or SB3's description of a constant
    schedule beside its pickle (None for anything else)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    text = value.get("value_schedule", value.get("val")) if _is_serialized(value) else None
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        return float(text)
    match = _CONSTANT_SCHEDULE.fullmatch(text) if isinstance(text, str) else None
    return float(match.group(1)) if match else None


def _saved_policy(cls: type[BaseAlgorithm], data: dict[str, Any]) -> type:
    """The registry's policy class of ``cls`` that the zip names (by module and name, read without unpickling)."""
    saved = saved_policy_class(data)
    if saved is None:
        raise ValueError("its policy class cannot be read without unpickling")
    for policy in cls.policy_aliases.values():
        if (policy.__module__, policy.__qualname__) == saved:
            return policy
    raise ValueError(f"{cls.__name__} has no policy {saved[0]}.{saved[1]}")


def _pth_entries(archive: zipfile.ZipFile, names: list[str], name: str) -> dict[str, Any]:
    """The zip's ``<object>.pth`` entries (state dicts) read with ``torch.load(weights_only=True)``."""
    loaded = {}
    for entry in names:
        if not entry.endswith(".pth") or entry == "pytorch_variables.pth":
            continue
        try:
            loaded[entry[:-4]] = th.load(io.BytesIO(archive.read(entry)), map_location="cpu", weights_only=True)
        except Exception as error:  # noqa: BLE001 - torch raises UnpicklingError, RuntimeError, ...
            raise ValueError(f"{name}: {entry} is not plain tensor data (refused without unpickling): "
                             f"{str(error)[:200]}") from None
    return loaded


def _build_from_json(path: Path, key: str, data: dict[str, Any], env: Any, names: list[str]) -> BaseAlgorithm:
    """Rebuild the ``key`` model an SB3 zip holds from its plain JSON and tensor entries (``ValueError`` when the zip
    has something that cannot be rebuilt that way)."""
    name = str(path)
    cls = ALGORITHMS[key].cls
    policy_class = _saved_policy(cls, data)
    allowed = _hyperparameter_names(cls)
    hyperparameters = {field: value for field, value in data.items()
                       if field in allowed and not _is_serialized(value) and field != "learning_rate"}
    for field in ("learning_rate", "clip_range"):  # constants only; another schedule takes the class's default
        value = _constant(data.get(field, data.get("lr_schedule") if field == "learning_rate" else None))
        if field in allowed and value is not None:
            hyperparameters[field] = value
    config: dict[str, Any] = {"policy_kwargs": _json_policy_kwargs(data.get("policy_kwargs")),
                              "hyperparameters": hyperparameters}
    spaces_ = {}
    for field in ("observation_space", "action_space"):
        try:
            config[field] = _json_space(data.get(field), field)
            spaces_[field] = _decode_space(config[field])
        except ValueError:
            if env is None:
                raise
            spaces_[field] = getattr(env, field)  # the caller's env gives what the file does not say in JSON
    with zipfile.ZipFile(path) as archive:
        if "policy.pth" not in names:
            raise ValueError(f"{name} is incomplete: no policy.pth entry")
        check_config_bounds(config, name, archive.getinfo("policy.pth").file_size)
        policy_kwargs = _decode_policy_kwargs(config["policy_kwargs"])
        states = _pth_entries(archive, names, name)
        variables = (_read_tensors(archive, "pytorch_variables.pth", name, "cpu")
                     if "pytorch_variables.pth" in names else {})
    # every algorithm of the registry takes _init_setup_model (SB3's off- and on-policy bases)
    model = cls(policy=policy_class, env=env, device="cpu", policy_kwargs=policy_kwargs,  # type: ignore[call-arg]
                _init_setup_model=False)
    if env is None:
        model.observation_space, model.action_space, model.n_envs = (spaces_["observation_space"],
                                                                    spaces_["action_space"], 1)
    elif model.env is not None:
        check_for_correct_spaces(model.env, spaces_["observation_space"], spaces_["action_space"])
    model.__dict__.update({field: tuple(value) if isinstance(value, list) else value
                           for field, value in hyperparameters.items()})
    model.__dict__.update({field: data[field] for field in _COUNTERS
                           if isinstance(data.get(field), (int, float)) and not isinstance(data.get(field), bool)})
    model._setup_model()
    expected_states, expected_variables = model._get_torch_save_params()
    if "policy" not in states or set(states) - set(expected_states):
        raise ValueError(f"{name}: its state entries {sorted(states)} are not {cls.__name__}'s {expected_states}")
    if set(variables) - set(expected_variables):
        raise ValueError(f"{name}: unexpected variables {sorted(set(variables) - set(expected_variables))}")
    policy_state = states["policy"]
    if not isinstance(policy_state, dict) or not all(isinstance(value, th.Tensor) for value in policy_state.values()):
        raise ValueError(f"{name}: policy.pth must hold a dict of named tensors")
    check_finite(policy_state, f"{name}: policy.pth")
    model.set_parameters(states, exact_match=set(states) == set(expected_states), device="cpu")
    for variable, tensor in variables.items():
        recursive_setattr(model, f"{variable}.data", tensor)
    if getattr(model, "use_sde", False):
        model.policy.reset_noise()  # type: ignore[operator]
    return model


def load_sb3_zip(path: str | Path, algo: str | None = None, *, env: Any = None,
                 data: dict[str, Any] | None = None) -> tuple[BaseAlgorithm, str]:
    """``(model, algorithm key)`` of an SB3 zip rebuilt without unpickling anything in it.

    The algorithm is chosen as SB3's ``load`` candidates are (:func:`load_model`); its policy class is the registry's
    class the zip names (read from the pickle's opcodes), the spaces are the float Boxes SB3 describes in plain JSON
    beside its pickles (or ``env``'s when they are not), ``policy_kwargs``, the constructor's hyperparameters and
    constant learning rates come from the JSON after the bounds of weights-only files are checked, and the policy,
    optimiser and variable entries are read with ``torch.load(weights_only=True)``. Settings SB3 keeps only as pickles
    (train frequency, action noise, buffer classes, schedules other than constants) take the class's defaults: the
    policy acts as saved, and training resumes with those defaults. ``ValueError`` naming the file when the zip
    cannot be rebuilt this way (then only SB3's unpickling load, ``trust_remote_code=True``, reads it).
    """
    path = Path(path)
    names = _zip_entries(path)
    data = _sb3_data(path) if data is None else data
    if algo is not None:
        algorithm(algo)
    saved = saved_policy_class(data)
    if saved is None:
        raise untrusted_sb3_zip_error(path, "its policy class cannot be read without unpickling")
    candidates = [key for key in _candidates(path, data, algo) if saved in ALGORITHMS[key].policy_classes()]
    if not candidates:
        raise untrusted_sb3_zip_error(path, f"no {'algorithm' if algo is None else algo} of the registry has its "
                                            f"policy class {saved[0]}.{saved[1]}")
    failures: list[str] = []
    for key in candidates:
        try:
            model = _build_from_json(path, key, data, env, names)
        except ValueError as error:
            if str(error).startswith(str(path)):  # the file itself is refused: no other algorithm reads it either
                raise
            failures.append(f"{key}: {str(error)[:160]}")
            continue
        except Exception as error:  # noqa: BLE001 - the JSON does not fit this class: try the next one
            failures.append(f"{key}: {type(error).__name__}: {str(error)[:120]}")
            continue
        return model, key
    reasons = {failure.split(": ", 1)[1] for failure in failures}
    reason = reasons.pop() if len(reasons) == 1 else "; ".join(failures)
    raise untrusted_sb3_zip_error(path, reason)


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
TRUST_HELP = ("load SB3 .zip models with SB3's own load, which unpickles them (code in them runs): only files you made "
              "or trust. Without it an SB3 zip is rebuilt from its JSON and tensors without unpickling, or refused")


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
