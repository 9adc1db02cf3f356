"""Where adaptation moves a policy whose targets are hidden: its resting point after K steps against the unadapted one.

    OMP_NUM_THREADS=1 python benchmarks/adaptation_direction.py 'runs/hidden/mtsac/*_seed*.zip' --k 0 1 10 50

Each model runs the adaptation study's own episodes (``evaluate_adaptation`` with one episode per task and K, as
``benchmarks/adaptation.py`` does; ``--max-length 4 --n-tasks 15`` are the study's tasks), and on the one-waypoint
instructions among them, per K, it reports where the active arm ends: its distance to the hidden target, how far that
end point moved from the unadapted policy's (K = 0), and the cosine between that move and the direction from the
unadapted end point to the target (1: straight at the target; 0: sideways). A success rate
near zero says nothing about whether the inner steps point the right way; this does. Prints a Markdown table (mean
over models of each model's mean over tasks, ± 95 % Student-t half width) and writes every episode with ``--out``.
"""

from __future__ import annotations

import argparse
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
from vafn_gym import InstructionBenchmark  # noqa: E402
from vafn_gym.benchmarks import confidence_half_width  # noqa: E402
from vafn_gym.files import write_csv_rows  # noqa: E402
from vafn_sb3.common.adaptation import evaluate_adaptation  # noqa: E402
from vafn_sb3.loading import add_trust_flag, load_model_or_exit  # noqa: E402

COLUMNS = ("final_cm", "moved_cm", "cosine", "success")


def move_toward(unadapted_end: np.ndarray, end: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """How far ``end`` lies from ``unadapted_end`` (cm) and the cosine between that move and the way to ``target``."""
    move, wanted = end - unadapted_end, target - unadapted_end
    moved = float(np.linalg.norm(move))
    if moved < 1e-9 or float(np.linalg.norm(wanted)) < 1e-9:
        return 100.0 * moved, float("nan")
    return 100.0 * moved, float(move @ wanted / (moved * np.linalg.norm(wanted)))


def first_arm_at_rest(env: gym.Env) -> dict:
    """Where the instruction's first arm came to rest and its target: an ``evaluate_adaptation`` episode-end hook."""
    arm = env.unwrapped.instruction.arms[0]
    return {"end": np.array(env.unwrapped.arms[arm].ee_position), "target": np.asarray(env.unwrapped.task.goal(arm))}


def resting_points(model, env_id: str, env_kwargs: dict, tasks: list, k_values: list[int], n_support: int,
                   seed: int) -> list[dict]:
    """The study's episodes on ``tasks`` (``evaluate_adaptation``, one per task and K); for each one-waypoint task,
    where its arm ended at each K and how that moved from where it ended at K = 0."""
    rows = evaluate_adaptation(model, env_id, tasks, n_support, k_values, n_eval_episodes=1, seed=seed,
                               env_kwargs=env_kwargs, keep_episodes=True, at_episode_end=first_arm_at_rest)
    unadapted = {row["task_index"]: row["episodes"][0]["end"] for row in rows if row["k"] == 0}
    points = []
    for row in rows:
        if len(tasks[row["task_index"]].arms) != 1:
            continue  # a longer task's episodes may end at another waypoint: their end points are not comparable
        (episode,) = row["episodes"]
        moved, cosine = (move_toward(unadapted[row["task_index"]], episode["end"], episode["target"]) if row["k"]
                         else (0.0, float("nan")))
        points.append({"task": row["task"], "k": row["k"], "success": episode["success"],
                       "final_cm": 100.0 * float(np.linalg.norm(episode["end"] - episode["target"])),
                       "moved_cm": moved, "cosine": cosine})
    return points


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
    add_trust_flag(parser)
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
    tasks = benchmark.test_tasks
    n_one_waypoint = sum(len(task.arms) == 1 for task in tasks)
    if not n_one_waypoint:
        raise SystemExit("no one-waypoint instruction among the held-out tasks: raise --n-tasks")
    k_values = sorted(set(args.k))
    models = {}
    for path in paths:  # every file is read before any episode runs, so a bad one fails at once
        model = load_model_or_exit(path, args.algo, trust_remote_code=args.trust_remote_code)[0]
        if max(k_values) > 0 and not callable(getattr(model, "adapt", None)):
            raise SystemExit(f"{path}: {type(model).__name__} has no adapt(); use --k 0")
        models[Path(path).name] = model
    rows = []
    for name, model in models.items():
        rows += [{"model": name, **row} for row in resting_points(
            model, args.env, args.env_kwargs, tasks, k_values, args.n_support, args.seed)]
    if args.out is not None:
        write_csv_rows(rows, args.out)
    lines = [f"{n_one_waypoint} one-waypoint held-out tasks, {len(paths)} models, support {args.n_support} env steps",
             "", *summary_table(rows, k_values)]
    print("\n".join(lines))
    return lines


if __name__ == "__main__":
    main()
