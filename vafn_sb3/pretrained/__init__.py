"""Pretrained policies shipped with the package, as weights-only files that cannot execute code when loaded.

Each ``<algo>__<EnvName>.zip`` (written by :func:`vafn_sb3.save_weights`) has a ``<algo>__<EnvName>.json`` beside it
with the training command, its wall/CPU time and the held-out evaluation of exactly that file
(``benchmarks/export_pretrained.py`` writes both).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import gymnasium as gym

PRETRAINED_DIR = Path(__file__).resolve().parent
#: Held-out success below which loading a packaged policy warns: it is shipped for a figure, not to be used.
WORKING_SUCCESS = 0.95
#: The shipped :class:`~vafn_sb3.LearnedTargetEstimator` of the hidden-target env (``LearnedTargetEstimator.load()``),
#: with its training command and held-out error in the JSON file beside it.
PRETRAINED_ESTIMATOR = PRETRAINED_DIR / "estimators" / "target_estimator__VAFN-ThreeArmReachHidden-v1.pt"
#: The shipped :class:`~vafn_sb3.GradientTargetEstimator` of the hidden-target env (``GradientTargetEstimator.load()``),
#: with its meta-training command and held-out error per gradient step in the JSON file beside it.
PRETRAINED_GRADIENT_ESTIMATOR = PRETRAINED_DIR / "estimators" / "gradient_estimator__VAFN-ThreeArmReachHidden-v1.pt"


def available_pretrained() -> list[tuple[str, str]]:
    """Every shipped ``(algo, env_id)`` pair."""
    pairs = []
    for meta in sorted(PRETRAINED_DIR.glob("*.json")):
        info = json.loads(meta.read_text())
        pairs.append((info["algo"], info["env_id"]))
    return pairs


def pretrained_info(algo: str, env_id: str = "VAFN/ThreeArmReach-v1") -> dict[str, Any]:
    """The metadata of a shipped policy: training command, wall/CPU time, held-out evaluation."""
    path = pretrained_path(algo, env_id).with_suffix(".json")
    if not path.is_file():
        listing = ", ".join(f"{a} on {e}" for a, e in available_pretrained()) or "none"
        raise ValueError(f"no pretrained {algo!r} policy for {env_id!r}; available: {listing}")
    return json.loads(path.read_text())


def load_pretrained(algo: str, env_id: str = "VAFN/ThreeArmReach-v1", env: gym.Env | None = None) -> Any:
    """The shipped policy of ``algo`` for ``env_id`` as an SB3 model (``ValueError`` listing what is available).

    :param algo: zoo key of the algorithm, e.g. ``"sac"`` or ``"maml_sac"``.
    :param env_id: the env it was trained on.
    :param env: optionally attach an env (needed only to continue training).
    """
    from vafn_sb3.common.serialization import load_weights

    info = pretrained_info(algo, env_id)  # the clear error for unknown pairs
    success = info["evaluation"]["success"]
    if success < WORKING_SUCCESS:
        note = info.get("note", "it is shipped to reproduce a negative result (see pretrained_info)")
        warnings.warn(f"the packaged {algo} policy of {env_id} completes only {success:.0%} of held-out instructions "
                      f"({info['evaluation']['protocol']}); {note}", stacklevel=2)
    return load_weights(pretrained_path(algo, env_id), env=env)


def pretrained_path(algo: str, env_id: str) -> Path:
    """Where the weights file of ``(algo, env_id)`` lives (or would live)."""
    return PRETRAINED_DIR / f"{algo}__{env_id.replace('/', '-')}.zip"
