"""Env steps/s of VAFN/ThreeArmReach-v0 against panda-gym's PandaReach-v3, measured in the same process.

Random actions, one thread, wrappers as ``gymnasium.make`` builds them. Rows: our default control step (5 × 1/240 s),
our env at panda-gym's simulated time per step (10 × 1/240 s ≈ 0.042 s vs 0.04 s), the PettingZoo view, and PandaReach.
Rounds alternate between envs so that machine load hits all of them alike; the best round is reported.

    python benchmarks/env_throughput.py [--steps 3000] [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import time
from typing import Callable

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

import vafn_gym  # noqa: E402,F401
from vafn_gym.constants import PHYSICS_DT  # noqa: E402

PANDA_SIM_TIME_PER_STEP = 0.04  # panda-gym: 20 substeps of 1/500 s


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


def main() -> None:
    """Run the benchmark and print the table."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    equal_time_substeps = int(round(PANDA_SIM_TIME_PER_STEP / PHYSICS_DT))
    candidates: dict[str, Callable[[], float]] = {
        "VAFN/ThreeArmReach-v0 (3 arms, 0.021 s/step)": lambda: steps_per_second(
            lambda: gym.make("VAFN/ThreeArmReach-v0"), args.steps
        ),
        f"VAFN/ThreeArmReach-v0 (3 arms, {equal_time_substeps * PHYSICS_DT:.3f} s/step)": lambda: steps_per_second(
            lambda: gym.make("VAFN/ThreeArmReach-v0", n_substeps=equal_time_substeps), args.steps
        ),
        "vafn_gym.pettingzoo view (0.021 s/step)": lambda: pettingzoo_steps_per_second(args.steps),
    }
    try:
        import panda_gym  # noqa: F401

        candidates["PandaReach-v3 (1 arm, 0.040 s/step)"] = lambda: steps_per_second(
            lambda: gym.make("PandaReach-v3"), args.steps
        )
    except ImportError:
        print("panda-gym is not installed (pip install -e '.[bench]'): no peer row")
    best = {name: 0.0 for name in candidates}
    for _ in range(args.rounds):
        for name, run in candidates.items():
            best[name] = max(best[name], run())
    peer = best.get("PandaReach-v3 (1 arm, 0.040 s/step)")
    print(f"\n| env | steps/s (best of {args.rounds}) | ratio to PandaReach-v3 |")
    print("|---|---|---|")
    for name, value in best.items():
        ratio = f"{value / peer:.2f}×" if peer else "n/a"
        print(f"| {name} | {value:.0f} | {ratio} |")


if __name__ == "__main__":
    main()
