"""Adaptation curves: the rows of :func:`vafn_sb3.common.adaptation.evaluate_adaptation` aggregated over seeds, and
their figure.

:func:`aggregate_adaptation` turns rows of several methods and seeds into one :class:`AdaptationCurve` per method and
metric: at every K, each seed's rows are first averaged over tasks, then the mean over seeds gets a 95 % Student-t
confidence interval (rates' intervals clipped to [0, 1]). :func:`plot_adaptation` draws success rate, collision rate
and return against K. ``benchmarks/adaptation.py`` (which ``zoo/reproduce.py`` runs for Fig. 3) uses them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vafn_gym.benchmarks import confidence_half_width

__all__ = [
    "ADAPTATION_METRICS",
    "AdaptationCurve",
    "aggregate_adaptation",
    "plot_adaptation",
]

#: Metric columns of an adaptation row -> axis label, in the order of the figure's panels.
ADAPTATION_METRICS: dict[str, str] = {
    "success_rate": "success rate",
    "collision_rate": "collision rate",
    "return_mean": "average return",
}
#: Metrics whose confidence interval is clipped to [0, 1].
RATE_METRICS = ("success_rate", "collision_rate")


@dataclass(frozen=True)
class AdaptationCurve:
    """One method's metric against K: mean over seeds and its 95 % Student-t interval (arrays aligned with ``k``).

    :param k: the adaptation steps, ascending.
    :param mean: mean over seeds of each seed's task mean.
    :param half_width: Student-t half width of that mean (0 with one seed), before any clipping.
    :param low: lower end of the interval (clipped to [0, 1] for rates).
    :param high: upper end of the interval (clipped to [0, 1] for rates).
    :param n_seeds: number of seeds.
    :param n_tasks: rows (tasks) per seed at the smallest K.
    """

    k: np.ndarray
    mean: np.ndarray
    half_width: np.ndarray
    low: np.ndarray
    high: np.ndarray
    n_seeds: int
    n_tasks: int


def aggregate_adaptation(
    rows: Sequence[Mapping[str, Any]], group: str = "method"
) -> dict[str, dict[str, AdaptationCurve]]:
    """``{metric: {method: curve}}`` of adaptation rows (methods in order of first appearance; ``group`` names them).

    Every row needs ``group``, ``seed``, ``k`` and the :data:`ADAPTATION_METRICS` columns (one row per task, as
    :func:`~vafn_sb3.common.adaptation.evaluate_adaptation` returns, with the method and seed added). Every seed of a
    method must have rows at every K of that method (``ValueError`` otherwise).
    """
    if not rows:
        raise ValueError("no adaptation rows to aggregate")
    curves: dict[str, dict[str, AdaptationCurve]] = {metric: {} for metric in ADAPTATION_METRICS}
    for method in dict.fromkeys(row[group] for row in rows):
        cells: dict[tuple[int, int], list[Mapping[str, Any]]] = {}
        for row in rows:
            if row[group] == method:
                cells.setdefault((row["seed"], row["k"]), []).append(row)
        seeds = sorted({seed for seed, _ in cells})
        ks = sorted({k for _, k in cells})
        missing = [(seed, k) for seed in seeds for k in ks if (seed, k) not in cells]
        if missing:
            raise ValueError(f"{method}: no rows for (seed, K) in {missing}; every seed needs every K")
        for metric in ADAPTATION_METRICS:
            per_seed = np.array([[np.mean([row[metric] for row in cells[seed, k]]) for k in ks] for seed in seeds])
            mean, half = per_seed.mean(axis=0), confidence_half_width(per_seed)
            low, high = mean - half, mean + half
            if metric in RATE_METRICS:
                low, high = np.clip(low, 0.0, 1.0), np.clip(high, 0.0, 1.0)
            curves[metric][method] = AdaptationCurve(
                np.array(ks), mean, half, low, high, len(seeds), len(cells[seeds[0], ks[0]])
            )
    return curves


def plot_adaptation(
    curves: Mapping[str, Mapping[str, AdaptationCurve]],
    path: str | Path,
    title: str = "",
    references: Sequence[str] = (),
) -> Path:
    """Success rate, collision rate and return against K in one PNG, one colour per method; returns ``path``.

    Methods with more than one K are lines with markers and a shaded 95 % interval (when they have several seeds).
    Methods evaluated at a single K, and the ``references`` (e.g. the scripted ceiling and the random floor), are
    horizontal lines at their first K's value across the K range: dashed for the references, dotted for the others.
    When every method is evaluated at K = 0 only (a zero-shot panel), each metric is one bar per method with its
    95 % interval instead, so that methods at the same value do not hide each other; references are hatched.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    k_max = max((float(curve.k.max()) for per_method in curves.values() for curve in per_method.values()), default=0)
    span = np.array([0.0, max(k_max, 1.0)])  # where the horizontal lines run
    n_methods = max((len(per_method) for per_method in curves.values()), default=0)
    fig, axes = plt.subplots(1, len(ADAPTATION_METRICS), figsize=(14, 4))
    colours = plt.get_cmap("tab10" if n_methods <= 10 else "tab20")  # one colour per method, never repeated
    for ax, (metric, label) in zip(axes, ADAPTATION_METRICS.items(), strict=True):
        methods = curves.get(metric, {})
        for index, (method, curve) in enumerate(methods.items()):
            style = {"color": colours(index % colours.N), "label": f"{method} (n={curve.n_seeds})"}
            band = curve.n_seeds > 1
            if k_max == 0:
                error = [[curve.mean[0] - curve.low[0]], [curve.high[0] - curve.mean[0]]] if band else None
                ax.bar(index, curve.mean[0], yerr=error, capsize=3, hatch="//" if method in references else None,
                       edgecolor="black", linewidth=0.5, **style)
            elif method in references or len(curve.k) == 1:
                ax.plot(span, np.repeat(curve.mean[0], 2), ls="--" if method in references else ":", **style)
                if band:
                    ax.fill_between(span, curve.low[0], curve.high[0], color=style["color"], alpha=0.15)
            else:
                ax.plot(curve.k, curve.mean, marker="o", ms=3, **style)
                if band:
                    ax.fill_between(curve.k, curve.low, curve.high, color=style["color"], alpha=0.15)
        if k_max == 0:
            ax.set_xticks(range(len(methods)), list(methods), rotation=45, ha="right", fontsize=7)
            ax.set_xlabel("zero-shot (K = 0)")
        else:
            ax.set_xscale("symlog", linthresh=1)
            ax.set_xlabel("adaptation steps K")
        ax.set_ylabel(label)
        if metric in RATE_METRICS:
            ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    # One legend beside the panels, so that no curve is hidden behind it.
    fig.legend(*axes[0].get_legend_handles_labels(), loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path
