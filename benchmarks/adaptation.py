"""Adaptation curves: success, return and collision rate against the number of adaptation steps K on held-out tasks.

Trains a MAML-SAC (or loads one with ``--model``), then runs :func:`vafn_sb3.common.adaptation.evaluate_adaptation`
on ``--n-tasks`` instructions of the *test* split (disjoint from the training orders), for every K in ``--k``. Writes
``adaptation.csv`` (one row per task and K), ``adaptation.png`` and prints the per-K means. Never asserts a number.

Usage (the run behind the numbers in the README)::

    OMP_NUM_THREADS=1 nice -n 10 python benchmarks/adaptation.py --env VAFN/ThreeArmReachHidden-v0 --max-length 2 \\
        --timesteps 300000 --warmup-steps 50000 --out results/maml_sac_hidden
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np
import torch
from stable_baselines3.common.env_util import make_vec_env

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_gym.tasks import TaskSampler, env_task_family
from vafn_sb3.common.adaptation import evaluate_adaptation
from vafn_sb3.maml_sac import MAMLSAC

DEFAULT_K = [0, 1, 2, 3, 5, 10, 20, 50]
METRICS = ("success_rate", "return_mean", "collision_rate")


def summarise(rows: list[dict]) -> list[dict]:
    """Mean (and standard error over tasks) of every metric, per K."""
    summary = []
    for k in sorted({row["k"] for row in rows}):
        subset = [row for row in rows if row["k"] == k]
        entry = {"k": k, "n_tasks": len(subset)}
        for metric in METRICS:
            values = np.array([row[metric] for row in subset])
            entry[metric] = float(values.mean())
            entry[f"{metric}_sem"] = float(values.std(ddof=1) / np.sqrt(len(values))) if len(values) > 1 else 0.0
        summary.append(entry)
    return summary


def plot(summary: list[dict], path: Path, title: str) -> None:
    """Three panels (success, return, collisions) against K, with ±1 standard error bands over tasks."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ks = np.array([entry["k"] for entry in summary])
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, metric in zip(axes, METRICS):
        mean = np.array([entry[metric] for entry in summary])
        sem = np.array([entry[f"{metric}_sem"] for entry in summary])
        ax.plot(ks, mean, marker="o")
        ax.fill_between(ks, mean - sem, mean + sem, alpha=0.25)
        ax.set_xscale("symlog", linthresh=1)
        ax.set_xlabel("adaptation steps K")
        ax.set_title(metric)
    axes[0].axhline(0.95, ls="--", c="grey", lw=0.8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    """Train or load a MAML-SAC, evaluate its adaptation curve on held-out test tasks, write CSV/PNG/JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="VAFN/ThreeArmReachHidden-v0")
    parser.add_argument("--max-length", type=int, default=2, help="longest instruction (training and test)")
    parser.add_argument("--model", type=Path, help="evaluate this saved MAMLSAC instead of training one")
    parser.add_argument("--resume", type=Path, help="continue training this saved MAMLSAC for --timesteps more steps")
    parser.add_argument("--timesteps", type=int, default=300_000, help="training env steps (warm-up included)")
    parser.add_argument("--warmup-steps", type=int, default=50_000, help="plain multi-task SAC steps first")
    parser.add_argument("--net-arch", type=int, nargs="+", default=[64, 64])
    parser.add_argument("--n-envs", type=int, default=1)
    parser.add_argument("--n-support", type=int, default=200)
    parser.add_argument("--inner-steps", type=int, default=1, help="K during meta-training")
    parser.add_argument("--outer-steps", type=int, default=50)
    parser.add_argument("--second-order", action="store_true")
    parser.add_argument("--learning-rate", type=float, default=3e-4, help="outer (and warm-up) Adam learning rate")
    parser.add_argument("--gamma", type=float, default=0.99)
    parser.add_argument("--ent-coef", default="auto", help="SAC's ent_coef: 'auto', 'auto_0.1' or a number")
    parser.add_argument("--n-tasks", type=int, default=20, help="held-out test instructions")
    parser.add_argument("--k", type=int, nargs="+", default=DEFAULT_K, help="adaptation steps to evaluate")
    parser.add_argument("--n-eval-episodes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("results/maml_sac_adaptation"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    env_kwargs = {"max_length": args.max_length}

    if args.model is not None:
        model = MAMLSAC.load(args.model)
        train_seconds = None
    else:
        venv = make_vec_env(args.env, n_envs=args.n_envs, env_kwargs=env_kwargs, seed=args.seed)
        if args.resume is not None:
            model = MAMLSAC.load(args.resume, env=venv, tensorboard_log=str(args.out / "tb"))
        else:
            model = MAMLSAC(
                "MlpPolicy", venv, n_support=args.n_support, inner_steps=args.inner_steps,
                outer_steps=args.outer_steps, second_order=args.second_order, warmup_steps=args.warmup_steps,
                policy_kwargs={"net_arch": args.net_arch}, learning_rate=args.learning_rate, gamma=args.gamma,
                ent_coef=args.ent_coef if args.ent_coef.startswith("auto") else float(args.ent_coef),
                tensorboard_log=str(args.out / "tb"), seed=args.seed,
            )
        start = time.perf_counter()
        model.learn(args.timesteps, log_interval=5, reset_num_timesteps=args.resume is None)
        train_seconds = time.perf_counter() - start
        model.save(args.out / "model.zip")

    family = env_task_family(args.env, env_kwargs)
    tasks = TaskSampler("test", family, 1, args.max_length).fixed_set(args.n_tasks, seed=args.seed)
    start = time.perf_counter()
    rows = evaluate_adaptation(
        model, args.env, tasks, n_support=args.n_support, k_values=args.k, n_eval_episodes=args.n_eval_episodes,
        seed=args.seed, env_kwargs=env_kwargs,
    )
    eval_seconds = time.perf_counter() - start
    with (args.out / "adaptation.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    summary = summarise(rows)
    meta = {
        "env": args.env, "max_length": args.max_length, "timesteps": model.num_timesteps,
        "meta_iterations": model.meta_iterations, "inner_lrs": model.inner_lrs, "train_seconds": train_seconds,
        "eval_seconds": eval_seconds, "n_support": args.n_support, "n_tasks": args.n_tasks, "summary": summary,
    }
    (args.out / "adaptation.json").write_text(json.dumps(meta, indent=2))
    title = (f"MAML-SAC on {args.env} (len<={args.max_length}), {model.num_timesteps} steps, "
             f"{args.n_tasks} test tasks, support {args.n_support}")
    plot(summary, args.out / "adaptation.png", title)
    print(title)
    print(f"{'K':>3} " + " ".join(f"{m:>22}" for m in METRICS))
    for entry in summary:
        print(f"{entry['k']:>3} " + " ".join(f"{entry[m]:>14.3f} ± {entry[m + '_sem']:.3f}" for m in METRICS))


if __name__ == "__main__":
    main()
