"""MARL baselines and MTSAC: returns of the CI-sized runs, and learner cost per gradient step. Prints, never asserts.

Usage (the runs behind the numbers in docs/algorithms.md, "Cost and CI-sized runs")::

    OMP_NUM_THREADS=1 nice -n 10 python benchmarks/baselines.py ci      # the training runs of tests/test_baselines.py
    OMP_NUM_THREADS=1 nice -n 10 python benchmarks/baselines.py speed   # thread-CPU ms per gradient step, batch 256

``ci`` trains on the tests' env (``VAFN/ThreeArmReach-v1``, instruction ``"1"``) and scores every episode with
:func:`vafn_gym.run_episode`; ``speed`` times on ``--env`` with ``--env-kwargs``. Smaller flags (``--steps``,
``--warmup-steps``, ``--timed-steps``, ``--rollout``) give a quick smoke run.

Times are thread CPU time (``time.thread_time``), so they hold up on a loaded machine; the load average is printed.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import gymnasium as gym
import torch
from stable_baselines3.common.logger import configure

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_sb3 import MAAC, MADDPG, MAPPO, MTSAC

BATCH_SIZE = 256
TIMED_STEPS = 60
WARMUP_STEPS = 1000
MAPPO_ROLLOUT = 2048


def load_average() -> str:
    """The 1/5/15-minute load averages."""
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def ci_returns(args: argparse.Namespace) -> None:
    """Re-run the CI-sized trainings of ``tests/test_baselines.py``; print return vs the random policy and CPU time."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_baselines import ALGORITHMS, SEED, UniformRandomPolicy, make_env, mean_return

    env = make_env()
    random_return = mean_return(UniformRandomPolicy(SEED, env.action_space.shape[0]), env)
    print(f"load average {load_average()}; random policy: mean return {random_return:.2f}")
    for name, (make_model, test_steps) in ALGORITHMS.items():
        steps = args.steps or test_steps
        model = make_model(env)
        start = time.thread_time()
        model.learn(steps)
        cpu = time.thread_time() - start
        print(f"{name}: {steps} steps, {model._n_updates} updates, {cpu:.1f} s thread CPU; "
              f"deterministic return {mean_return(model, env):.2f} vs random {random_return:.2f}", flush=True)


def speed(args: argparse.Namespace) -> None:
    """Thread-CPU cost of one gradient step of each algorithm at its reference network sizes."""
    env = gym.make(args.env, **{"instruction": "1,2", **args.env_kwargs})
    warmup, timed = args.warmup_steps, args.timed_steps
    off_policy = {
        "MTSAC (SAC, MLP 256x256)": lambda: MTSAC("MlpPolicy", env, learning_starts=warmup, seed=0),
        "MADDPG (64x64, 1 critic)": lambda: MADDPG(env=env, learning_starts=warmup, seed=0),
        "MAAC (pi 128x128, attention 128, 4 heads, 2 critics)": lambda: MAAC(env=env, learning_starts=warmup, seed=0),
    }
    print(f"load average at start: {load_average()}")
    for name, make_model in off_policy.items():
        model = make_model()
        model.learn(warmup)  # fills the replay buffer with random actions; no update yet
        model.set_logger(configure(folder=None, format_strings=[]))
        model.train(gradient_steps=5, batch_size=BATCH_SIZE)  # warm-up
        start = time.thread_time()
        model.train(gradient_steps=timed, batch_size=BATCH_SIZE)
        per_step = (time.thread_time() - start) / timed
        print(f"{name}: {1000 * per_step:.1f} ms thread CPU per gradient step (batch {BATCH_SIZE})", flush=True)
    model = MAPPO(env=env, n_steps=args.rollout, seed=0)
    start = time.thread_time()
    model.learn(args.rollout)
    total = time.thread_time() - start
    start = time.thread_time()
    model.train()
    update = time.thread_time() - start
    print(f"MAPPO (64x64, LayerNorm): {args.rollout}-step rollout + update {total:.1f} s thread CPU; the update "
          f"({model.n_epochs} full-batch epochs) {update:.2f} s = {1000 * update / model.n_epochs:.0f} ms per epoch")
    print(f"load average at end: {load_average()}")
    env.close()


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """``--help``: the module docstring as written, and every option's default."""


def plain(text: str) -> str:
    """``text`` without reStructuredText markup (roles and double backticks), for ``--help``."""
    return re.sub(r":\w+:`([^`]*)`", r"\1", text).replace("``", "").replace("::\n", ":\n")


def main() -> None:
    """Run the chosen measurement with one torch thread."""
    parser = argparse.ArgumentParser(description=plain(__doc__), formatter_class=HelpFormatter)
    parser.add_argument("what", choices=["ci", "speed"],
                        help="ci: the CI-sized training runs against a random policy; speed: cost per gradient step")
    parser.add_argument("--steps", type=int,
                        help="ci: env steps per algorithm (None: the budgets of tests/test_baselines.py)")
    parser.add_argument("--env", default="VAFN/ThreeArmReach-v1", help="speed: env ID")
    parser.add_argument("--env-kwargs", type=json.loads, default={}, help='speed: JSON, e.g. \'{"n_arms": 4}\'')
    parser.add_argument("--warmup-steps", type=int, default=WARMUP_STEPS, help="speed: random steps before timing")
    parser.add_argument("--timed-steps", type=int, default=TIMED_STEPS, help="speed: gradient steps timed")
    parser.add_argument("--rollout", type=int, default=MAPPO_ROLLOUT, help="speed: MAPPO rollout length")
    args = parser.parse_args()
    torch.set_num_threads(1)
    {"ci": ci_returns, "speed": speed}[args.what](args)


if __name__ == "__main__":
    main()
