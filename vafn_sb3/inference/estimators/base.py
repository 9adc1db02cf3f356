"""What the target estimators share: reading counts, refinement settings, seeded networks and the saved format."""

from __future__ import annotations

import pickle
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm.auto import tqdm

from vafn_sb3.common.adaptation import seeded_torch_stream

__all__ = ["ESTIMATOR_READINGS", "REFINE_SOLVER", "REFINE_SOLVERS", "REFINE_STEPS", "Estimator",
           "FirstReadingsEstimator", "fit_minibatches", "seeded_mlp"]

#: What an inference policy calls on a waypoint's readings so far, ``(points, distances)``: a target, or None (not yet).
Estimator = Callable[[Sequence[np.ndarray], Sequence[float]], "np.ndarray | None"]

#: Readings a ``LearnedTargetEstimator`` reads by default: the first and one after each probe move, which do not
#: depend on the policy it serves (later ones do: an estimator trained on them is tied to one policy).
ESTIMATOR_READINGS = 4

#: How ``GradientTargetEstimator.refine`` steps on its three numbers: Gauss-Newton steps (the default: the readings
#: of an approach lie nearly on a line, so plain gradient steps barely move the estimate across it) or gradient steps.
REFINE_SOLVERS = ("gauss-newton", "gradient")
#: The refinement solver ``GradientInferencePolicy`` uses by default.
REFINE_SOLVER = "gauss-newton"
#: Refinement steps per later reading of each solver, by default.
REFINE_STEPS = {"gauss-newton": 1, "gradient": 5}


def seeded_mlp(n_in: int, hidden: Sequence[int], n_out: int, activation: type[nn.Module], seed: int) -> nn.Sequential:
    """``Linear`` layers with ``activation`` between them, initialised from ``seed`` (the caller's stream untouched)."""
    sizes = [n_in, *hidden]
    with seeded_torch_stream(seed):
        layers: list[nn.Module] = []
        for size_in, size_out in zip(sizes[:-1], sizes[1:]):
            layers += [nn.Linear(size_in, size_out), activation()]
        return nn.Sequential(*layers, nn.Linear(sizes[-1], n_out))


def fit_minibatches(
    parameters: Sequence[torch.Tensor], batch_loss: Callable[[torch.Tensor], torch.Tensor], n: int, epochs: int,
    batch_size: int, lr: float, seed: int, description: str, progress: bool,
) -> list[float]:
    """Adam, cosine schedule, ``batch_loss(indices)`` over seeded shuffles of ``n`` rows; the mean loss per epoch."""
    optimizer = torch.optim.Adam(parameters, lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=epochs)
    generator = torch.Generator().manual_seed(seed)
    losses = []
    for _ in tqdm(range(epochs), desc=description, disable=not progress):
        total = 0.0
        for batch in torch.randperm(n, generator=generator).split(batch_size):
            loss = batch_loss(batch)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            total += loss.item() * len(batch)
        schedule.step()
        losses.append(total / n)
    return losses


class FirstReadingsEstimator:
    """What the target estimators share: they read a waypoint's first ``n_readings`` (position, distance) readings
    and keep a network, its standardisation statistics and their sizes in one weights-only ``torch.save`` file.

    Subclasses build ``self.net`` and ``self.stats`` and implement ``predict(points, distances)``.
    """

    net: nn.Module
    stats: dict[str, np.ndarray]

    def __init__(self, n_readings: int, hidden: Sequence[int]) -> None:
        if n_readings < 4:
            raise ValueError(f"n_readings must be at least 4 (a point in space needs four distances), got {n_readings}")
        self.n_readings = int(n_readings)
        self.hidden = tuple(int(size) for size in hidden)

    def predict(self, points: np.ndarray, distances: np.ndarray) -> np.ndarray:
        """Targets ``(N, 3)`` of a batch of readings ``points (N, R, 3)``, ``distances (N, R)``."""
        raise NotImplementedError

    def __call__(self, points: Sequence[np.ndarray], distances: Sequence[float]) -> np.ndarray | None:
        """The target of one waypoint's readings (its first ``n_readings``), or None before that many."""
        n = self.n_readings
        if len(points) < n:
            return None
        return self.predict(np.asarray(points[:n])[None], np.asarray(distances[:n])[None])[0]

    def _training_readings(
        self, points: np.ndarray, distances: np.ndarray, targets: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``fit``'s arrays as float64, cut to the first ``n_readings`` (``ValueError`` if their lengths differ)."""
        points, targets = np.asarray(points, dtype=np.float64), np.asarray(targets, dtype=np.float64)
        points, distances = points[:, : self.n_readings], np.asarray(distances, dtype=np.float64)[:, : self.n_readings]
        if not (len(points) == len(distances) == len(targets)) or len(points) < 2:
            raise ValueError(f"need as many readings as targets, at least 2: {len(points)}, {len(distances)}, "
                             f"{len(targets)}")
        return points, distances, targets

    def _saved_extras(self) -> dict[str, Any]:
        """What a subclass saves besides the sizes, weights and statistics."""
        return {}

    def save(self, path: str | Path) -> None:
        """Weights, layer sizes and standardisation statistics (and a subclass's extras) in one ``torch.save`` file."""
        stats = {key: torch.as_tensor(value, dtype=torch.float64) for key, value in self.stats.items()}
        torch.save({"n_readings": self.n_readings, "hidden": list(self.hidden), "state_dict": self.net.state_dict(),
                    "stats": stats, **self._saved_extras()}, path)

    @classmethod
    def _from_saved(cls, saved: dict[str, Any]) -> FirstReadingsEstimator:
        """An estimator of the saved sizes (a subclass also restores its extras here)."""
        return cls(saved["n_readings"], saved["hidden"])

    @classmethod
    def _load(cls, path: str | Path) -> Any:
        """The estimator :meth:`save` wrote to ``path`` (tensors and numbers only: a file carrying code is refused)."""
        try:
            saved = torch.load(path, map_location="cpu", weights_only=True)
            estimator = cls._from_saved(saved)
            estimator.net.load_state_dict(saved["state_dict"])
            estimator.stats = {key: value.double().numpy() for key, value in saved["stats"].items()}
        except (OSError, KeyError, TypeError, RuntimeError, EOFError, pickle.UnpicklingError) as error:
            raise ValueError(f"{path} is not a file of {cls.__name__}.save: {error}") from error
        return estimator
