"""Compare algorithms across seeds: return, success rate and collision rate against steps, mean ± 95 % CI.

Reads TensorBoard event files (the zoo's ``-tb`` layout ``<tb>/<EnvName>/<ALGO>_<N>/events.*``) and/or the zoo's
evaluation logs (``<logs>/<algo>/<EnvName>_<N>/evaluations.npz``) and writes one PNG per metric plus a CSV of the
curves:

    python zoo/plot.py --tb tb/VAFN-ThreeArmReach-v0 --out results/training
    python zoo/plot.py --logs logs --env VAFN/ThreeArmReach-v0 --out results/training

A run's algorithm is its folder name without the trailing ``_<N>`` (TensorBoard) or its parent folder (logs); every
run of one algorithm counts as one seed. Curves are interpolated onto a common step grid up to the shortest run.
"""

from __future__ import annotations

import argparse
import csv
import re
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from vafn_gym.benchmarks import confidence_half_width

#: metric -> TensorBoard tags tried in order (evaluation first, training rollouts as the fallback).
TB_TAGS: dict[str, tuple[str, ...]] = {
    "return": ("eval/mean_reward", "rollout/ep_rew_mean"),
    "success": ("eval/success_rate", "rollout/success_rate"),
    "collision": ("eval/collision_rate", "rollout/collision_rate"),
}
#: metric -> key of the zoo's evaluations.npz.
NPZ_KEYS: dict[str, str] = {"return": "results", "success": "successes", "collision": "collisions"}
RATE_METRICS = ("success", "collision")
LABELS: dict[str, str] = {"return": "episode return", "success": "success rate", "collision": "collision rate"}
GRID_POINTS = 100
RUN_SUFFIX = re.compile(r"_\d+$")


@dataclass
class Curve:
    """One run's metric against environment steps."""

    steps: np.ndarray
    values: np.ndarray


@dataclass
class Aggregate:
    """Mean and confidence band of several runs on a common x grid."""

    x: np.ndarray
    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray
    n_runs: int


def algo_of_run(run_name: str) -> str:
    """``SAC_3`` -> ``SAC``: the zoo's TensorBoard run folder without its counter."""
    return RUN_SUFFIX.sub("", run_name)


def load_tensorboard(paths: Iterable[Path], metrics: Sequence[str]) -> dict[str, dict[str, list[Curve]]]:
    """``{metric: {algo: [curve per run]}}`` from every event-file folder under ``paths``."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    curves: dict[str, dict[str, list[Curve]]] = {m: defaultdict(list) for m in metrics}
    run_dirs = sorted({event.parent for path in paths for event in Path(path).rglob("events.out.tfevents.*")})
    if not run_dirs:
        raise FileNotFoundError(f"no TensorBoard event files under {[str(p) for p in paths]}")
    for run_dir in run_dirs:
        accumulator = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
        accumulator.Reload()
        available = set(accumulator.Tags()["scalars"])
        for metric in metrics:
            tag = next((t for t in TB_TAGS[metric] if t in available), None)
            if tag is None:
                continue
            events = accumulator.Scalars(tag)
            curves[metric][algo_of_run(run_dir.name)].append(
                Curve(np.array([e.step for e in events], float), np.array([e.value for e in events], float))
            )
    return curves


class NoEvaluationsError(FileNotFoundError):
    """A run folder holds no evaluation yet (message says why and what to do)."""


NO_EVAL_HINT = (
    "the zoo evaluates every --eval-freq training steps, so a run with --eval-freq larger than -n (its training "
    "steps) never evaluates; rerun with --eval-freq below -n, or plot the training rollouts with --tb"
)


def load_evaluations(
    log_folder: Path, env_name: str | None, metrics: Sequence[str]
) -> dict[str, dict[str, list[Curve]]]:
    """``{metric: {algo: [curve per run]}}`` from ``<log_folder>/<algo>/<EnvName>_<N>/evaluations.npz``."""
    curves: dict[str, dict[str, list[Curve]]] = {m: defaultdict(list) for m in metrics}
    pattern = f"{env_name}_*/evaluations.npz" if env_name else "*/evaluations.npz"
    files = sorted(Path(log_folder).glob(f"*/{pattern}"))
    if not files:
        runs = sorted(Path(log_folder).glob(f"*/{env_name}_*" if env_name else "*/*_*"))
        found = f"runs {', '.join(str(r) for r in runs[:5])} have" if runs else "no run folder has"
        raise NoEvaluationsError(f"no evaluations yet under {log_folder}/<algo>/{pattern}: {found} no "
                                 f"evaluations.npz; {NO_EVAL_HINT}")
    for file in files:
        data = np.load(file)
        algo = file.parent.parent.name
        for metric in metrics:
            key = NPZ_KEYS[metric]
            if key in data and np.asarray(data[key]).size:
                values = np.asarray(data[key], float).mean(axis=1)
                curves[metric][algo].append(Curve(np.asarray(data["timesteps"], float), values))
    return curves


def aggregate(curves: list[Curve], grid_points: int = GRID_POINTS) -> Aggregate:
    """Interpolate runs onto a common grid (up to the shortest run) and take mean ± 95 % CI over runs."""
    if not curves:
        raise ValueError("no runs to aggregate")
    start = max(c.steps.min() for c in curves)
    stop = min(c.steps.max() for c in curves)
    logged = np.unique(np.concatenate([c.steps[(c.steps >= start) & (c.steps <= stop)] for c in curves]))
    # Few evaluations: keep the logged steps themselves (drawn with markers) instead of a dense interpolated grid.
    x = logged if len(logged) <= grid_points else np.linspace(start, stop, grid_points)
    if not len(x):
        x = np.array([stop])
    return mean_ci(x, np.stack([np.interp(x, c.steps, c.values) for c in curves]))


def mean_ci(x: np.ndarray, stacked: np.ndarray) -> Aggregate:
    """Mean ± 95 % CI over runs (axis 0) of curves already on the common grid ``x``."""
    mean, half = stacked.mean(axis=0), confidence_half_width(stacked)
    return Aggregate(x, mean, mean - half, mean + half, stacked.shape[0])


def plot_metric(
    per_algo: dict[str, Aggregate], ylabel: str, path: Path, title: str = "", xlabel: str = "environment steps",
    rate: bool = False,
) -> Path:
    """One PNG: a mean line and a shaded 95 % CI per algorithm (one colour each)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    colours = plt.get_cmap("tab10")
    for index, (algo, agg) in enumerate(sorted(per_algo.items())):
        colour = colours(index % colours.N)
        ax.plot(
            agg.x, agg.mean, color=colour, label=f"{algo} (n={agg.n_runs})", marker="o" if len(agg.x) < 20 else None
        )
        if agg.n_runs > 1:
            ax.fill_between(agg.x, agg.low, agg.high, color=colour, alpha=0.2)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if rate:
        ax.set_ylim(-0.05, 1.05)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_curves_csv(aggregates: dict[str, dict[str, Aggregate]], path: Path) -> Path:
    """All aggregated curves in one long CSV: metric, algo, x, mean, ci_low, ci_high, n_runs."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["metric", "algo", "x", "mean", "ci_low", "ci_high", "n_runs"])
        for metric, per_algo in aggregates.items():
            for algo, agg in sorted(per_algo.items()):
                for row in zip(agg.x, agg.mean, agg.low, agg.high):
                    writer.writerow([metric, algo, *(f"{v:.6g}" for v in row), agg.n_runs])
    return path


def clip_rate(agg: Aggregate) -> Aggregate:
    """The same aggregate with its CI clipped to [0, 1] (for success and collision rates)."""
    return Aggregate(agg.x, agg.mean, np.clip(agg.low, 0.0, 1.0), np.clip(agg.high, 0.0, 1.0), agg.n_runs)


def make_plots(curves: dict[str, dict[str, list[Curve]]], out: Path, title: str = "") -> list[Path]:
    """Aggregate and plot every metric that has data; returns the written files (PNGs, then the CSV)."""
    aggregates = {
        metric: {
            algo: clip_rate(aggregate(runs)) if metric in RATE_METRICS else aggregate(runs)
            for algo, runs in per_algo.items() if runs
        }
        for metric, per_algo in curves.items()
    }
    aggregates = {metric: per_algo for metric, per_algo in aggregates.items() if per_algo}
    if not aggregates:
        raise ValueError("none of the runs logged return, success or collision")
    written = [
        plot_metric(
            per_algo, LABELS[metric], out.parent / f"{out.name}_{metric}.png", title, rate=metric in RATE_METRICS
        )
        for metric, per_algo in aggregates.items()
    ]
    written.append(write_curves_csv(aggregates, out.parent / f"{out.name}_curves.csv"))
    return written


def _merge(into: dict[str, dict[str, list[Curve]]], other: dict[str, dict[str, list[Curve]]]) -> None:
    for metric, per_algo in other.items():
        for algo, runs in per_algo.items():
            into.setdefault(metric, defaultdict(list))[algo].extend(runs)


def env_names(curves_sources: Sequence[Path], logs: Path | None) -> list[str]:
    """Env names found in the run folders (TensorBoard ``<EnvName>/<ALGO>_<N>``, logs ``<algo>/<EnvName>_<N>``)."""
    names = set()
    for path in curves_sources:
        for event in Path(path).rglob("events.out.tfevents.*"):
            parent = event.parent.parent.name
            if parent.startswith("VAFN-"):
                names.add(parent)
    if logs is not None:
        names.update(algo_of_run(run.name) for run in Path(logs).glob("*/*_*") if run.name.startswith("VAFN-"))
    return sorted(names)


def output_prefix(out: str) -> Path:
    """``--out``: a prefix (``results/training`` -> ``results/training_<metric>.png``); a folder when it ends in
    ``/`` or is an existing folder (``runs/plots/`` -> ``runs/plots/training_<metric>.png``)."""
    path = Path(out)
    return path / "training" if out.endswith(("/", "\\")) or path.is_dir() else path


def main(argv: list[str] | None = None) -> list[Path]:
    """Command-line entry point; returns the written files."""
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--tb", nargs="*", default=[], type=Path, help="TensorBoard folders (searched recursively)")
    parser.add_argument(
        "--logs", type=Path, default=None, help="zoo log folder with <algo>/<EnvName>_<N>/evaluations.npz"
    )
    parser.add_argument("--env", default=None, help="env ID or EnvName to select in --logs (None: all)")
    parser.add_argument("--metrics", nargs="+", default=list(TB_TAGS), choices=list(TB_TAGS), help="what to plot")
    parser.add_argument("--algos", nargs="*", default=None, help="keep only these algorithms (None: all, as labelled)")
    parser.add_argument("--out", default="results/training",
                        help="output prefix: writes <out>_<metric>.png and <out>_curves.csv; ending in / (or an "
                        "existing folder) it is a folder: <out>/training_<metric>.png")
    parser.add_argument("--title", default="", help="plot title (empty: the env name and the sources)")
    args = parser.parse_args(argv)
    if not args.tb and args.logs is None:
        parser.error("give --tb and/or --logs")
    curves: dict[str, dict[str, list[Curve]]] = {m: defaultdict(list) for m in args.metrics}
    try:
        if args.tb:
            _merge(curves, load_tensorboard(args.tb, args.metrics))
        if args.logs is not None:
            env_name = args.env.replace("/", "-") if args.env else None
            _merge(curves, load_evaluations(args.logs, env_name, args.metrics))
        if args.algos:
            wanted = {a.lower() for a in args.algos}
            curves = {m: {a: r for a, r in per_algo.items() if a.lower() in wanted} for m, per_algo in curves.items()}
        envs = [args.env] if args.env else env_names(args.tb, args.logs)
        title = args.title or (", ".join(envs) if envs else "")
        written = make_plots(curves, output_prefix(args.out), title)
    except FileNotFoundError as error:  # NoEvaluationsError included
        parser.exit(1, f"plot.py: {error}\n")
    except ValueError as error:
        parser.exit(1, f"plot.py: {error}; if the runs are new, {NO_EVAL_HINT}\n")
    for path in written:
        print(path)
    return written


if __name__ == "__main__":
    sys.exit(0 if main() else 1)


def plot_online_distances(controller: Any, path: str | Path) -> Path:
    """Each arm's distance to its current target over an :class:`~vafn_sb3.OnlineController` run, phases shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    steps = np.asarray(controller.trace["step"])
    distances = np.asarray(controller.trace["distances"])
    distances = distances.reshape(len(steps), -1) if len(steps) else np.zeros((0, 1))
    fig, ax = plt.subplots(figsize=(12, 4))
    for column in range(distances.shape[1]):
        ax.plot(steps, distances[:, column], lw=1.0, label=f"arm {column + 1}")
    top = float(distances.max()) if len(steps) else 1.0
    for index, entry in enumerate(controller.log):
        if entry.start_step < 0:
            continue
        end = (
            entry.completion_step
            if entry.completion_step >= 0
            else (int(steps[-1]) if len(steps) else entry.start_step)
        )
        colour = "tab:green" if entry.success else "tab:red"
        ax.axvspan(entry.start_step, end, color=colour, alpha=0.12 if index % 2 else 0.2, lw=0)
        ax.text(entry.start_step, top, f"#{entry.sequence} [{entry.instruction}]", fontsize=7, va="top", rotation=90)
    ax.set_xlabel("stream step")
    ax.set_ylabel("distance to current target (m)")
    ax.set_title("Online control: green = instruction succeeded, red = failed/timeout, white = holding")
    ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
