"""Cost of one MAML-SAC outer (meta) step against one plain SB3 SAC gradient step, looped vs vmapped meta-batch.

Times are the best of ``--repeats`` calls in thread CPU time. Both use the same ``--policy`` (default: SB3's MLP,
256x256) on ``--env``'s spaces (15-D/9-D for three arms) and the same batch size; buffers hold random data (the cost
does not depend on the values). Prints a table; never asserts a speed.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/maml_step_cost.py --steps 20 --repeats 3
    OMP_NUM_THREADS=1 python benchmarks/maml_step_cost.py --env VAFN/MultiArmReach-v1 --env-kwargs '{"n_arms": 6}'
"""

from __future__ import annotations

import argparse
import json
import re
import time
from collections.abc import Callable
from functools import partial

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.logger import configure

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_sb3 import SAC
from vafn_sb3.common.adaptation import SupportSet
from vafn_sb3.maml_sac import MAMLSAC

ENV_ID = "VAFN/ThreeArmReachHidden-v1"


def fill_replay(buffer: ReplayBuffer, n: int, obs_dim: int, act_dim: int, rng: np.random.Generator) -> None:
    """Add ``n`` random transitions to an SB3 replay buffer (one env)."""
    for _ in range(n):
        buffer.add(
            rng.normal(size=(1, obs_dim)), rng.normal(size=(1, obs_dim)), rng.uniform(-1, 1, size=(1, act_dim)),
            rng.normal(size=1), np.zeros(1), [{}],
        )


def random_support(n: int, obs_dim: int, act_dim: int, rng: np.random.Generator) -> SupportSet:
    """A support set of random transitions with an episode end every 100 steps."""
    ends = np.zeros(n, dtype=np.float32)
    ends[99::100] = 1.0
    ends[-1] = 1.0
    return SupportSet(
        observations=rng.normal(size=(n, obs_dim)).astype(np.float32),
        actions=rng.uniform(-1, 1, size=(n, act_dim)).astype(np.float32),
        rewards=rng.normal(size=n).astype(np.float32),
        next_observations=rng.normal(size=(n, obs_dim)).astype(np.float32),
        terminated=np.zeros(n, dtype=np.float32),
        episode_ends=ends,
        successes=np.zeros(n, dtype=np.float32),
        collisions=np.zeros(n, dtype=np.float32),
    )


def time_call(fn: Callable[[], object], repeats: int) -> float:
    """Best thread CPU time of ``repeats`` calls of ``fn`` (after one warm-up call).

    CPU time of the calling thread, not wall time: on a shared machine wall time mostly measures the other processes.
    """
    fn()
    best = float("inf")
    for _ in range(repeats):
        start = time.thread_time()
        fn()
        best = min(best, time.thread_time() - start)
    return best


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """``--help``: the module docstring as written, and every option's default."""


def plain(text: str) -> str:
    """``text`` without reStructuredText markup (roles and double backticks), for ``--help``."""
    return re.sub(r":\w+:`([^`]*)`", r"\1", text).replace("``", "").replace("::\n", ":\n")


def main() -> None:
    """Time plain SAC and MAML-SAC (loop/vmap x first/second order x K) and print per-step costs and ratios."""
    parser = argparse.ArgumentParser(description=plain(__doc__), formatter_class=HelpFormatter)
    parser.add_argument("--env", default=ENV_ID, help="env ID whose spaces size the networks")
    parser.add_argument("--env-kwargs", type=json.loads, default={}, help='env kwargs as JSON, e.g. \'{"n_arms": 4}\'')
    parser.add_argument("--policy", default="MlpPolicy", help="policy alias of both (MlpPolicy or SharedAgentPolicy)")
    parser.add_argument("--steps", type=int, default=20, help="gradient steps per timed call")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls (the best is kept)")
    parser.add_argument("--meta-batch-size", type=int, default=5, help="tasks per MAML-SAC outer step")
    parser.add_argument("--n-support", type=int, default=200, help="support transitions per task")
    parser.add_argument("--batch-size", type=int, default=256, help="minibatch size of both algorithms")
    parser.add_argument("--inner-steps", type=int, nargs="+", default=[1, 3], help="inner-loop steps K to time")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    env = gym.make(args.env, **{"max_length": 1, **args.env_kwargs})
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    logger = configure(None, [])

    sac = SAC(args.policy, env, batch_size=args.batch_size, seed=0)
    sac.set_logger(logger)
    fill_replay(sac.replay_buffer, 2 * args.batch_size, obs_dim, act_dim, rng)
    sac_step = time_call(lambda: sac.train(gradient_steps=args.steps, batch_size=args.batch_size), args.repeats)
    sac_step /= args.steps
    print(f"plain SAC gradient step ({args.policy}): {1e3 * sac_step:.2f} ms (batch {args.batch_size})")
    print(f"{'mode':>5} {'order':>6} {'K':>2} {'ms/outer step':>14} {'x SAC step':>11}")
    for k in args.inner_steps:
        for second_order in (False, True):
            for mode in ("loop", "vmap"):
                model = MAMLSAC(
                    args.policy, env, meta_batch_size=args.meta_batch_size, n_support=args.n_support,
                    inner_steps=k, second_order=second_order, outer_steps=args.steps, meta_batch_mode=mode,
                    batch_size=args.batch_size, seed=0,
                )
                model.set_logger(logger)
                task_ids = list(range(args.meta_batch_size))
                for task_id in task_ids:
                    model.support_sets[task_id] = random_support(args.n_support, obs_dim, act_dim, rng)
                    fill_replay(model._query_buffer(task_id), 2 * args.batch_size, obs_dim, act_dim, rng)
                step = time_call(partial(model.meta_train, task_ids), args.repeats) / args.steps
                order = "second" if second_order else "first"
                print(f"{mode:>5} {order:>6} {k:>2} {1e3 * step:>14.1f} {step / sac_step:>11.1f}")
    env.close()


if __name__ == "__main__":
    main()
