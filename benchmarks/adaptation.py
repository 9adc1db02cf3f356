"""Adaptation curves: success, return and collision rate against the number of adaptation steps K on held-out tasks.

Trains a MAML-SAC from ``hyperparams/maml_sac.yml`` (flags override single values), or loads one with ``--model``,
then runs :func:`vafn_sb3.common.adaptation.evaluate_adaptation` on the first ``--n-tasks`` held-out test instructions
of :class:`vafn_gym.InstructionBenchmark` (its default seed, the same tasks as every other script), for every K in
``--k``. Meta-training draws its task pool from the same benchmark's training instructions. Writes ``adaptation.csv``
(one row per task and K), ``adaptation.png``, ``adaptation.json`` and prints the per-K means. Never asserts a number.

Usage::

    OMP_NUM_THREADS=1 nice -n 10 python benchmarks/adaptation.py --env VAFN/ThreeArmReachHidden-v1 --max-length 2 \\
        --timesteps 300000 --warmup-steps 50000 --out results/maml_sac_hidden
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from stable_baselines3.common.env_util import make_vec_env  # noqa: E402

from vafn_gym import InstructionBenchmark  # noqa: E402
from vafn_sb3.common.adaptation import evaluate_adaptation  # noqa: E402
from vafn_sb3.maml_sac import MAMLSAC  # noqa: E402
from zoo.hyperparams import load_hyperparams  # noqa: E402

DEFAULT_K = [0, 1, 2, 3, 5, 10, 20, 50]
METRICS = ("success_rate", "return_mean", "collision_rate")
#: Flags that override the YAML value of the MAMLSAC keyword of the same name when given.
OVERRIDES = ("n_support", "inner_steps", "outer_steps", "warmup_steps", "learning_rate", "gamma", "ent_coef")


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
    for ax, metric in zip(axes, METRICS, strict=True):
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


def maml_kwargs(args: argparse.Namespace) -> tuple[dict[str, Any], int, str]:
    """``(MAMLSAC kwargs, timesteps, policy)``: the YAML's entry for ``args.env``, updated by the flags given."""
    kwargs, yaml_steps, policy = load_hyperparams("maml_sac", args.env)
    for name in OVERRIDES:
        value = getattr(args, name)
        if value is not None:
            kwargs[name] = value
    if isinstance(kwargs.get("ent_coef"), str) and not kwargs["ent_coef"].startswith("auto"):
        kwargs["ent_coef"] = float(kwargs["ent_coef"])
    if args.second_order:
        kwargs["second_order"] = True
    if args.net_arch is not None:
        kwargs["policy_kwargs"] = {**kwargs.get("policy_kwargs", {}), "net_arch": args.net_arch}
    return kwargs, args.timesteps or yaml_steps, args.policy or policy


def train(args: argparse.Namespace, benchmark: InstructionBenchmark, env_kwargs: dict[str, Any]) -> MAMLSAC:
    """Train (or, with ``--resume``, continue) a MAML-SAC on the benchmark's training instructions; save it."""
    kwargs, timesteps, policy = maml_kwargs(args)
    venv = make_vec_env(args.env, n_envs=args.n_envs, env_kwargs=env_kwargs, seed=args.seed)
    tensorboard_log = str(args.out / "tb")
    if args.resume is not None:
        model = MAMLSAC.load(args.resume, env=venv, tensorboard_log=tensorboard_log)
    else:
        kwargs["train_tasks"] = benchmark.train_tasks
        model = MAMLSAC(policy, venv, tensorboard_log=tensorboard_log, seed=args.seed, **kwargs)
    model.learn(timesteps, log_interval=5, reset_num_timesteps=args.resume is None)
    model.save(args.out / "model.zip")
    return model


def write_csv(rows: list[dict], path: Path) -> None:
    """One CSV row per dict (the first row's keys are the header)."""
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line flags; training flags left unset take ``hyperparams/maml_sac.yml``'s value."""
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--env", default="VAFN/ThreeArmReachHidden-v1", help="env ID")
    parser.add_argument("--env-kwargs", type=json.loads, default={}, help='JSON, e.g. \'{"n_arms": 4}\'')
    parser.add_argument("--max-length", type=int, default=2, help="longest instruction (training and test)")
    parser.add_argument("--model", type=Path, help="evaluate this saved MAMLSAC instead of training one")
    parser.add_argument("--resume", type=Path, help="continue training this saved MAMLSAC for --timesteps more steps")
    parser.add_argument("--timesteps", type=int, help="training env steps (warm-up included)")
    parser.add_argument("--warmup-steps", type=int, help="plain multi-task SAC steps first")
    parser.add_argument("--policy", help="policy alias (SharedAgentPolicy or MlpPolicy)")
    parser.add_argument("--net-arch", type=int, nargs="+", help="hidden layer sizes (default: the YAML's)")
    parser.add_argument("--n-envs", type=int, default=1, help="training envs")
    parser.add_argument("--n-support", type=int, help="support transitions (meta-training and evaluation)")
    parser.add_argument("--inner-steps", type=int, help="K during meta-training")
    parser.add_argument("--outer-steps", type=int, help="meta-gradient steps per meta-iteration")
    parser.add_argument("--second-order", action="store_true", help="second-order MAML")
    parser.add_argument("--learning-rate", type=float, help="outer (and warm-up) Adam learning rate")
    parser.add_argument("--gamma", type=float, help="discount factor")
    parser.add_argument("--ent-coef", help="SAC's ent_coef: 'auto', 'auto_0.1' or a number")
    parser.add_argument("--n-tasks", type=int, default=20, help="held-out test instructions")
    parser.add_argument("--k", type=int, nargs="+", default=DEFAULT_K, help="adaptation steps to evaluate")
    parser.add_argument("--n-eval-episodes", type=int, default=3, help="episodes per task and K")
    parser.add_argument("--seed", type=int, default=0, help="training, support and evaluation-episode seed")
    parser.add_argument("--out", type=Path, default=Path("results/maml_sac_adaptation"), help="output folder")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    """Train or load a MAML-SAC, evaluate its adaptation curve on held-out test tasks, write CSV/PNG/JSON."""
    args = parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    env_kwargs = {**args.env_kwargs, "max_length": args.max_length}
    benchmark = InstructionBenchmark(
        args.env, 1, args.max_length, n_test=args.n_tasks, env_kwargs=args.env_kwargs, train_max_length=args.max_length
    )
    start = time.perf_counter()
    if args.model is not None:
        model, train_seconds = MAMLSAC.load(args.model), None
    else:
        model = train(args, benchmark, env_kwargs)
        train_seconds = time.perf_counter() - start
    n_support = args.n_support or model.n_support
    start = time.perf_counter()
    rows = evaluate_adaptation(
        model, args.env, benchmark.test_tasks, n_support=n_support, k_values=args.k,
        n_eval_episodes=args.n_eval_episodes, seed=args.seed, env_kwargs=env_kwargs,
    )
    eval_seconds = time.perf_counter() - start
    write_csv(rows, args.out / "adaptation.csv")
    summary = summarise(rows)
    meta = {
        "env": args.env, "env_kwargs": args.env_kwargs, "max_length": args.max_length,
        "test_seed": benchmark.seed, "timesteps": model.num_timesteps, "meta_iterations": model.meta_iterations,
        "inner_lrs": model.inner_lrs, "train_seconds": train_seconds, "eval_seconds": eval_seconds,
        "n_support": n_support, "n_tasks": args.n_tasks, "command": " ".join(sys.argv), "summary": summary,
    }
    (args.out / "adaptation.json").write_text(json.dumps(meta, indent=2))
    title = (f"MAML-SAC on {args.env} (len<={args.max_length}), {model.num_timesteps} steps, "
             f"{args.n_tasks} test tasks, support {n_support}")
    plot(summary, args.out / "adaptation.png", title)
    print(title)
    print(f"{'K':>3} " + " ".join(f"{m:>22}" for m in METRICS))
    for entry in summary:
        print(f"{entry['k']:>3} " + " ".join(f"{entry[m]:>14.3f} ± {entry[m + '_sem']:.3f}" for m in METRICS))


if __name__ == "__main__":
    main()
