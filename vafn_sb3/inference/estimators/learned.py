"""A regression estimator: a network from a waypoint's first readings to its target (RMA's adaptation module)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import nn

from vafn_sb3.inference.estimators.base import ESTIMATOR_READINGS, FirstReadingsEstimator, fit_minibatches, seeded_mlp

__all__ = ["LearnedTargetEstimator"]


class LearnedTargetEstimator(FirstReadingsEstimator):
    """A network from the first ``n_readings`` (position, distance) readings of a waypoint to its target.

    Input: the later positions relative to the first, the later distances relative to the first, and the first
    distance; output: the target relative to the first position (so it is translation-invariant by construction,
    nothing else is assumed). Inputs and outputs are standardised with the training set's statistics, which
    :meth:`fit` stores with the weights.

    :param n_readings: readings it reads (at least 4: fewer cannot determine a point in space).
    :param hidden: hidden layer sizes.
    :param seed: seed of the initial weights.
    """

    def __init__(self, n_readings: int = ESTIMATOR_READINGS, hidden: Sequence[int] = (256, 256), seed: int = 0) -> None:
        super().__init__(n_readings, hidden)
        n_in = 4 * self.n_readings - 3
        self.net = seeded_mlp(n_in, self.hidden, 3, nn.ReLU, seed)
        self.stats = {"x_mean": np.zeros(n_in), "x_std": np.ones(n_in), "y_mean": np.zeros(3), "y_std": np.ones(3)}

    @staticmethod
    def features(points: np.ndarray, distances: np.ndarray) -> np.ndarray:
        """Network inputs ``(..., 4 R - 3)`` of ``R`` readings: ``points (..., R, 3)``, ``distances (..., R)``."""
        points, distances = np.asarray(points, dtype=np.float64), np.asarray(distances, dtype=np.float64)
        offsets = points[..., 1:, :] - points[..., :1, :]
        # changes of the reading, not readings: they are millimetres on a ~40 cm reading, lost in its scale otherwise
        changes = distances[..., 1:] - distances[..., :1]
        return np.concatenate([offsets.reshape(*offsets.shape[:-2], -1), changes, distances[..., :1]], axis=-1)

    def predict(self, points: np.ndarray, distances: np.ndarray) -> np.ndarray:
        """Targets ``(N, 3)`` of a batch of readings ``points (N, R, 3)``, ``distances (N, R)`` (R = ``n_readings``)."""
        x = (self.features(points, distances) - self.stats["x_mean"]) / self.stats["x_std"]
        with torch.no_grad():
            y = self.net(torch.as_tensor(x, dtype=torch.float32)).double().numpy()
        return np.asarray(points, dtype=np.float64)[:, 0] + y * self.stats["y_std"] + self.stats["y_mean"]

    def fit(
        self, points: np.ndarray, distances: np.ndarray, targets: np.ndarray, epochs: int = 200,
        batch_size: int = 256, lr: float = 1e-3, seed: int = 0, progress: bool = True,
    ) -> list[float]:
        """Regress ``targets (N, 3)`` on readings ``points (N, R, 3)``, ``distances (N, R)``; mean loss per epoch."""
        points, distances, targets = self._training_readings(points, distances, targets)
        x = self.features(points, distances)
        y = targets - points[:, 0]
        self.stats = {"x_mean": x.mean(0), "x_std": x.std(0) + 1e-8, "y_mean": y.mean(0), "y_std": y.std(0) + 1e-8}
        x_t = torch.as_tensor((x - self.stats["x_mean"]) / self.stats["x_std"], dtype=torch.float32)
        y_t = torch.as_tensor((y - self.stats["y_mean"]) / self.stats["y_std"], dtype=torch.float32)
        return fit_minibatches(list(self.net.parameters()),
                               lambda batch: nn.functional.mse_loss(self.net(x_t[batch]), y_t[batch]), len(x_t),
                               epochs, batch_size, lr, seed, "fitting the target estimator", progress)

    @classmethod
    def load(cls, path: str | Path | None = None) -> LearnedTargetEstimator:
        """An estimator saved by :meth:`save` (tensors and numbers only: a file carrying code is refused, not run).

        :param path: the file; None loads the packaged estimator of ``VAFN/ThreeArmReachHidden-v1`` (its training
            command and held-out error are in the JSON file beside it).
        """
        if path is None:
            from vafn_sb3.pretrained import PRETRAINED_ESTIMATOR

            path = PRETRAINED_ESTIMATOR
        return cls._load(path)
