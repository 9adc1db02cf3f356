"""Success and collision rates of the ScriptedController: the feasibility proof and ceiling of every learning curve.

    python benchmarks/scripted_ceiling.py [--env-id VAFN/MultiArmReach-v1] [--n-arms 4] [--robot panda] [--n-tasks 200]

The instructions are the held-out test tasks of :class:`vafn_gym.InstructionBenchmark` (lengths 1..10, all
difficulties), each run once with :func:`vafn_gym.run_episode`, so the numbers compare with every learning curve.
``--n-arms`` and ``--robot`` are passed to ``gym.make`` only when given (the ThreeArm IDs fix three KUKA arms).
"""

from __future__ import annotations

import argparse
import math
import os
import re
import time
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

import vafn_gym  # noqa: E402,F401
from vafn_gym import (  # noqa: E402
    InstructionBenchmark,
    ScriptedController,
    difficulty_of,
)
from vafn_gym.files import write_csv_rows  # noqa: E402

Z_95 = 1.959963984540054


def wilson_interval(successes: float, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of a binomial rate (sensible at 0 % and 100 %, unlike the normal approximation)."""
    if n == 0:
        return (0.0, 1.0)
    rate = successes / n
    centre = (rate + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(rate * (1 - rate) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, centre - half), min(1.0, centre + half))


def env_kwargs_from(args: argparse.Namespace) -> dict[str, Any]:
    """The ``gym.make`` kwargs given on the command line."""
    kwargs: dict[str, Any] = {}
    if args.n_arms is not None:
        kwargs["n_arms"] = args.n_arms
    if args.robot is not None:
        kwargs["robot"] = args.robot
    if args.targets is not None:
        kwargs["targets"] = args.targets
    if args.observe_goal:
        kwargs["observe_goal"] = True
    return kwargs


def run(env_id: str, env_kwargs: dict[str, Any], n_tasks: int, seed: int) -> list[dict[str, Any]]:
    """One scripted episode per held-out test task (:meth:`InstructionBenchmark.evaluate`); one row per task."""
    benchmark = InstructionBenchmark(env_id, 1, 10, n_test=n_tasks, seed=seed, env_kwargs=env_kwargs)
    probe = benchmark.make_env()
    try:
        controller = ScriptedController.for_env(probe)
    finally:
        probe.close()
    return benchmark.evaluate(controller)


def summary_line(label: str, rows: list[dict[str, Any]]) -> str:
    """One markdown row: episodes, success and collision rates with 95 % Wilson CIs, mean steps."""
    n = len(rows)
    success = sum(r["success"] for r in rows)
    collision = sum(r["collision"] for r in rows)
    s_low, s_high = wilson_interval(success, n)
    c_low, c_high = wilson_interval(collision, n)
    steps = np.mean([r["steps"] for r in rows]) if rows else float("nan")
    return (
        f"| {label} | {n} | {success / n:.3f} [{s_low:.3f}, {s_high:.3f}] | "
        f"{collision / n:.3f} [{c_low:.3f}, {c_high:.3f}] | {steps:.0f} |"
    )


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """``--help``: the module docstring as written, and every option's default."""


def plain(text: str) -> str:
    """``text`` without reStructuredText markup (roles and double backticks), for ``--help``."""
    return re.sub(r":\w+:`([^`]*)`", r"\1", text).replace("``", "").replace("::\n", ":\n")


def main() -> None:
    """Run the controller on the benchmark's test tasks and print a table per difficulty."""
    parser = argparse.ArgumentParser(description=plain(__doc__), formatter_class=HelpFormatter)
    parser.add_argument("--env-id", default="VAFN/ThreeArmReach-v1", help="registered env ID")
    parser.add_argument("--n-arms", type=int, default=None, help="arm count (None: the env's own)")
    parser.add_argument("--robot", default=None, choices=sorted(vafn_gym.ROBOTS), help="robot (None: the env's own)")
    parser.add_argument("--targets", default=None, choices=vafn_gym.TARGET_MODES,
                        help="target mode (None: the env's own)")
    parser.add_argument("--observe-goal", action="store_true", help="observe the targets (8 numbers per arm)")
    parser.add_argument("--n-tasks", type=int, default=200, help="held-out test instructions, one episode each")
    parser.add_argument("--seed", type=int, default=1234, help="seed of the held-out test set")
    parser.add_argument("--csv", default=None, help="also write one row per episode to this CSV file")
    args = parser.parse_args()
    env_kwargs = env_kwargs_from(args)
    start = time.perf_counter()
    rows = run(args.env_id, env_kwargs, args.n_tasks, args.seed)
    elapsed = time.perf_counter() - start
    label = f"{args.env_id} {env_kwargs or ''}".strip()
    print(f"# {label}: {len(rows)} test tasks in {elapsed:.0f} s")
    print("| difficulty | episodes | success [95 % CI] | collision [95 % CI] | mean steps |")
    print("|---|---|---|---|---|")
    for difficulty in ("easy", "medium", "hard"):
        subset = [r for r in rows if difficulty_of(r["length"]) == difficulty]
        if subset:
            print(summary_line(difficulty, subset))
    print(summary_line("all", rows))
    failures = [r for r in rows if not r["success"] or r["collision"]]
    for row in failures[:10]:
        print(f"  failed task {row['task_index']} ({row['task']}): collision={row['collision']}, steps={row['steps']}")
    if args.csv:
        write_csv_rows(rows, args.csv)


if __name__ == "__main__":
    main()
