"""Learning benchmark: train an algorithm from its YAML on short train instructions, evaluate on held-out test ones.

    python benchmarks/learning.py --algo sac --env VAFN/ThreeArmReach-v1 --seeds 0 1 2 --steps 50000

Every ``--eval-every`` env steps the policy runs once on ``--n-eval`` validation instructions (lengths 1-10, the
validation suite of :class:`vafn_gym.InstructionBenchmark`; the curve a run is watched and tuned on); at the end on
``--n-test`` held-out test instructions (the versioned test suite, 200 distinct). Writes
``<out>/<algo>_<env>_curves.csv`` (one row per seed and evaluation, its ``split`` named) and
``<out>/<algo>_<env>_summary.json`` (final test success / collision / episode length with 95 % CIs over seeds, env
steps to first cross 0.95, wall and CPU time), and prints them. Training uses one torch thread. ``--save DIR`` keeps
each seed's final model for ``benchmarks/export_pretrained.py`` and ``benchmarks/adaptation.py``: weights only
(``vafn_sb3.save_weights``, which loads without running code), or an SB3 zip for an algorithm with no weights format
(``ppo_lstm``).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))
os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from rl_zoo3.utils import get_wrapper_class  # noqa: E402
from stable_baselines3.common.base_class import BaseAlgorithm  # noqa: E402
from tqdm import tqdm  # noqa: E402

import vafn_gym  # noqa: E402,F401  (registers the env IDs)
from vafn_gym import InstructionBenchmark, confidence_half_width, episode_rates  # noqa: E402
from vafn_gym.files import write_csv_rows  # noqa: E402
from zoo.hyperparams import load_entry, load_hyperparams, load_training_env_kwargs  # noqa: E402
from zoo.jobs import short_commit  # noqa: E402
from vafn_sb3 import save_weights  # noqa: E402
from vafn_sb3.registry import weights_classes  # noqa: E402
from zoo.registry import register_algorithms, require_algorithm  # noqa: E402

SUCCESS_TARGET = 0.95


def training_env_kwargs(args: argparse.Namespace) -> dict:
    """The training env's kwargs: the YAML's ``env_kwargs`` (training only), ``--hyperparams``' and ``--env-kwargs``."""
    return {**load_training_env_kwargs(args.algo, args.env), **args.hyperparams.get("env_kwargs", {}),
            **args.env_kwargs}


def training_env_wrapper(args: argparse.Namespace) -> Callable[[gym.Env], gym.Env] | None:
    """The training env's wrapper: ``--hyperparams``' ``env_wrapper``, else the YAML's (rl_zoo3's format)."""
    wrapper = args.hyperparams.get("env_wrapper", load_entry(args.algo, args.env).get("env_wrapper"))
    return get_wrapper_class({"env_wrapper": wrapper})


def save_model(model: BaseAlgorithm, path: Path) -> None:
    """``model`` at ``path``: weights only where its algorithm has that format, else an SB3 zip (which unpickles)."""
    if weights_classes().get(type(model).__name__) is type(model):
        path.parent.mkdir(parents=True, exist_ok=True)
        save_weights(model, path)
    else:
        model.save(path)


def train_one(args: argparse.Namespace, seed: int, benchmark: InstructionBenchmark) -> tuple[list[dict], object]:
    """Train one seed; returns its evaluation rows (validation ones, the last one on the test suite) and the model."""
    kwargs, yaml_steps, policy = load_hyperparams(args.algo, args.env)
    kwargs.update({key: value for key, value in args.hyperparams.items() if key not in ("env_kwargs", "env_wrapper")})
    env = gym.make(args.env, max_length=args.train_max_length, **training_env_kwargs(args))
    wrapper = training_env_wrapper(args)
    if wrapper is not None:
        env = wrapper(env)
    model = require_algorithm(args.algo)(policy, env, seed=seed, verbose=0, **kwargs)
    steps = args.steps or yaml_steps
    rows, wall0, cpu0 = [], time.perf_counter(), time.process_time()
    with tqdm(total=steps, desc=f"{args.algo} seed {seed}", unit="step") as bar:
        while model.num_timesteps < steps:
            before = model.num_timesteps
            model.learn(min(args.eval_every, steps - model.num_timesteps), reset_num_timesteps=False)
            bar.update(model.num_timesteps - before)
            final = model.num_timesteps >= steps
            wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0  # evaluation time included
            n_tasks, split = (args.n_test, "test") if final else (args.n_eval, "validation")
            metrics = episode_rates(benchmark.evaluate(model, n_tasks=n_tasks, split=split))
            rows.append({"seed": seed, "timesteps": model.num_timesteps, "n_tasks": n_tasks, "split": split,
                         "wall_s": round(wall, 1), "cpu_s": round(cpu, 1), **metrics})
            bar.set_postfix(success=f"{metrics['success']:.2f}", collision=f"{metrics['collision']:.2f}")
    env.close()
    return rows, model


def read_curves(path: Path, exclude: list[int]) -> list[dict]:
    """Rows of an existing curves file (numbers parsed), without the seeds in ``exclude``."""
    with path.open(newline="") as handle:
        rows = [{k: (v if k == "split" else float(v) if k not in ("seed", "timesteps", "n_tasks") else int(v))
                 for k, v in row.items()}
                for row in csv.DictReader(handle)]
    return [row for row in rows if row["seed"] not in exclude]


def summarise(rows: list[dict], seeds: list[int]) -> dict:
    """Final metrics over seeds (mean ± 95 % Student-t CI) and steps to the first evaluation at >= 0.95 success."""
    finals = [max((r for r in rows if r["seed"] == s), key=lambda r: r["timesteps"]) for s in seeds]
    summary: dict = {"seeds": seeds, "n_test": finals[0]["n_tasks"]}
    for key in ("success", "collision", "episode_steps", "wall_s", "cpu_s"):
        values = np.array([f[key] for f in finals], dtype=np.float64)
        summary[key] = {"mean": float(values.mean()), "ci95": float(confidence_half_width(values[:, None])[0])}
    summary["steps_to_success_0.95"] = {
        str(s): next((r["timesteps"] for r in rows if r["seed"] == s and r["success"] >= SUCCESS_TARGET), None)
        for s in seeds
    }
    return summary


def main() -> None:
    """Parse arguments, train every seed, write the curves and the summary."""
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--algo", default="sac", help="zoo key of the algorithm (sac, mtsac, maml_sac, ...)")
    parser.add_argument("--env", default="VAFN/ThreeArmReach-v1", help="env ID")
    parser.add_argument("--env-kwargs", type=json.loads, default={}, help='JSON, e.g. \'{"inactive_arms": "policy"}\'')
    parser.add_argument("--hyperparams", type=json.loads, default={},
                        help="JSON overrides of the YAML values (its env_kwargs and env_wrapper configure the "
                        "training env only)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="training seeds")
    parser.add_argument("--steps", type=int, default=None, help="env steps per seed (default: the YAML's n_timesteps)")
    parser.add_argument("--train-max-length", type=int, default=3, help="longest training instruction")
    parser.add_argument("--eval-every", type=int, default=10_000, help="env steps between evaluations")
    parser.add_argument("--n-eval", type=int, default=30, help="validation instructions per intermediate evaluation")
    parser.add_argument("--n-test", type=int, default=200, help="test instructions of the final evaluation")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "results" / "learning", help="output folder")
    parser.add_argument("--tag", default="", help="suffix of the output files")
    parser.add_argument("--save", type=Path, default=None, help="folder for each seed's final model")
    parser.add_argument("--append", action="store_true",
                        help="keep the other seeds' rows of an existing curves file (re-read after every seed, so "
                        "parallel processes with different --seeds can share it); the summary covers all its seeds")
    args = parser.parse_args()
    torch.set_num_threads(1)
    register_algorithms()
    benchmark = InstructionBenchmark(args.env, 1, 10, n_test=args.n_test, env_kwargs=args.env_kwargs)
    name = f"{args.algo}_{args.env.split('/')[-1]}{args.tag}"
    args.out.mkdir(parents=True, exist_ok=True)
    curves = args.out / f"{name}_curves.csv"
    own: list[dict] = []
    for seed in args.seeds:
        seed_rows, model = train_one(args, seed, benchmark)
        own.extend(seed_rows)
        if args.save is not None:
            save_model(model, args.save / f"{name}_seed{seed}.zip")
        # Re-read just before writing, so seeds run in parallel processes with --append all land in one file.
        rows = (read_curves(curves, exclude=args.seeds) if args.append and curves.is_file() else []) + own
        write_csv_rows(rows, curves, missing="nan")  # rewritten after every seed
    seeds = sorted({row["seed"] for row in rows})
    summary = {"algo": args.algo, "env": args.env, "env_kwargs": args.env_kwargs,
               "train_env_kwargs": training_env_kwargs(args),
               "hyperparams": args.hyperparams,
               "train_max_length": args.train_max_length, "command": " ".join(sys.argv), "commit": short_commit(),
               **summarise(rows, seeds)}
    (args.out / f"{name}_summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
