"""Training speed: stock SB3 SAC versus vafn_sb3.SAC's lean update, side by side on one thread.

    python benchmarks/train_speed.py --block 400 --repeats 5

Both models get the same hyperparameters (hyperparams/sac.yml for the env, ``net_arch`` from ``--net-archs``), the
same seed and a warm-up past ``learning_starts``; then short blocks of ``learn()`` alternate between them (A/B, B/A,
...) so the load of a shared machine falls on both alike, and likewise blocks of single gradient steps
(``train(1, batch_size)``, as ``learn`` calls it) and of env steps with random actions (the env-bound limit). Writes
``<out>/train_speed.csv`` (one row per block) and ``<out>/train_speed.md`` (medians with min-max over blocks, the
paired lean/stock ratios, the command, the git commit).

    python benchmarks/train_speed.py --learning results/train_speed/learning

only tabulates a learning comparison instead: held-out success per evaluation step, mean and 95 % CI over seeds, of
``benchmarks/learning.py`` runs tagged ``_stock`` (``--hyperparams '{"lean_update": false}'``) and ``_lean`` in that
folder, written to ``<folder>/learning.md``.
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import stable_baselines3  # noqa: E402
import torch  # noqa: E402

import vafn_gym  # noqa: E402,F401  (registers the env IDs)
import vafn_sb3  # noqa: E402  (registers SharedAgentPolicy as a stock SB3 alias)
from vafn_gym import confidence_half_width  # noqa: E402
from vafn_gym.files import write_csv_rows  # noqa: E402
from zoo.hyperparams import load_hyperparams  # noqa: E402

VARIANTS = ("stock", "lean")


def git_commit() -> str:
    """The short commit of the checkout, with ``+dirty`` if the measured code differs from it."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True).stdout.strip()

    commit = git("rev-parse", "--short", "HEAD") or "unknown"
    dirty = git("status", "--porcelain", "--", "vafn_sb3/sac", "benchmarks/train_speed.py")
    return commit + ("+dirty" if dirty else "")


def make_model(variant: str, env_id: str, net_arch: list[int], seed: int) -> Any:
    """Stock ``stable_baselines3.SAC`` or ``vafn_sb3.SAC`` (lean update) with the env's YAML hyperparameters."""
    kwargs, _, policy = load_hyperparams("sac", env_id)
    kwargs["policy_kwargs"] = {**kwargs.get("policy_kwargs", {}), "net_arch": net_arch}
    cls = stable_baselines3.SAC if variant == "stock" else vafn_sb3.SAC
    extra = {} if variant == "stock" else {"lean_update": True}
    return cls(policy, gym.make(env_id), seed=seed, verbose=0, **kwargs, **extra)


def timed(run: Callable[[], int]) -> tuple[int, float, float]:
    """``run()`` (returns its step count) with its wall and process CPU seconds."""
    wall, cpu = time.perf_counter(), time.process_time()
    steps = run()
    return steps, time.perf_counter() - wall, time.process_time() - cpu


def learn_block(model: Any, steps: int) -> Callable[[], int]:
    """``steps`` more env steps of ``learn`` (one gradient step each, as in the YAML)."""
    def run() -> int:
        model.learn(steps, reset_num_timesteps=False)
        return steps
    return run


def train_block(model: Any, steps: int) -> Callable[[], int]:
    """``steps`` calls of ``train(1, batch_size)``: gradient steps as ``learn`` takes them."""
    def run() -> int:
        for _ in range(steps):
            model.train(gradient_steps=1, batch_size=model.batch_size)
        return steps
    return run


def env_block(env: gym.Env, steps: int) -> Callable[[], int]:
    """``steps`` env steps with random actions (resetting at episode ends): the env-bound limit."""
    def run() -> int:
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()
        return steps
    return run


def measure(args: argparse.Namespace, net_arch: list[int]) -> list[dict]:
    """Interleaved blocks of ``learn``, ``train`` and env steps for both variants; one row per block."""
    models = {variant: make_model(variant, args.env, net_arch, args.seed) for variant in VARIANTS}
    for model in models.values():
        model.learn(model.learning_starts + args.warmup)
    env = gym.make(args.env)
    env.reset(seed=args.seed)
    rows = []
    for repeat in range(args.repeats):
        order = VARIANTS if repeat % 2 == 0 else VARIANTS[::-1]
        blocks = [("env", "env", env_block(env, args.block))]
        blocks += [(variant, "learn", learn_block(models[variant], args.block)) for variant in order]
        blocks += [(variant, "train", train_block(models[variant], args.block)) for variant in order]
        for variant, kind, run in blocks:
            steps, wall, cpu = timed(run)
            rows.append({"net_arch": "-".join(map(str, net_arch)), "variant": variant, "kind": kind,
                         "repeat": repeat, "steps": steps, "wall_s": round(wall, 4), "cpu_s": round(cpu, 4),
                         "steps_per_s": round(steps / wall, 2), "cpu_steps_per_s": round(steps / cpu, 2),
                         "load_1min": round(os.getloadavg()[0], 2)})
        print(rows[-5:], flush=True)
    env.close()
    return rows


def spread(values: list[float]) -> str:
    """``median [min-max]``."""
    return f"{np.median(values):.1f} [{min(values):.1f}-{max(values):.1f}]"


def ratio_spread(values: list[float]) -> str:
    """``median× [min-max]``."""
    return f"{np.median(values):.2f}x [{min(values):.2f}-{max(values):.2f}]"


def pick(rows: list[dict], arch: str, variant: str, kind: str, key: str) -> list[float]:
    """One column of the blocks of one architecture, variant and kind, in repeat order."""
    chosen = [r for r in rows if r["net_arch"] == arch and r["variant"] == variant and r["kind"] == kind]
    return [r[key] for r in sorted(chosen, key=lambda r: r["repeat"])]


def markdown(rows: list[dict], args: argparse.Namespace, command: str) -> str:
    """The report: per architecture and variant, env steps/s, gradient steps/s, share of the env-bound limit."""
    lines = [
        "# Training speed: stock SB3 SAC vs vafn_sb3.SAC's lean update",
        "",
        f"Command: `{command}`  ",
        f"Commit: {git_commit()}; torch {torch.__version__}, stable-baselines3 {stable_baselines3.__version__}, "
        f"Python {platform.python_version()}, one torch thread, {os.cpu_count()} logical CPUs shared with other "
        "jobs.  ",
        f"Env {args.env}, hyperparams/sac.yml (batch 256, train_freq 1, gradient_steps 1, shared per-arm actor), "
        f"seed {args.seed}; {args.repeats} interleaved blocks of {args.block} steps per measurement, after "
        f"learning_starts + {args.warmup} warm-up steps. Values: median [min-max] over the blocks; speed-ups: "
        "median [min-max] of the lean/stock ratio of blocks run back to back.",
        "",
        "| net_arch | update | env steps/s (`learn`), wall | per CPU second | share of env-bound limit (CPU) | "
        "gradient steps/s (`train`), wall | per CPU second | speed-up per env step, wall / CPU | "
        "speed-up per gradient step, wall / CPU |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for arch in dict.fromkeys(r["net_arch"] for r in rows):
        label = f"[{arch.replace('-', ', ')}]"
        limit = float(np.median(pick(rows, arch, "env", "env", "cpu_steps_per_s")))
        for variant in VARIANTS:
            columns = {(kind, key): pick(rows, arch, variant, kind, key)
                       for kind in ("learn", "train") for key in ("steps_per_s", "cpu_steps_per_s")}
            speedups = []
            for kind in ("learn", "train"):
                stock = {key: pick(rows, arch, "stock", kind, key) for key in ("steps_per_s", "cpu_steps_per_s")}
                ratios = [ratio_spread([a / b for a, b in zip(columns[kind, key], stock[key])]) for key in stock]
                speedups.append("1" if variant == "stock" else " / ".join(ratios))
            share = f"{100 * np.median(columns['learn', 'cpu_steps_per_s']) / limit:.1f} %"
            lines.append(f"| {label} | {variant} | {spread(columns['learn', 'steps_per_s'])} | "
                         f"{spread(columns['learn', 'cpu_steps_per_s'])} | {share} | "
                         f"{spread(columns['train', 'steps_per_s'])} | {spread(columns['train', 'cpu_steps_per_s'])} | "
                         f"{speedups[0]} | {speedups[1]} |")
        lines.append(f"| {label} | env only (random actions) | {spread(pick(rows, arch, 'env', 'env', 'steps_per_s'))} "
                     f"| {spread(pick(rows, arch, 'env', 'env', 'cpu_steps_per_s'))} | 100 % | | | | |")
    loads = [r["load_1min"] for r in rows]
    lines += ["", f"1-minute load average during the blocks: {spread(loads)} on {os.cpu_count()} logical CPUs. Per CPU "
              "second: steps per second of this process's CPU time (`time.process_time`), which leaves out the time "
              "other processes held the core; wall: per second of elapsed time."]
    lines += ["", "stock: `stable_baselines3.SAC`; lean: `vafn_sb3.SAC` (`lean_update=True`, the default; "
              "vafn_sb3/sac/lean.py). One row per block: train_speed.csv.", ""]
    return "\n".join(lines)


def learning_table(folder: Path, env_id: str) -> str:
    """Held-out success per evaluation step of the ``_stock`` and ``_lean`` learning runs in ``folder``, mean ± 95 % CI
    over seeds, per-seed values, and whether the two intervals overlap."""
    curves = {variant: list(csv.DictReader((folder / f"sac_{env_id.split('/')[-1]}_{variant}_curves.csv").open()))
              for variant in VARIANTS}
    steps = sorted({int(r["timesteps"]) for rows in curves.values() for r in rows})
    lines = ["| env steps | " + " | ".join(f"{v}: success (mean ± 95 % CI) | {v}: per seed" for v in VARIANTS)
             + " | intervals overlap |", "|---" * (2 * len(VARIANTS) + 2) + "|"]
    for step in steps:
        cells, intervals = [], []
        for variant in VARIANTS:
            chosen = sorted((r for r in curves[variant] if int(r["timesteps"]) == step), key=lambda r: int(r["seed"]))
            values = np.array([float(r["success"]) for r in chosen])
            half = float(confidence_half_width(values[:, None])[0]) if len(values) else float("nan")
            intervals.append((values.mean() - half, values.mean() + half) if len(values) else (np.nan, np.nan))
            cells += [f"{values.mean():.2f} ± {half:.2f} (n={len(values)})" if len(values) else "-",
                      ", ".join(f"s{r['seed']} {float(r['success']):.2f} ({r['n_tasks']} tasks)" for r in chosen)]
        (low_a, high_a), (low_b, high_b) = intervals
        overlap = "yes" if max(low_a, low_b) <= min(high_a, high_b) else "no"
        lines.append(f"| {step} | " + " | ".join(cells) + f" | {overlap} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    """Parse arguments, measure every architecture, write the csv and the markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--env", default="VAFN/ThreeArmReach-v1", help="env ID")
    parser.add_argument("--net-archs", nargs="+", default=["64,64", "256,256"], help="hidden layers, e.g. 64,64")
    parser.add_argument("--block", type=int, default=400, help="steps per timed block")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved blocks per variant and measurement")
    parser.add_argument("--warmup", type=int, default=200, help="steps after learning_starts before timing")
    parser.add_argument("--seed", type=int, default=0, help="seed of both models and of the env")
    parser.add_argument("--out", type=Path, default=Path("results/train_speed"), help="output folder")
    parser.add_argument("--learning", type=Path, default=None,
                        help="only tabulate the _stock/_lean learning runs in this folder (see the module docstring)")
    args = parser.parse_args()
    if args.learning is not None:
        table = learning_table(args.learning, args.env)
        (args.learning / "learning.md").write_text(table)
        print(table)
        return
    torch.set_num_threads(1)
    command = " ".join(["python", "benchmarks/train_speed.py", *sys.argv[1:]])
    rows = [row for arch in args.net_archs for row in measure(args, [int(w) for w in arch.split(",")])]
    args.out.mkdir(parents=True, exist_ok=True)
    write_csv_rows(rows, args.out / "train_speed.csv")
    report = markdown(rows, args, command)
    (args.out / "train_speed.md").write_text(report)
    print(report)


if __name__ == "__main__":
    main()
