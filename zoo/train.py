"""Train (or tune) a vafn agent exactly like ``python -m rl_zoo3.train``, with the vafn algorithms and YAMLs plugged in.

    python zoo/train.py --algo maml_sac --env VAFN/ThreeArmReach-v1 -n 30000 --seed 1 -tb tb -P
    python zoo/train.py --algo sac --env VAFN/ThreeArmReach-v1 -optimize --n-trials 20 -n 10000

Every rl_zoo3 flag works unchanged, except that ``--env`` is required (rl_zoo3 would silently train CartPole-v1).
Defaults added here (each only when the flag is absent): ``--conf-file hyperparams/<algo>.yml``, ``--num-threads 1``,
``--gym-packages vafn_gym``, and for ``-optimize`` a local journal
``--storage <log-folder>/<algo>/optuna/<EnvName>.log`` with ``--study-name <algo>_<EnvName>`` (rerun the same command
to resume or to add a worker). An RDB ``--storage`` URL (e.g. ``postgresql+psycopg2://user:password@host/db``) gets
Optuna heartbeats: ``--heartbeat-interval S`` (default 60) and ``--heartbeat-grace S`` (default twice the interval)
set how soon a dead worker's trial is failed and re-queued. See docs/tuning.md.
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

import vafn_gym  # noqa: E402  (registers the VAFN/* env IDs in this process)
from zoo.experiment import VAFNExperimentManager  # noqa: E402
from zoo.registry import UNAVAILABLE, register_algorithms  # noqa: E402
from zoo.tuning import HEARTBEAT_INTERVAL_S  # noqa: E402

HYPERPARAMS_DIR = REPO_ROOT / "hyperparams"
DEFAULT_ALGO = "ppo"  # rl_zoo3's own default, kept so the wrapper changes no default
DEFAULT_LOG_FOLDER = "logs"


def _pre_parse(argv: list[str]) -> argparse.Namespace:
    """Read the few zoo flags the wrapper needs to fill defaults; everything else is left to rl_zoo3."""
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--algo", default=DEFAULT_ALGO)
    parser.add_argument("--env", default=None)
    parser.add_argument("-f", "--log-folder", default=DEFAULT_LOG_FOLDER)
    parser.add_argument("-conf", "--conf-file", default=None)
    parser.add_argument("--num-threads", type=int, default=None)
    parser.add_argument("--gym-packages", nargs="+", default=None)
    parser.add_argument("-optimize", "--optimize-hyperparameters", action="store_true")
    parser.add_argument("--storage", default=None)
    parser.add_argument("--study-name", default=None)
    return parser.parse_known_args(argv)[0]


def require_env(argv: list[str]) -> None:
    """Exit with a one-line error when ``--env`` is missing (rl_zoo3 would silently train CartPole-v1)."""
    if _pre_parse(argv).env is None and not {"-h", "--help"} & set(argv):
        raise SystemExit(
            f"zoo/train.py: --env is required, one of: {', '.join(vafn_gym.ENV_IDS)} (or any registered Gymnasium ID)"
        )


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
    if args.optimize_hyperparameters and args.env is not None:
        env_name = str(EnvironmentName(args.env))
        if args.storage is None:
            storage = Path(args.log_folder) / args.algo / "optuna" / f"{env_name}.log"
            extra += ["--storage", str(storage)]
        if args.study_name is None:
            extra += ["--study-name", f"{args.algo}_{env_name}"]
    if args.gym_packages is None:
        extra += ["--gym-packages", "vafn_gym"]  # last: nargs="+" swallows what follows
    return list(argv) + extra


def _positive_seconds(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number of seconds >= 1, got {text}")
    return value


def _wrapper_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="zoo/train.py", add_help=False, allow_abbrev=False)
    group = parser.add_argument_group("vafn options (the rl_zoo3 options follow)")
    group.add_argument(
        "--heartbeat-interval", type=_positive_seconds, default=HEARTBEAT_INTERVAL_S, metavar="S",
        help="-optimize with an RDB --storage URL: seconds between Optuna heartbeats of a running trial "
        f"(default: {HEARTBEAT_INTERVAL_S})",
    )
    group.add_argument(
        "--heartbeat-grace", type=_positive_seconds, default=None, metavar="S",
        help="seconds without a heartbeat after which another worker fails and re-queues the trial "
        "(default: twice --heartbeat-interval)",
    )
    return parser


def split_heartbeat_args(argv: list[str]) -> tuple[int, int | None, list[str]]:
    """``(heartbeat interval, grace period, the other arguments)``: the wrapper's own flags, removed for rl_zoo3."""
    parser = _wrapper_parser()
    if {"-h", "--help"} & set(argv):
        print(parser.format_help())
    args, rest = parser.parse_known_args(argv)
    if args.heartbeat_grace is not None and args.heartbeat_grace <= args.heartbeat_interval:
        parser.error(
            f"--heartbeat-grace ({args.heartbeat_grace} s) must exceed --heartbeat-interval "
            f"({args.heartbeat_interval} s), or live trials are failed between two heartbeats"
        )
    return args.heartbeat_interval, args.heartbeat_grace, rest


def main(argv: list[str] | None = None) -> None:
    """Register the vafn algorithms, fill the vafn defaults and hand over to ``rl_zoo3.train.train()``."""
    register_algorithms()
    interval, grace, argv = split_heartbeat_args(sys.argv[1:] if argv is None else list(argv))
    require_env(argv)
    argv = complete_argv(argv)
    saved_manager, saved_argv = zoo_train.ExperimentManager, sys.argv
    zoo_train.ExperimentManager = VAFNExperimentManager.with_heartbeat(interval, grace)
    sys.argv = [str(Path(__file__)), *argv]
    try:
        zoo_train.train()
    finally:
        sys.argv = saved_argv
        zoo_train.ExperimentManager = saved_manager


if __name__ == "__main__":
    main()
