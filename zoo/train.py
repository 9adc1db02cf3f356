"""Train (or tune) a vafn agent exactly like ``python -m rl_zoo3.train``, with the vafn algorithms and YAMLs plugged in.

    python zoo/train.py --algo maml_sac --env VAFN/ThreeArmReach-v0 -n 20000 --seed 1 -tb tb -P
    python zoo/train.py --algo sac --env VAFN/ThreeArmReach-v0 -optimize --n-trials 20 -n 10000

Every rl_zoo3 flag works unchanged. Defaults added here (each only when the flag is absent): ``--conf-file
hyperparams/<algo>.yml``, ``--num-threads 1``, ``--gym-packages vafn_gym``, and for ``-optimize`` a local journal
``--storage <log-folder>/<algo>/optuna/<EnvName>.log`` with ``--study-name <algo>_<EnvName>`` (rerun the same command to
resume or to add a worker).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # `python zoo/train.py` puts zoo/ first on the path, not the repo root
    sys.path.insert(0, str(REPO_ROOT))
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))

import rl_zoo3.train as zoo_train  # noqa: E402
from huggingface_sb3 import EnvironmentName  # noqa: E402

import vafn_gym  # noqa: E402,F401  (registers the VAFN/* env IDs in this process)
from zoo.experiment import VAFNExperimentManager  # noqa: E402
from zoo.registry import UNAVAILABLE, register_algorithms  # noqa: E402

HYPERPARAMS_DIR = REPO_ROOT / "hyperparams"
DEFAULT_ALGO = "ppo"  # rl_zoo3's own default, kept so the wrapper changes no default
DEFAULT_LOG_FOLDER = "logs"


def _pre_parse(argv: list[str]) -> argparse.Namespace:
    """Read the few zoo flags the wrapper needs to fill defaults; everything else is left to rl_zoo3."""
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--algo", default=DEFAULT_ALGO)
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("-f", "--log-folder", default=DEFAULT_LOG_FOLDER)
    parser.add_argument("-conf", "--conf-file", default=None)
    parser.add_argument("--num-threads", type=int, default=None)
    parser.add_argument("--gym-packages", nargs="+", default=None)
    parser.add_argument("-optimize", "--optimize-hyperparameters", action="store_true")
    parser.add_argument("--storage", default=None)
    parser.add_argument("--study-name", default=None)
    return parser.parse_known_args(argv)[0]


def complete_argv(argv: list[str]) -> list[str]:
    """``argv`` plus the vafn defaults for every flag the user left out (see the module docstring)."""
    args = _pre_parse(argv)
    if args.algo in UNAVAILABLE:
        raise SystemExit(f"zoo/train.py: algorithm {args.algo!r} is not available: {UNAVAILABLE[args.algo]}")
    extra: list[str] = []
    if args.conf_file is None:
        conf = HYPERPARAMS_DIR / f"{args.algo}.yml"
        if conf.is_file():
            extra += ["--conf-file", str(conf)]
    if args.num_threads is None:
        extra += ["--num-threads", "1"]
    if args.optimize_hyperparameters:
        env_name = str(EnvironmentName(args.env))
        if args.storage is None:
            storage = Path(args.log_folder) / args.algo / "optuna" / f"{env_name}.log"
            extra += ["--storage", str(storage)]
        if args.study_name is None:
            extra += ["--study-name", f"{args.algo}_{env_name}"]
    if args.gym_packages is None:
        extra += ["--gym-packages", "vafn_gym"]  # last: nargs="+" swallows what follows
    return list(argv) + extra


def main(argv: list[str] | None = None) -> None:
    """Register the vafn algorithms, fill the vafn defaults and hand over to ``rl_zoo3.train.train()``."""
    register_algorithms()
    argv = complete_argv(sys.argv[1:] if argv is None else list(argv))
    zoo_train.ExperimentManager = VAFNExperimentManager
    saved_argv = sys.argv
    sys.argv = [str(Path(__file__)), *argv]
    try:
        zoo_train.train()
    finally:
        sys.argv = saved_argv


if __name__ == "__main__":
    main()
