"""Env steps/s of VAFN/ThreeArmReach-v1 against panda-gym's PandaReach-v3, and against the number of arms.

Random actions, one thread, wrappers as ``gymnasium.make`` builds them. Table 1 rows: our default control step
(5 × 1/240 s), our env at panda-gym's simulated time per step (10 × 1/240 s ≈ 0.042 s vs 0.04 s), the PettingZoo
view, and PandaReach-v3 (needs the ``[bench]`` extra). Table 2: ``VAFN/MultiArmReach-v1`` with 2, 3, 4 and 6 KUKA arms.
Rounds alternate between envs so that machine load hits all of them alike; the best round is reported.

    python benchmarks/env_throughput.py [--steps 3000] [--rounds 3] [--arms 2 3 4 6] [--csv FILE]
"""

from __future__ import annotations

import argparse
import os
import re
import time
from collections.abc import Callable
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

import vafn_gym  # noqa: E402,F401
from vafn_gym.constants import PHYSICS_DT  # noqa: E402
from vafn_gym.files import write_csv_rows  # noqa: E402

PANDA_SIM_TIME_PER_STEP = 0.04  # panda-gym: 20 substeps of 1/500 s
PEER = "PandaReach-v3 (1 arm, 0.040 s/step)"


def steps_per_second(make: Callable[[], gym.Env], steps: int, seed: int = 0) -> float:
    """Wall-clock env steps/s of random actions (resets included, env creation excluded)."""
    env = make()
    env.reset(seed=seed)
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(steps)]
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    return steps / elapsed


def pettingzoo_steps_per_second(steps: int, seed: int = 0) -> float:
    """Steps/s of the PettingZoo ParallelEnv view (random actions)."""
    from vafn_gym.pettingzoo import parallel_env

    env = parallel_env()
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    start = time.perf_counter()
    for _ in range(steps):
        actions = {agent: rng.uniform(-1, 1, 3).astype(np.float32) for agent in env.agents}
        env.step(actions)
        if not env.agents:
            env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    return steps / elapsed


def best_of(candidates: dict[str, Callable[[], float]], rounds: int) -> dict[str, float]:
    """Best steps/s of each candidate over ``rounds`` alternating rounds."""
    best = {name: 0.0 for name in candidates}
    for _ in range(rounds):
        for name, run in candidates.items():
            best[name] = max(best[name], run())
    return best


def peer_candidates(steps: int) -> dict[str, Callable[[], float]]:
    """Table 1: our env at two step lengths, the PettingZoo view and PandaReach-v3 when panda-gym is installed."""
    equal_time_substeps = int(round(PANDA_SIM_TIME_PER_STEP / PHYSICS_DT))
    candidates: dict[str, Callable[[], float]] = {
        "VAFN/ThreeArmReach-v1 (3 arms, 0.021 s/step)": lambda: steps_per_second(
            lambda: gym.make("VAFN/ThreeArmReach-v1"), steps
        ),
        f"VAFN/ThreeArmReach-v1 (3 arms, {equal_time_substeps * PHYSICS_DT:.3f} s/step)": lambda: steps_per_second(
            lambda: gym.make("VAFN/ThreeArmReach-v1", n_substeps=equal_time_substeps), steps
        ),
        "vafn_gym.pettingzoo view (3 arms, 0.021 s/step)": lambda: pettingzoo_steps_per_second(steps),
    }
    try:
        import panda_gym  # noqa: F401

        candidates[PEER] = lambda: steps_per_second(lambda: gym.make("PandaReach-v3"), steps)
    except ImportError:
        print("panda-gym is not installed (pip install -e '.[bench]'): no peer row")
    return candidates


def arm_count_candidates(steps: int, arm_counts: list[int]) -> dict[str, Callable[[], float]]:
    """Table 2: MultiArmReach-v1 with each arm count, inactive arms held (default) and moved by the policy."""
    candidates: dict[str, Callable[[], float]] = {}
    for n_arms in arm_counts:
        for mode in ("hold", "policy"):
            candidates[f"{n_arms}|{mode}"] = (
                lambda n=n_arms, m=mode: steps_per_second(
                    lambda: gym.make("VAFN/MultiArmReach-v1", n_arms=n, inactive_arms=m), steps
                )
            )
    return candidates


def print_peer_table(best: dict[str, float], rounds: int) -> list[dict[str, Any]]:
    """Print table 1; returns its rows."""
    peer = best.get(PEER)
    print(f"\n| env | steps/s (best of {rounds}) | ratio to PandaReach-v3 |")
    print("|---|---|---|")
    rows = []
    for name, value in best.items():
        ratio = value / peer if peer else float("nan")
        print(f"| {name} | {value:.0f} | {f'{ratio:.2f}×' if peer else 'n/a'} |")
        rows.append(
            {"table": "peer", "env": name, "steps_per_s": round(value, 1), "ratio_to_panda_reach": round(ratio, 3)}
        )
    return rows


def print_arm_table(best: dict[str, float], rounds: int) -> list[dict[str, Any]]:
    """Print table 2 (steps/s and arm-steps/s per arm count); returns its rows."""
    print(f"\n| arms | inactive_arms | steps/s (best of {rounds}) | arm-steps/s | relative to 3 arms |")
    print("|---|---|---|---|---|")
    rows = []
    for key, value in best.items():
        n_arms, mode = key.split("|")
        reference = best.get(f"3|{mode}")
        relative = f"{value / reference:.2f}" if reference else "n/a"
        print(f"| {n_arms} | {mode} | {value:.0f} | {value * int(n_arms):.0f} | {relative} |")
        rows.append({"table": "arms", "env": f"MultiArmReach-v1 n_arms={n_arms} inactive_arms={mode}",
                     "steps_per_s": round(value, 1), "ratio_to_panda_reach": ""})
    return rows


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """``--help``: the module docstring as written, and every option's default."""


def plain(text: str) -> str:
    """``text`` without reStructuredText markup (roles and double backticks), for ``--help``."""
    return re.sub(r":\w+:`([^`]*)`", r"\1", text).replace("``", "").replace("::\n", ":\n")


def main() -> None:
    """Run the benchmark and print the tables."""
    parser = argparse.ArgumentParser(description=plain(__doc__), formatter_class=HelpFormatter)
    parser.add_argument("--steps", type=int, default=3000, help="random-action env steps per env and round")
    parser.add_argument("--rounds", type=int, default=3, help="rounds over all envs; the best round is reported")
    parser.add_argument("--arms", type=int, nargs="*", default=[2, 3, 4, 6],
                        help="arm counts of the second table (none: skip it)")
    parser.add_argument("--csv", default=None, help="also write both tables to this CSV file")
    args = parser.parse_args()
    rows = print_peer_table(best_of(peer_candidates(args.steps), args.rounds), args.rounds)
    if args.arms:
        rows += print_arm_table(best_of(arm_count_candidates(args.steps, args.arms), args.rounds), args.rounds)
    if args.csv:
        write_csv_rows(rows, args.csv)


if __name__ == "__main__":
    main()
