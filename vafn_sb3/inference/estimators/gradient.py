"""Target inference by gradient steps on a context: a meta-learned reading model, adapted per waypoint.

:class:`GradientTargetEstimator` is the gradient-based counterpart of :class:`~vafn_sb3.LearnedTargetEstimator`. Where
that network maps a waypoint's first (position, distance) readings straight to the target, this one holds a *reading
model* ``F(offsets, z) -> readings`` (which readings a target at ``z`` would give along the arm's first moves) and
infers the target by ``K`` gradient steps on ``z`` alone, from a meta-learned start ``z_0``, to make ``F`` reproduce the
readings actually seen. Only the three numbers of ``z`` adapt, never the network: fast context adaptation (CAVIA,
Zintgraf et al., 2019) with per-dimension meta-learned step sizes (Meta-SGD, Li et al., 2017). Meta-training
(:meth:`GradientTargetEstimator.fit`) differentiates through the ``K`` steps so that every step count up to ``K`` lands
near the target the training env knows, and also regresses ``F`` on the true target so that the target is where the
readings are explained (the steps then stay there past ``K``). ``meta=False`` trains the reading model alone and
adapts with plain gradient descent from the mean target at the step size that does best on the training readings: the
"fine-tuning" baseline that shows what the meta-learning adds. Like the regression estimator it is never told that a
reading is ``|p - t|``.

Estimating once from the first readings leaves a few waypoints several centimetres off (the reading model is least
precise where the training targets thin out, at the edges of the target region). :meth:`GradientTargetEstimator.refine`
keeps adapting the same three numbers as the arm moves: a second, per-reading model ``f(offset, z) -> distance``
(:meth:`GradientTargetEstimator.fit_refinement`, fitted by regression on readings along whole approaches, so it reads
any number of readings at any offsets) takes steps on ``z`` over every reading so far, starting from the current
estimate (and from any restart point given). Readings centimetres apart constrain the target far better than the first
millimetre moves. The steps are Gauss-Newton steps by default (the model's Jacobian in ``z`` from one backward pass,
the step a least-squares solve): an arm's readings along its approach lie nearly on a line, so the error is flat
across it and plain gradient steps (``solver="gradient"``) barely move the estimate in that direction.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from vafn_sb3.inference.estimators.base import (
    ESTIMATOR_READINGS,
    REFINE_SOLVER,
    REFINE_SOLVERS,
    FirstReadingsEstimator,
    fit_minibatches,
    seeded_mlp,
)
from vafn_sb3.inference.estimators.learned import LearnedTargetEstimator

__all__ = ["REFINE_MAX_STEP", "REFINE_SCALE", "REFINE_STEP_SIZE", "GradientTargetEstimator"]

#: Length scale (metres) of the refinement model's inputs and output: offsets, contexts and distances are divided by it.
REFINE_SCALE = 0.1
#: Step size of a refinement step, in units of :data:`REFINE_SCALE`.
REFINE_STEP_SIZE = 0.01
#: Longest refinement step, in units of :data:`REFINE_SCALE` (5 cm): a longer one is shortened to it.
REFINE_MAX_STEP = 0.5

#: Step sizes the ``meta=False`` baseline chooses its one step size from (standardised units).
BASELINE_STEP_SIZES = tuple(float(step) for step in np.logspace(-3, 0.5, 15))


class GradientTargetEstimator(FirstReadingsEstimator):
    """Infers a waypoint's target with ``steps`` gradient steps on a 3-number context (see the module docstring).

    :param n_readings: readings it reads (at least 4: fewer cannot determine a point in space).
    :param hidden: hidden layer sizes of the reading model.
    :param steps: gradient steps per inference (``with_steps`` changes it; 0 returns the meta-learned start).
    :param seed: seed of the initial weights.
    """

    def __init__(
        self, n_readings: int = ESTIMATOR_READINGS, hidden: Sequence[int] = (128, 128), steps: int = 20, seed: int = 0
    ) -> None:
        super().__init__(n_readings, hidden)
        if steps < 0:
            raise ValueError(f"steps must be >= 0, got {steps}")
        self.steps = int(steps)
        #: Whether :meth:`fit` meta-learned the start, the step sizes and the reading model (False: the baseline).
        self.meta = True
        # tanh: smooth, its gradient in z is what adapts
        self.net = seeded_mlp(3 * (self.n_readings - 1) + 3, self.hidden, self.n_readings, nn.Tanh, seed)
        self.start = nn.Parameter(torch.zeros(3))
        self.log_step = nn.Parameter(torch.full((3,), math.log(0.1)))
        n_offsets = 3 * (self.n_readings - 1)
        self.stats = {"x_mean": np.zeros(n_offsets), "x_std": np.ones(n_offsets), "r_mean": np.zeros(self.n_readings),
                      "r_std": np.ones(self.n_readings), "z_mean": np.zeros(3), "z_std": np.ones(3)}
        #: The per-reading model :meth:`refine` steps on (None until :meth:`fit_refinement`: no refinement).
        self.reading_net: nn.Sequential | None = None

    def _inputs(self, points: np.ndarray, distances: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Standardised move offsets ``(N, 3 (R - 1))`` and readings ``(N, R)`` of a batch (first ``R`` readings)."""
        n = self.n_readings
        features = LearnedTargetEstimator.features(np.asarray(points)[:, :n], np.asarray(distances)[:, :n])
        return self._standardised(features)

    def _standardised(self, features: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`_inputs` of readings already turned into ``LearnedTargetEstimator.features``."""
        n_offsets = 3 * (self.n_readings - 1)
        offsets = (features[:, :n_offsets] - self.stats["x_mean"]) / self.stats["x_std"]
        readings = (features[:, n_offsets:] - self.stats["r_mean"]) / self.stats["r_std"]
        return torch.as_tensor(offsets, dtype=torch.float32), torch.as_tensor(readings, dtype=torch.float32)

    def _contexts(self, offsets: torch.Tensor, readings: torch.Tensor, steps: int, train: bool) -> list[torch.Tensor]:
        """The context after 0, 1, ..., ``steps`` gradient steps on the reading error (graph kept when ``train``)."""
        z = self.start.expand(len(offsets), 3)
        if not train:
            z = z.detach().requires_grad_(True)
        contexts = [z]
        for _ in range(steps):
            # summed over the batch, so each row's gradient is its own reading error's
            error = ((self.net(torch.cat([offsets, z], dim=1)) - readings) ** 2).sum()
            (gradient,) = torch.autograd.grad(error, z, create_graph=train)
            z = z - self.log_step.exp() * gradient
            if not train:
                z = z.detach().requires_grad_(True)
            contexts.append(z)
        return contexts

    def predict(self, points: np.ndarray, distances: np.ndarray, steps: int | None = None) -> np.ndarray:
        """Targets ``(N, 3)`` of readings ``points (N, R, 3)``, ``distances (N, R)`` after ``steps`` (None: its own)."""
        offsets, readings = self._inputs(points, distances)
        with torch.enable_grad():
            z = self._contexts(offsets, readings, self.steps if steps is None else int(steps), train=False)[-1]
        z = z.detach().double().numpy() * self.stats["z_std"] + self.stats["z_mean"]
        return np.asarray(points, dtype=np.float64)[:, 0] + z

    def with_steps(self, steps: int) -> GradientTargetEstimator:
        """A copy sharing the weights that takes ``steps`` gradient steps per inference."""
        if int(steps) < 0:
            raise ValueError(f"steps must be >= 0, got {steps}")
        adapted = copy.copy(self)
        adapted.steps = int(steps)
        return adapted

    def fit(
        self, points: np.ndarray, distances: np.ndarray, targets: np.ndarray, meta: bool = True, epochs: int = 200,
        batch_size: int = 256, lr: float = 1e-3, seed: int = 0, progress: bool = True,
    ) -> list[float]:
        """Meta-train on readings ``points (N, R, 3)``, ``distances (N, R)`` labelled with ``targets (N, 3)``.

        ``meta=True``: the loss is the context's squared error after each of 1..``steps`` steps (mean over the steps)
        plus the reading model's error at the true target; the start, the step sizes and the reading model all learn.
        ``meta=False``: the reading model's error only; then the start is the mean target and the step size the one of
        :data:`BASELINE_STEP_SIZES` with the smallest error after ``steps`` steps on these readings.
        :return: mean loss per epoch.
        """
        points, distances, targets = self._training_readings(points, distances, targets)
        features = LearnedTargetEstimator.features(points, distances)
        z = targets - points[:, 0]
        n_offsets = 3 * (self.n_readings - 1)
        self.stats = {"x_mean": features[:, :n_offsets].mean(0), "x_std": features[:, :n_offsets].std(0) + 1e-8,
                      "r_mean": features[:, n_offsets:].mean(0), "r_std": features[:, n_offsets:].std(0) + 1e-8,
                      "z_mean": z.mean(0), "z_std": z.std(0) + 1e-8}
        self.meta = bool(meta)
        offsets, readings = self._standardised(features)
        true_z = torch.as_tensor((z - self.stats["z_mean"]) / self.stats["z_std"], dtype=torch.float32)
        parameters = [*self.net.parameters(), *([self.start, self.log_step] if meta else [])]

        def batch_loss(batch: torch.Tensor) -> torch.Tensor:
            x, r, target = offsets[batch], readings[batch], true_z[batch]
            loss = nn.functional.mse_loss(self.net(torch.cat([x, target], dim=1)), r)
            if meta and self.steps > 0:
                contexts = self._contexts(x, r, self.steps, train=True)[1:]
                loss = loss + torch.stack([((c - target) ** 2).sum(1).mean() for c in contexts]).mean()
            return loss

        description = "meta-training the gradient estimator" if meta else "fitting the reading model"
        losses = fit_minibatches(parameters, batch_loss, len(offsets), epochs, batch_size, lr, seed, description,
                                 progress)
        if not meta:
            with torch.no_grad():
                self.start.zero_()  # the mean target, in standardised units
            errors = {}
            for step in BASELINE_STEP_SIZES:
                with torch.no_grad():
                    self.log_step.fill_(math.log(step))
                final = self._contexts(offsets, readings, self.steps, train=False)[-1].detach()
                error = ((final - true_z) ** 2).sum(1).mean().item()
                errors[step] = error if math.isfinite(error) else math.inf
            with torch.no_grad():
                self.log_step.fill_(math.log(min(errors, key=errors.__getitem__)))
        return losses

    @staticmethod
    def _reading_net(hidden: Sequence[int], seed: int) -> nn.Sequential:
        """The refinement model: ``(offset, context)`` (6 numbers) to one distance, smooth in the context."""
        return seeded_mlp(6, hidden, 1, nn.SiLU, seed)

    def fit_refinement(
        self, points: np.ndarray, distances: np.ndarray, targets: np.ndarray, hidden: Sequence[int] = (128, 128, 128),
        epochs: int = 200, batch_size: int = 256, lr: float = 1e-3, seed: int = 0, progress: bool = True,
    ) -> list[float]:
        """Fit the per-reading model :meth:`refine` uses on every reading of ``points (N, R, 3)``, ``distances (N, R)``.

        Each reading is one example: its offset from the waypoint's first position and the target relative to that
        position (``targets (N, 3)``, the label) in, the distance out. Longer readings (e.g. ``R = 24``, a whole
        approach) teach it the offsets the arm reaches after its probe moves. :return: mean loss per epoch.
        """
        points, distances = np.asarray(points, dtype=np.float64), np.asarray(distances, dtype=np.float64)
        targets = np.asarray(targets, dtype=np.float64)
        if points.ndim != 3 or points.shape[:2] != distances.shape or targets.shape != (len(points), 3):
            raise ValueError(f"need points (N, R, 3), distances (N, R), targets (N, 3), got {points.shape}, "
                             f"{distances.shape}, {targets.shape}")
        offsets = (points - points[:, :1]) / REFINE_SCALE
        contexts = np.broadcast_to(((targets - points[:, 0]) / REFINE_SCALE)[:, None], offsets.shape)
        x = torch.as_tensor(np.concatenate([offsets, contexts], -1).reshape(-1, 6), dtype=torch.float32)
        y = torch.as_tensor(distances.reshape(-1, 1) / REFINE_SCALE, dtype=torch.float32)
        self.reading_net = net = self._reading_net(hidden, seed)
        return fit_minibatches(list(net.parameters()), lambda batch: nn.functional.mse_loss(net(x[batch]), y[batch]),
                               len(x), epochs, batch_size, lr, seed, "fitting the refinement model", progress)

    def refine(self, points: Sequence[np.ndarray], distances: Sequence[float], estimate: np.ndarray,
               steps: int, solver: str = REFINE_SOLVER, restarts: Sequence[np.ndarray] = ()) -> np.ndarray:
        """``estimate`` after ``steps`` steps of ``solver`` (one of ``REFINE_SOLVERS``) on the refinement model's error.

        The error is the squared difference between the model's distance and each reading so far. ``"gauss-newton"``:
        each step solves the linearised least-squares problem (minimum norm where the readings leave a direction
        undetermined); ``"gradient"``: each step is ``REFINE_STEP_SIZE`` times the gradient. Either step is shortened
        to ``REFINE_MAX_STEP``. ``restarts``: more points to take the same steps from; of all the results, the one
        whose error is least is returned (a first estimate far off, from readings unlike any in training, is then
        dropped once the readings place the target).
        """
        if self.reading_net is None:
            raise ValueError("this estimator has no refinement model: call fit_refinement first")
        if solver not in REFINE_SOLVERS:
            raise ValueError(f"solver must be one of {REFINE_SOLVERS}, got {solver!r}")
        array = np.asarray(points, dtype=np.float64)
        offsets = torch.as_tensor((array - array[0]) / REFINE_SCALE, dtype=torch.float32)
        readings = torch.as_tensor(np.asarray(distances, dtype=np.float64) / REFINE_SCALE, dtype=torch.float32)
        ends = [self._refined(offsets, readings, torch.as_tensor((np.asarray(start) - array[0]) / REFINE_SCALE,
                                                                 dtype=torch.float32), steps, solver)
                for start in (estimate, *restarts)]
        z = ends[0] if len(ends) == 1 else min(ends, key=lambda end: self._reading_error(offsets, readings, end))
        return array[0] + z.double().numpy() * REFINE_SCALE

    def _refined(self, offsets: torch.Tensor, readings: torch.Tensor, z: torch.Tensor, steps: int,
                 solver: str) -> torch.Tensor:
        """The context after :meth:`refine`'s ``steps`` from ``z`` (scaled units, relative to the first reading)."""
        with torch.enable_grad():
            for _ in range(steps):
                if solver == "gradient":
                    z = z.detach().requires_grad_(True)
                    predicted = self._distances(offsets, z)
                    (gradient,) = torch.autograd.grad(((predicted - readings) ** 2).sum(), z)
                    step = REFINE_STEP_SIZE * gradient
                else:
                    # one copy of z per reading: the gradient of the summed predictions is then the Jacobian, row by row
                    rows = z.detach().expand(len(offsets), 3).clone().requires_grad_(True)
                    predicted = self._distances(offsets, rows)
                    (jacobian,) = torch.autograd.grad(predicted.sum(), rows)
                    residual = (predicted.detach() - readings)[:, None]
                    step = torch.linalg.lstsq(jacobian, residual).solution[:, 0]
                if not torch.isfinite(step).all():
                    break
                # readings far from any the model was fitted on (an arm that wandered) can give huge steps
                z = z.detach() - step * min(1.0, REFINE_MAX_STEP / max(step.norm().item(), 1e-12))
        return z.detach()

    def _distances(self, offsets: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """The refinement model's distance at each offset ``(N, 3)`` with the context ``z``: ``(3,)`` or one per row."""
        assert self.reading_net is not None, "refine checks that a refinement model exists"
        return self.reading_net(torch.cat([offsets, z.expand(len(offsets), 3)], dim=1))[:, 0]

    def _reading_error(self, offsets: torch.Tensor, readings: torch.Tensor, z: torch.Tensor) -> float:
        """The refinement model's squared error over the readings with the context ``z``."""
        with torch.no_grad():
            return float(((self._distances(offsets, z) - readings) ** 2).sum())

    def _saved_extras(self) -> dict[str, Any]:
        """The step count, whether it was meta-learned, the start, the step sizes and the refinement model if any."""
        extras = {"steps": self.steps, "meta": self.meta, "start": self.start.detach(),
                  "log_step": self.log_step.detach()}
        if self.reading_net is not None:
            linear = [layer.out_features for layer in self.reading_net if isinstance(layer, nn.Linear)]
            extras["refinement"] = {"hidden": linear[:-1], "state_dict": self.reading_net.state_dict()}
        return extras

    @classmethod
    def _from_saved(cls, saved: dict[str, Any]) -> GradientTargetEstimator:
        estimator = cls(saved["n_readings"], saved["hidden"], steps=saved["steps"])
        with torch.no_grad():
            estimator.start.copy_(saved["start"])
            estimator.log_step.copy_(saved["log_step"])
        estimator.meta = bool(saved["meta"])
        if "refinement" in saved:  # files saved before refinement existed have none
            estimator.reading_net = cls._reading_net(saved["refinement"]["hidden"], seed=0)
            estimator.reading_net.load_state_dict(saved["refinement"]["state_dict"])
        return estimator

    @classmethod
    def load(cls, path: str | Path | None = None) -> GradientTargetEstimator:
        """An estimator saved by :meth:`save` (tensors and numbers only: a file carrying code is refused, not run).

        :param path: the file; None loads the packaged estimator of ``VAFN/ThreeArmReachHidden-v1``.
        """
        if path is None:
            from vafn_sb3.pretrained import PRETRAINED_GRADIENT_ESTIMATOR

            path = PRETRAINED_GRADIENT_ESTIMATOR
        return cls._load(path)
