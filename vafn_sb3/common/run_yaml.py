"""Safe loading of the ``config.yml`` / ``args.yml`` files that rl_zoo3 writes into a run folder.

rl_zoo3 dumps them with ``yaml.dump``, so they carry a few Python tags (an ``OrderedDict``, tuples, activation or
optimiser classes inside ``policy_kwargs``). Reading them with ``yaml.UnsafeLoader`` lets anyone who can write into a
shared run folder run code; :class:`RunConfigLoader` is a ``SafeLoader`` that understands only those tags.
(``zoo/run_config.py`` re-exports this module; ``vafn_sb3.loading`` reads a run's ``config.yml`` with it.)
"""

from __future__ import annotations

import importlib
from collections import OrderedDict
from pathlib import Path
from typing import Any

import yaml

PYTHON_TAG = "tag:yaml.org,2002:python/"
#: Modules whose classes a ``!!python/name:`` tag may name, with the base class the named object must derive from.
ALLOWED_NAME_MODULES: dict[str, tuple[str, str]] = {
    "torch.nn.modules.activation": ("torch.nn", "Module"),
    "torch.optim": ("torch.optim", "Optimizer"),
}


class RunConfigLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` plus the Python tags rl_zoo3 writes: OrderedDict, tuple and allow-listed torch classes."""


def _construct_tuple(loader: yaml.Loader, node: yaml.Node) -> tuple:
    return tuple(loader.construct_sequence(node, deep=True))


def _construct_ordered_dict(loader: yaml.Loader, node: yaml.Node) -> OrderedDict:
    # yaml.dump writes OrderedDict(items) as ``!!python/object/apply:collections.OrderedDict [[[key, value], ...]]``.
    if not isinstance(node, yaml.SequenceNode):
        raise yaml.constructor.ConstructorError(None, None, "expected OrderedDict's argument list", node.start_mark)
    args = loader.construct_sequence(node, deep=True)
    if len(args) > 1:
        raise yaml.constructor.ConstructorError(None, None, "OrderedDict takes at most one argument", node.start_mark)
    return OrderedDict(*args)


def _allowed_module(module_name: str) -> tuple[str, str] | None:
    for allowed, base in ALLOWED_NAME_MODULES.items():
        if module_name == allowed or module_name.startswith(allowed + "."):
            return base
    return None


def resolve_allowed_name(dotted: str) -> type:
    """The class ``dotted`` (``module.Class``) if its module is allow-listed and it derives from the expected base."""
    module_name, _, attr = dotted.rpartition(".")
    base = _allowed_module(module_name)
    if base is None or not attr.isidentifier() or attr.startswith("_"):
        raise yaml.constructor.ConstructorError(None, None, f"refusing to load the Python name {dotted!r}")
    obj = getattr(importlib.import_module(module_name), attr, None)
    base_class = getattr(importlib.import_module(base[0]), base[1])
    if not (isinstance(obj, type) and issubclass(obj, base_class)):
        raise yaml.constructor.ConstructorError(None, None, f"{dotted!r} is not a {base[0]}.{base[1]} class")
    return obj


def _construct_name(loader: yaml.Loader, suffix: str, node: yaml.Node) -> type:
    if loader.construct_scalar(node):
        raise yaml.constructor.ConstructorError(None, None, "a !!python/name tag takes an empty value", node.start_mark)
    return resolve_allowed_name(suffix)


RunConfigLoader.add_constructor(PYTHON_TAG + "tuple", _construct_tuple)
RunConfigLoader.add_constructor(PYTHON_TAG + "object/apply:collections.OrderedDict", _construct_ordered_dict)
RunConfigLoader.add_multi_constructor(PYTHON_TAG + "name:", _construct_name)


def load_run_yaml(text: str) -> Any:
    """Parse rl_zoo3 run YAML (``config.yml``, ``args.yml``) without executing any other Python tag."""
    return yaml.load(text, Loader=RunConfigLoader)  # noqa: S506 - RunConfigLoader is a SafeLoader subclass


def load_run_config(path: str | Path) -> dict[str, Any]:
    """The hyperparameters saved in a run's ``config.yml`` (an empty dict for an empty file)."""
    config = load_run_yaml(Path(path).read_text())
    if config is None:
        return {}
    if not isinstance(config, dict):
        raise ValueError(f"{path}: expected a mapping of hyperparameters, got {type(config).__name__}")
    return config
