"""Where adaptation moves a policy whose targets are hidden: its resting point after K steps against the unadapted one.

    OMP_NUM_THREADS=1 python benchmarks/adaptation_direction.py 'runs/hidden/mtsac/*_seed*.zip' --k 0 1 10 50

On the one-waypoint instructions among the adaptation study's held-out tasks (``--max-length 4 --n-tasks 15`` are
the study's), each model adapts as ``benchmarks/adaptation.py`` does (the same support seeds and first evaluation
episode) and runs one deterministic episode per K. Per K it reports where the active arm ends: its distance to the
hidden target, how far that end point moved from the unadapted policy's (K = 0), and the cosine between that move and
the direction from the unadapted end point to the target (1: straight at the target; 0: sideways). A success rate
near zero says nothing about whether the inner steps point the right way; this does. Prints a Markdown table (mean
over models of each model's mean over tasks, ± 95 % Student-t half width) and writes every episode with ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import glob
import json
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import vafn_gym  # noqa: E402, F401  (registers the env IDs)
from vafn_gym import InstructionBenchmark, run_episode  # noqa: E402
from vafn_gym.benchmarks import confidence_half_width  # noqa: E402
from vafn_sb3.common.adaptation import EVAL_SEED_OFFSET  # noqa: E402
from vafn_sb3.loading import load_model  # noqa: E402

COLUMNS = ("final_cm", "moved_cm", "cosine", "success")


def move_toward(unadapted_end: np.ndarray, end: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """How far ``end`` lies from ``unadapted_end`` (cm) and the cosine between that move and the way to ``target``."""
    move, wanted = end - unadapted_end, target - unadapted_end
    moved = float(np.linalg.norm(move))
    if moved < 1e-9 or float(np.linalg.norm(wanted)) < 1e-9:
        return 100.0 * moved, float("nan")
    return 100.0 * moved, float(move @ wanted / (moved * np.linalg.norm(wanted)))


def resting_points(model, env_id: str, env_kwargs: dict, tasks: list, task_indices: list[int], k_values: list[int],
                   n_support: int, seed: int) -> list[dict]:
    """One deterministic episode per (task, K) after adapting on the study's support set; where the active arm ends."""
    rows = []
    for task, index in zip(tasks, task_indices):
        arm = task.arms[0]
        unadapted_end = None
        for k in k_values:
            env = gym.make(env_id, **env_kwargs)
            policy = model if k == 0 else model.adapt(env, task=task, n_support=n_support, k=k, seed=seed + index)
            env.unwrapped.set_task(task)
            episode = run_episode(policy, env, seed=seed + EVAL_SEED_OFFSET + index)
            end, target = np.array(env.unwrapped.arms[arm].ee_position), np.asarray(env.unwrapped.task.goal(arm))
            env.close()
            unadapted_end = end if k == 0 else unadapted_end
            moved, cosine = move_toward(unadapted_end, end, target) if k else (0.0, float("nan"))
            rows.append({"task": task.to_code(), "k": k, "success": episode["success"],
                         "final_cm": 100.0 * float(np.linalg.norm(end - target)), "moved_cm": moved, "cosine": cosine})
    return rows


def summary_table(rows: list[dict], k_values: list[int]) -> list[str]:
    """Markdown rows: per K, each column's mean over models of per-model task means, ± 95 % Student-t half width."""
    lines = ["| K | " + " | ".join(COLUMNS) + " | models |", "|---" * (len(COLUMNS) + 2) + "|"]
    models = sorted({row["model"] for row in rows})
    for k in k_values:
        cells = []
        for column in COLUMNS:
            per_model = [[r[column] for r in rows if r["model"] == m and r["k"] == k and np.isfinite(r[column])]
                         for m in models]
            means = np.array([np.mean(values) for values in per_model if values])
            if not len(means):
                cells.append("–")  # no cosine at K = 0: nothing moved
            else:
                half = f" ± {confidence_half_width(means):.2f}" if len(means) > 1 else ""
                cells.append(f"{means.mean():.2f}{half}")
        lines.append(f"| {k} | " + " | ".join(cells) + f" | {len(models)} |")
    return lines


def main(argv: list[str] | None = None) -> list[str]:
    """Adapt every model to the one-waypoint held-out tasks and print where its active arm ends per K."""
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("models", help="glob of saved models, one per seed (quote it)")
    parser.add_argument("--algo", default=None, help="force the models' algorithm key")
    parser.add_argument("--env", default="VAFN/ThreeArmReachHidden-v1", help="env ID")
    parser.add_argument("--env-kwargs", type=json.loads, default={}, help="JSON env kwargs, as the models trained")
    parser.add_argument("--max-length", type=int, default=4, help="longest test instruction (the study's)")
    parser.add_argument("--n-tasks", type=int, default=15, help="held-out test instructions (the study's)")
    parser.add_argument("--k", type=int, nargs="+", default=[0, 1, 10, 50], help="adaptation steps; must include 0")
    parser.add_argument("--n-support", type=int, default=400, help="support env steps per adaptation")
    parser.add_argument("--seed", type=int, default=0, help="base seed, as adaptation.py's")
    parser.add_argument("--out", type=Path, default=None, help="also write every episode's row to this CSV")
    args = parser.parse_args(argv)
    if 0 not in args.k or min(args.k) < 0:
        raise SystemExit(f"--k must be >= 0 and include 0 (the unadapted resting point the others are measured "
                         f"from), got {args.k}")
    paths = sorted(glob.glob(args.models))
    if not paths:
        raise SystemExit(f"no model matches {args.models!r}")
    torch.set_num_threads(1)
    benchmark = InstructionBenchmark(args.env, 1, args.max_length, n_test=args.n_tasks, env_kwargs=args.env_kwargs)
    indices = [i for i, task in enumerate(benchmark.test_tasks) if len(task.arms) == 1]
    if not indices:
        raise SystemExit("no one-waypoint instruction among the held-out tasks: raise --n-tasks")
    tasks = [benchmark.test_tasks[i] for i in indices]
    k_values = sorted(set(args.k))
    models = {}
    for path in paths:  # every file is read before any episode runs, so a bad one fails at once
        try:
            model = load_model(path, args.algo)[0]
        except (ValueError, FileNotFoundError) as error:
            raise SystemExit(str(error)) from None
        if max(k_values) > 0 and not callable(getattr(model, "adapt", None)):
            raise SystemExit(f"{path}: {type(model).__name__} has no adapt(); use --k 0")
        models[Path(path).name] = model
    rows = []
    for name, model in models.items():
        rows += [{"model": name, **row} for row in resting_points(
            model, args.env, args.env_kwargs, tasks, indices, k_values, args.n_support, args.seed)]
    if args.out is not None:
        with args.out.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    lines = [f"{len(tasks)} one-waypoint held-out tasks, {len(paths)} models, support {args.n_support} env steps", "",
             *summary_table(rows, k_values)]
    print("\n".join(lines))
    return lines


if __name__ == "__main__":
    main()
