"""Success and collision rates of the ScriptedController: the feasibility proof and ceiling of every learning curve.

    python benchmarks/scripted_ceiling.py [--episodes 200]

Instructions are drawn from the test split over lengths 1..10 (all difficulties), for each task family.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import gymnasium as gym
from tqdm import tqdm

import vafn_gym  # noqa: F401
from vafn_gym import ScriptedController


def main() -> None:
    """Run the controller and print a table per task family and difficulty."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--env-ids", nargs="+", default=["VAFN/ThreeArmReach-v0", "VAFN/ThreeArmReachHidden-v0"])
    args = parser.parse_args()
    controller = ScriptedController()
    print("| env | difficulty | episodes | success | collision | mean steps |")
    print("|---|---|---|---|---|---|")
    for env_id in args.env_ids:
        env = gym.make(env_id, split="test")
        stats: dict[str, list[tuple[bool, bool, int]]] = defaultdict(list)
        start = time.perf_counter()
        for seed in tqdm(range(args.episodes), desc=env_id, leave=False):
            info = controller.run_episode(env, seed)
            stats[info["instruction"].difficulty].append((info["is_success"], info["collided"], env.unwrapped.steps))
        stats["all"] = [row for rows in list(stats.values()) for row in rows]
        for difficulty in ("easy", "medium", "hard", "all"):
            rows = stats.get(difficulty, [])
            if rows:
                n = len(rows)
                print(f"| {env_id} | {difficulty} | {n} | {sum(r[0] for r in rows) / n:.3f} | "
                      f"{sum(r[1] for r in rows) / n:.3f} | {sum(r[2] for r in rows) / n:.0f} |")
        print(f"<!-- {env_id}: {time.perf_counter() - start:.0f} s -->")
        env.close()


if __name__ == "__main__":
    main()
