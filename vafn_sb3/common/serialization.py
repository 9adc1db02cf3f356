"""Safe model files: atomic writes for every save, and a weights-only format that loading cannot execute code from.

- :func:`atomic_write` writes through a temporary file in the target's folder and renames it onto the target, so a crash
  mid-write leaves the previous file intact; :class:`~vafn_sb3.common.save.AtomicSaveMixin` routes SB3's ``save``
  through it and makes ``load`` reject truncated or incomplete zips with a ``ValueError`` naming the file.
- SB3's ``load`` unpickles (cloudpickle) the ``data`` entry of the zip, which can run arbitrary code from an untrusted
  file. :func:`save_weights` / :func:`load_weights` use a second format that needs no unpickling: one zip holding
  ``config.json`` (algorithm name, Box spaces, policy alias, JSON-safe ``policy_kwargs`` with classes stored by name,
  JSON-safe hyperparameters) and ``policy.pt`` / ``variables.pt`` (plain tensor dicts, read with
  ``torch.load(weights_only=True)``). Optimiser states and non-JSON hyperparameters (schedules other than constants,
  action-noise objects, buffer classes) are not stored; they take their defaults on load.
- Limits before work: :func:`load_weights` reads entry sizes from the zip directory and checks every size the config
  gives (layers, critics, buffers, spaces; :data:`MAX_LAYER_WIDTH` and the other bounds below) before it inflates an
  entry or builds a network, and refuses weights that are not finite.
"""

from __future__ import annotations

import enum
import inspect
import io
import json
import math
import os
import zipfile
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common import torch_layers
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.save_util import recursive_getattr, recursive_setattr
from stable_baselines3.common.utils import ConstantSchedule, FloatSchedule, check_for_correct_spaces
from torch import nn

from vafn_gym.files import atomic_write  # re-exported: one implementation for every writer
from vafn_sb3.common.save import CONFIG_ENTRY, POLICY_ENTRY, VARIABLES_ENTRY, check_zip_entries
from vafn_sb3.registry import weights_classes

#: ``format`` field of a weights file's ``config.json`` and the version this module writes and reads.
WEIGHTS_FORMAT = "vafn-weights"
WEIGHTS_VERSION = 1
#: Constructor parameters that are never stored as hyperparameters: given at load time, stored separately, or
#: machine-specific.
_NOT_HYPERPARAMETERS = frozenset(
    {"self", "args", "kwargs", "policy", "env", "device", "policy_kwargs", "_init_setup_model", "tensorboard_log"}
)
#: Box dtypes a weights file may declare.
_SPACE_DTYPES = ("float32", "float64")
#: Bounds of the sizes a weights config gives, checked before anything is allocated: units in a layer, layers in a
#: network (items in any ``policy_kwargs`` list), critics, attention heads, elements of a Box space.
MAX_LAYER_WIDTH = 4096
MAX_LAYERS = 16
MAX_CRITICS = 16
MAX_ATTENTION_HEADS = 64
MAX_SPACE_SIZE = 4096
#: Largest value of the hyperparameters that size a buffer allocated when the model is built.
MAX_HYPERPARAMETERS = {"buffer_size": 10**7, "query_buffer_size": 10**7, "n_steps": 10**6, "batch_size": 10**6}
#: Largest buffer (bytes of float32 observations, next observations and actions) those hyperparameters may ask for.
MAX_BUFFER_BYTES = 2 * 2**30


class _ClassKwarg:
    """A class-valued policy keyword stored by name and resolved only inside one module, to subclasses of one base."""

    def __init__(self, module: ModuleType, base: type) -> None:
        self.module = module
        self.base = base

    def resolve(self, name: Any) -> type:
        value = getattr(self.module, name, None) if isinstance(name, str) else None
        if not (isinstance(value, type) and issubclass(value, self.base)) or value is self.base:
            raise ValueError(f"{name!r} is not a {self.base.__name__} class of {self.module.__name__}")
        return value


#: Class-valued ``policy_kwargs`` a weights file may name; any other class needs pickling and is refused.
_CLASS_KWARGS = {
    "activation_fn": _ClassKwarg(nn.modules.activation, nn.Module),
    "optimizer_class": _ClassKwarg(th.optim, th.optim.Optimizer),
    "features_extractor_class": _ClassKwarg(torch_layers, torch_layers.BaseFeaturesExtractor),
}


class _NotJSON(TypeError):
    """A value with no JSON form."""


def weights_algorithms() -> list[str]:
    """Names of the algorithms :func:`save_weights` and :func:`load_weights` support."""
    return sorted(weights_classes())


def _to_json(value: Any) -> Any:
    """``value`` as plain JSON data; constant SB3 schedules become their constant, enums their value."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, enum.Enum):
        return _to_json(value.value)
    if isinstance(value, FloatSchedule):
        return _to_json(value.value_schedule)
    if isinstance(value, ConstantSchedule):
        return _to_json(value.val)
    if isinstance(value, (list, tuple)):
        return [_to_json(item) for item in value]
    if isinstance(value, dict) and all(isinstance(key, str) for key in value):
        return {key: _to_json(item) for key, item in value.items()}
    raise _NotJSON(f"{type(value).__name__} has no JSON form")


def _hyperparameter_names(cls: type[BaseAlgorithm]) -> set[str]:
    """Public constructor parameters of ``cls``: its own, and its bases' for as long as ``**kwargs`` passes them on."""
    names: set[str] = set()
    for klass in cls.__mro__:
        if "__init__" not in vars(klass):
            continue
        parameters = inspect.signature(vars(klass)["__init__"]).parameters
        names.update(parameters)
        if not any(parameter.kind is inspect.Parameter.VAR_KEYWORD for parameter in parameters.values()):
            break
    return names - _NOT_HYPERPARAMETERS


def _policy_alias(model: BaseAlgorithm) -> str:
    for alias, policy_class in model.policy_aliases.items():
        if policy_class is model.policy_class:
            return alias
    raise ValueError(
        f"{type(model).__name__}'s policy class {model.policy_class.__name__} has no alias in policy_aliases "
        f"({sorted(model.policy_aliases)}); a weights file names the policy by alias"
    )


def _encode_policy_kwargs(policy_kwargs: dict[str, Any]) -> dict[str, Any]:
    encoded: dict[str, Any] = {}
    for key, value in policy_kwargs.items():
        if key in _CLASS_KWARGS:
            name = getattr(value, "__name__", None)
            try:
                stored_by_name = _CLASS_KWARGS[key].resolve(name) is value
            except ValueError:
                stored_by_name = False
            if not stored_by_name:
                raise ValueError(f"policy_kwargs[{key!r}] = {value!r} cannot be stored by name: {name!r} is not a "
                                 f"{_CLASS_KWARGS[key].base.__name__} class of {_CLASS_KWARGS[key].module.__name__}")
            encoded[key] = name
            continue
        try:
            encoded[key] = _to_json(value)
        except _NotJSON as error:
            raise ValueError(f"policy_kwargs[{key!r}] = {value!r} cannot be stored without pickling: {error}") from None
    return encoded


def _decode_policy_kwargs(encoded: Any) -> dict[str, Any]:
    if not isinstance(encoded, dict):
        raise ValueError(f"policy_kwargs must be a JSON object, got {type(encoded).__name__}")
    return {key: _CLASS_KWARGS[key].resolve(value) if key in _CLASS_KWARGS else value for key, value in encoded.items()}


def _encode_space(space: spaces.Space) -> dict[str, Any]:
    if not isinstance(space, spaces.Box) or space.dtype.name not in _SPACE_DTYPES:
        raise ValueError(f"weights files support float Box spaces only, got {space}")
    return {"type": "Box", "shape": list(space.shape), "dtype": space.dtype.name,
            "low": space.low.tolist(), "high": space.high.tolist()}


def _decode_space(encoded: Any) -> spaces.Box:
    if not isinstance(encoded, dict) or encoded.get("type") != "Box" or encoded.get("dtype") not in _SPACE_DTYPES:
        raise ValueError(f"expected a float Box space description, got {str(encoded)[:200]}")
    try:
        shape = tuple(int(size) for size in encoded["shape"])
        if len(shape) > MAX_LAYERS or min(shape, default=1) < 0 or math.prod(shape) > MAX_SPACE_SIZE:
            raise ValueError(f"a Box of shape {shape} is outside the bounds (at most {MAX_SPACE_SIZE} elements)")
        low = np.asarray(encoded["low"], dtype=encoded["dtype"]).reshape(shape)
        high = np.asarray(encoded["high"], dtype=encoded["dtype"]).reshape(shape)
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"malformed Box space description {str(encoded)[:200]}: {error}") from error
    return spaces.Box(low=low, high=high, shape=shape, dtype=encoded["dtype"])


def weights_config(model: BaseAlgorithm) -> dict[str, Any]:
    """The ``config.json`` of :func:`save_weights`; ``ValueError`` if the model cannot be rebuilt from JSON alone."""
    name = type(model).__name__
    registered = weights_classes().get(name)
    if registered is None or not issubclass(registered, type(model)):  # vafn's SAC also reads SB3 SAC models
        raise ValueError(f"weights files support {weights_algorithms()}, got {type(model).__qualname__}")
    hyperparameters, not_saved = {}, []
    for key in sorted(_hyperparameter_names(type(model))):
        if key not in vars(model):
            continue
        try:
            hyperparameters[key] = _to_json(vars(model)[key])
        except _NotJSON:
            not_saved.append(key)
    return {
        "format": WEIGHTS_FORMAT,
        "version": WEIGHTS_VERSION,
        "algorithm": name,
        "observation_space": _encode_space(model.observation_space),
        "action_space": _encode_space(model.action_space),
        "policy": _policy_alias(model),
        "policy_kwargs": _encode_policy_kwargs(model.policy_kwargs),
        "hyperparameters": hyperparameters,
        "not_saved": not_saved,
    }


def _tensor_bytes(tensors: dict[str, th.Tensor]) -> bytes:
    buffer = io.BytesIO()
    th.save({key: tensor.detach().cpu() for key, tensor in tensors.items()}, buffer)
    return buffer.getvalue()


def save_weights(model: BaseAlgorithm, path: str | os.PathLike[str]) -> Path:
    """Write ``model`` as one weights-only zip (a JSON config and tensor dicts; loading it never unpickles).

    :param model: a model of one of :func:`weights_algorithms`.
    :param path: the file to write (atomically; no suffix is added).
    :return: the written path.
    """
    config = json.dumps(weights_config(model), indent=1)
    policy = _tensor_bytes(model.policy.state_dict())
    variables = _tensor_bytes({name: recursive_getattr(model, name) for name in model._get_torch_save_params()[1]})

    def write(tmp: Path) -> None:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as archive:
            archive.writestr(CONFIG_ENTRY, config)
            archive.writestr(POLICY_ENTRY, policy)
            archive.writestr(VARIABLES_ENTRY, variables)

    return atomic_write(path, write)


def _read_tensors(archive: zipfile.ZipFile, entry: str, name: str, device: th.device | str) -> dict[str, th.Tensor]:
    try:
        tensors = th.load(io.BytesIO(archive.read(entry)), map_location=device, weights_only=True)
    except Exception as error:  # torch raises UnpicklingError, RuntimeError, ... for anything but plain tensor data
        raise ValueError(f"{name}: {entry} is not a plain tensor dict (refused without unpickling): {error}") from error
    if not isinstance(tensors, dict) or not all(
        isinstance(key, str) and isinstance(value, th.Tensor) for key, value in tensors.items()
    ):
        raise ValueError(f"{name}: {entry} must hold a dict of named tensors")
    check_finite(tensors, f"{name}: {entry}")
    return tensors


def check_finite(tensors: dict[str, th.Tensor], where: str) -> None:
    """``ValueError`` naming ``where`` and the tensor when a floating-point tensor holds NaN or infinite values."""
    for key, tensor in tensors.items():
        if tensor.is_floating_point() and not bool(th.isfinite(tensor).all()):
            raise ValueError(f"{where}: {key} holds NaN or infinite values (refused: a model must have finite weights)")


def _size_errors(value: Any, where: str) -> list[str]:
    """Sizes in a ``policy_kwargs`` value outside the bounds: lists longer than MAX_LAYERS, integers outside
    [0, MAX_LAYER_WIDTH] (layer widths at least 1)."""
    if isinstance(value, dict):
        return [error for key, item in value.items() for error in _size_errors(item, f"{where}[{key!r}]")]
    if isinstance(value, list):
        head = [f"{where} has {len(value)} items (at most {MAX_LAYERS})"] if len(value) > MAX_LAYERS else []
        return head + [error for i, item in enumerate(value[:MAX_LAYERS]) for error in _size_errors(item, where)]
    low = 1 if "net_arch" in where else 0
    if isinstance(value, int) and not isinstance(value, bool) and not low <= value <= MAX_LAYER_WIDTH:
        return [f"{where} = {value} is outside [{low}, {MAX_LAYER_WIDTH}]"]
    return []


def _count_errors(mapping: dict[str, Any], bounds: dict[str, int], where: str) -> list[str]:
    """Counts in ``mapping`` that are not numbers in [1, bound]."""
    errors = []
    for key, bound in bounds.items():
        value = mapping.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                  or not 1 <= value <= bound):
            errors.append(f"{where}[{key!r}] = {str(value)[:40]} is outside [1, {bound:,}]")
    return errors


def _hidden_parameters(policy_kwargs: dict[str, Any]) -> int:
    """A lower bound on the policy's parameters from its ``net_arch``: the weights between consecutive hidden layers,
    the ``qf`` network's once per critic."""
    arch = policy_kwargs.get("net_arch")
    nets = arch.items() if isinstance(arch, dict) else [("", arch)]
    critics = policy_kwargs.get("n_critics", 1)
    total = 0
    for key, net in nets:
        widths = [width for width in net if isinstance(width, int)] if isinstance(net, list) else []
        total += sum(a * b for a, b in zip(widths, widths[1:])) * (critics if key == "qf" else 1)
    return total


def _space_size(encoded: Any) -> int:
    """Elements of a stored Box space (0 when the description is malformed: :func:`_decode_space` says why)."""
    shape = encoded.get("shape") if isinstance(encoded, dict) else None
    if not isinstance(shape, list) or not all(isinstance(size, int) and size >= 0 for size in shape):
        return 0
    return math.prod(shape[:MAX_LAYERS])


def _buffer_errors(config: dict[str, Any]) -> list[str]:
    """Buffers the hyperparameters size larger than :data:`MAX_BUFFER_BYTES` for the stored spaces."""
    per_item = 4 * (2 * _space_size(config.get("observation_space")) + _space_size(config.get("action_space")))
    hyperparameters = config.get("hyperparameters", {})
    return [f"hyperparameters[{key!r}] = {hyperparameters[key]:,} asks for a {hyperparameters[key] * per_item:,}-byte "
            f"buffer (at most {MAX_BUFFER_BYTES:,})" for key in ("buffer_size", "query_buffer_size", "n_steps")
            if hyperparameters.get(key, 0) * per_item > MAX_BUFFER_BYTES]


def check_config_bounds(config: dict[str, Any], name: str, policy_bytes: int) -> None:
    """``ValueError`` naming the file when a size in a weights config is outside the documented bounds, or when its
    networks need more weights than its ``policy.pt`` (``policy_bytes`` uncompressed) can hold; nothing is allocated.
    """
    policy_kwargs = config.get("policy_kwargs", {})
    hyperparameters = config.get("hyperparameters", {})
    if not isinstance(policy_kwargs, dict) or not isinstance(hyperparameters, dict):
        raise ValueError(f"{name}: policy_kwargs and hyperparameters must be JSON objects")
    errors = _size_errors(policy_kwargs, "policy_kwargs")
    errors += _count_errors(policy_kwargs, {"n_critics": MAX_CRITICS, "attend_heads": MAX_ATTENTION_HEADS},
                            "policy_kwargs")
    errors += _count_errors(hyperparameters, MAX_HYPERPARAMETERS, "hyperparameters")
    errors += [f"{key} has {_space_size(config.get(key)):,} elements (at most {MAX_SPACE_SIZE})"
               for key in ("observation_space", "action_space") if _space_size(config.get(key)) > MAX_SPACE_SIZE]
    errors = errors or _buffer_errors(config)
    if errors:
        raise ValueError(f"{name}: {'; '.join(errors[:3])} (refused before building the model)")
    needed = 4 * _hidden_parameters(policy_kwargs)
    if needed > policy_bytes:
        raise ValueError(f"{name}: its net_arch needs at least {needed:,} bytes of weights, its {POLICY_ENTRY} holds "
                         f"{policy_bytes:,} (refused before building the model)")


def _read_config(archive: zipfile.ZipFile, name: str) -> dict[str, Any]:
    try:
        config = json.loads(archive.read(CONFIG_ENTRY).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{name}: {CONFIG_ENTRY} is not valid JSON: {error}") from error
    if not isinstance(config, dict) or config.get("format") != WEIGHTS_FORMAT:
        raise ValueError(f"{name}: {CONFIG_ENTRY} is not a {WEIGHTS_FORMAT} config")
    if config.get("version") != WEIGHTS_VERSION:
        raise ValueError(f"{name}: weights format version {config.get('version')!r}, this code reads {WEIGHTS_VERSION}")
    return config


def load_weights(path: str | os.PathLike[str], env: Any = None, device: th.device | str = "cpu") -> BaseAlgorithm:
    """Rebuild a model from a :func:`save_weights` file; nothing in the file is unpickled or executed.

    :param path: the weights file.
    :param env: optional env (its spaces must match the stored ones); without it the model can ``predict`` only.
    :param device: device of the rebuilt model.
    :return: the model, with its policy weights and pytorch variables (entropy coefficient, ...) loaded.
    """
    name = str(path)
    entries = check_zip_entries(Path(path), name, (), bounded=True)
    if CONFIG_ENTRY not in entries or POLICY_ENTRY not in entries:
        hint = " (an SB3 model zip: load it with vafn_sb3.loading.load_model)" if "data" in entries else ""
        raise ValueError(f"{name} is not a weights file: it needs {CONFIG_ENTRY} and {POLICY_ENTRY}{hint}")
    with zipfile.ZipFile(path) as archive:
        config = _read_config(archive, name)
        check_config_bounds(config, name, archive.getinfo(POLICY_ENTRY).file_size)
        policy_state = _read_tensors(archive, POLICY_ENTRY, name, device)
        variables = _read_tensors(archive, VARIABLES_ENTRY, name, device) if VARIABLES_ENTRY in entries else {}

    algorithms = weights_classes()
    cls = algorithms.get(config.get("algorithm"))  # type: ignore[arg-type]
    if cls is None:
        raise ValueError(f"{name}: unknown algorithm {config.get('algorithm')!r}; supported: {sorted(algorithms)}")
    policy = config.get("policy")
    if policy not in cls.policy_aliases:
        raise ValueError(f"{name}: {cls.__name__} has no policy alias {policy!r} ({sorted(cls.policy_aliases)})")
    hyperparameters = config.get("hyperparameters", {})
    if not isinstance(hyperparameters, dict):
        raise ValueError(f"{name}: hyperparameters must be a JSON object")
    unknown = set(hyperparameters) - _hyperparameter_names(cls)
    if unknown:
        raise ValueError(f"{name}: unknown {cls.__name__} hyperparameters {sorted(unknown)}")
    observation_space = _decode_space(config.get("observation_space"))
    action_space = _decode_space(config.get("action_space"))
    policy_kwargs = _decode_policy_kwargs(config.get("policy_kwargs", {}))

    # every algorithm of the registry takes _init_setup_model (SB3's off- and on-policy bases)
    model = cls(policy=policy, env=env, device=device, policy_kwargs=policy_kwargs, _init_setup_model=False)  # type: ignore[call-arg]
    if env is None:
        model.observation_space, model.action_space, model.n_envs = observation_space, action_space, 1
    elif model.env is not None:  # set from env by the constructor
        check_for_correct_spaces(model.env, observation_space, action_space)
    # SB3 tuples (train_freq) arrive as JSON lists; SB3 accepts tuples wherever it takes a top-level sequence.
    model.__dict__.update({key: tuple(value) if isinstance(value, list) else value
                           for key, value in hyperparameters.items()})
    model._setup_model()
    try:
        model.policy.load_state_dict(policy_state)
    except RuntimeError as error:
        raise ValueError(f"{name}: the weights do not fit the architecture of the config: {error}") from error
    expected = set(model._get_torch_save_params()[1])
    if set(variables) - expected:
        raise ValueError(f"{name}: unexpected variables {sorted(set(variables) - expected)}")
    for key, tensor in variables.items():
        recursive_setattr(model, f"{key}.data", tensor)
    return model
