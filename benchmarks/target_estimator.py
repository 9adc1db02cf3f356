"""Learned target inference: train a LearnedTargetEstimator on hidden-target readings, measure it on held-out ones.

    python benchmarks/target_estimator.py --seeds 0 1 2 3 4 --out runs/target_estimator

A goal-observing policy (default: the packaged ``load_pretrained("mappo", env_id="VAFN/ThreeArmReachGoal-v1")``) runs
on ``--train-tasks`` train-split instructions of the hidden-target env, moving as
``TargetInferencePolicy(inference="learned")`` does (:func:`vafn_sb3.collect_waypoint_readings`); each waypoint's
first ``--n-readings`` (position, distance) readings, labelled with the target the env knows, train one
:class:`vafn_sb3.LearnedTargetEstimator` per seed (regression; it is never told that the reading is ``|p - t|``). The
same collection on the benchmark's held-out test instructions measures the estimation error, beside trilateration of
the same readings. Writes ``--out/target_estimator_seed<N>.pt`` (for ``benchmarks/adaptation.py --target-estimator``
and ``zoo/online_control.py --infer-targets learned --target-estimator``) and ``--out/target_estimator.json`` (errors,
sizes, CPU times, the command); prints a Markdown table. Never asserts a number.

``--estimator gradient`` meta-trains a :class:`vafn_sb3.GradientTargetEstimator` per seed instead (a reading model
whose 3-number context adapts by ``--steps`` gradient steps; files ``gradient_estimator_seed<N>.pt`` and
``gradient_estimator.json``, for ``benchmarks/adaptation.py --gradient-estimator``), and ``--estimator gradient-plain``
its baseline without meta-learning (``gradient_plain_estimator_*``); both report the held-out error after each
``--report-k`` steps. The readings are saved as ``--out/readings.npz``; ``--readings`` reuses such a file instead of
collecting again (the JSON of the run that collected it says from which env, model and instructions).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from vafn_gym import InstructionBenchmark, trilaterate  # noqa: E402
from vafn_gym.constants import SUCCESS_TOLERANCE  # noqa: E402
from vafn_sb3 import (  # noqa: E402
    GradientTargetEstimator,
    LearnedTargetEstimator,
    collect_waypoint_readings,
    load_pretrained,
)
from vafn_sb3.loading import add_trust_flag, load_model  # noqa: E402
from vafn_sb3.inference import ESTIMATOR_READINGS, REFINE_SOLVERS, REFINE_STEPS  # noqa: E402
from zoo.registry import register_algorithms  # noqa: E402

#: Reset seeds of the collection episodes (train and test episodes never share one).
TRAIN_EPISODE_SEED, TEST_EPISODE_SEED = 0, 500_000
#: ``--estimator`` kinds: file prefix and default hidden sizes of each.
ESTIMATORS = {"regression": ("target_estimator", [256, 256]), "gradient": ("gradient_estimator", [128, 128]),
              "gradient-plain": ("gradient_plain_estimator", [128, 128])}


def error_stats(estimates: np.ndarray, targets: np.ndarray) -> dict[str, float]:
    """Error median, 90th percentile, max in cm (inf: no estimate); shares within 1 cm and the tolerance; misses."""
    errors = np.linalg.norm(estimates - targets, axis=1)
    missing = np.isnan(errors)
    errors = np.where(missing, np.inf, errors)  # no estimate counts as a miss (an infinite error)
    return {"median_cm": 100 * float(np.percentile(errors, 50, method="higher")),
            "p90_cm": 100 * float(np.percentile(errors, 90, method="higher")), "max_cm": 100 * float(errors.max()),
            "within_1cm": float((errors < 0.01).mean()), "within_tolerance": float((errors < SUCCESS_TOLERANCE).mean()),
            "no_estimate": int(missing.sum())}


def trilaterated(readings: dict[str, np.ndarray]) -> np.ndarray:
    """Trilateration of every row's readings (NaN where the points span no volume)."""
    rows = [trilaterate(list(points), list(distances)) for points, distances in
            zip(readings["points"], readings["distances"])]
    return np.array([np.full(3, np.nan) if row is None else row for row in rows])


def load_readings(path: Path, flag: str) -> tuple[dict, dict]:
    """The train and test readings of a ``readings.npz`` this benchmark saved (``SystemExit`` naming ``flag``)."""
    try:
        with np.load(path) as saved:
            split = {name: {key.split("/", 1)[1]: saved[key] for key in saved.files if key.startswith(name + "/")}
                     for name in ("train", "test")}
        if any(set(split[name]) != {"points", "distances", "targets", "arms"} for name in split):
            raise ValueError("it lacks train/ or test/ points, distances, targets and arms")
    except (OSError, ValueError) as error:
        raise SystemExit(f"{flag} {path}: not a readings file of this benchmark ({error})") from None
    return split["train"], split["test"]


def refined(estimator: GradientTargetEstimator, readings: dict[str, np.ndarray], first: np.ndarray,
            solver: str) -> np.ndarray:
    """The ``first`` estimates refined at every later reading of each row by ``solver``'s default steps.

    As ``GradientInferencePolicy`` refines, except for its restart from the shared region's centre (the env's).
    """
    n = estimator.n_readings
    estimates = first.copy()
    for row, (points, distances) in enumerate(zip(readings["points"], readings["distances"])):
        for count in range(n + 1, len(points) + 1):
            estimates[row] = estimator.refine(points[:count], distances[:count], estimates[row],
                                              REFINE_STEPS[solver], solver)
    return estimates


def joined_readings(paths: list[Path]) -> tuple[dict, dict]:
    """The train and test splits of several ``--refine-readings`` files, each split concatenated in the given order."""
    splits = [load_readings(path, "--refine-readings") for path in paths]
    if len({split[0]["points"].shape[1] for split in splits}) > 1:
        raise SystemExit("--refine-readings: the files have different numbers of readings per waypoint")
    return tuple({key: np.concatenate([split[index][key] for split in splits]) for key in splits[0][index]}
                 for index in (0, 1))


def collect_or_load(args: argparse.Namespace, model: Any) -> tuple[dict, dict, float | None]:
    """Train and test readings: from ``--readings`` (no collection CPU time), or collected and saved to ``--out``."""
    if args.readings is not None:
        return (*load_readings(args.readings, "--readings"), None)
    benchmark = InstructionBenchmark(args.env, max_length=args.max_length, n_test=args.test_tasks,
                                     env_kwargs=args.env_kwargs, n_train=args.train_tasks)
    env = benchmark.make_env()
    try:
        start = time.process_time()
        train, test = (collect_waypoint_readings(model, env, tasks, seed, args.n_readings,
                                                 heading_after=args.heading_after)
                       for tasks, seed in ((benchmark.train_tasks, TRAIN_EPISODE_SEED),
                                           (benchmark.test_tasks, TEST_EPISODE_SEED)))
        collect_cpu_s = time.process_time() - start
    finally:
        env.close()
    splits = {"train": train, "test": test}
    np.savez(args.out / "readings.npz",
             **{f"{name}/{key}": value for name, readings in splits.items() for key, value in readings.items()})
    return train, test, collect_cpu_s


def goal_policy(args: argparse.Namespace) -> Any:
    """The goal-observing model whose motion the readings come from."""
    if args.model is None:
        return load_pretrained("mappo", env_id="VAFN/ThreeArmReachGoal-v1")
    register_algorithms()
    return load_model(args.model, args.algo, trust_remote_code=args.trust_remote_code)[0]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Collect, fit one estimator per seed, measure on held-out readings; write the files, print the table."""
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--env", default="VAFN/ThreeArmReachHidden-v1", help="hidden-target env ID")
    parser.add_argument("--env-kwargs", type=json.loads, default={}, help="JSON kwargs of the env")
    parser.add_argument("--model", type=Path, default=None,
                        help="goal-observing model (None: the packaged goal-observing MAPPO)")
    parser.add_argument("--algo", default=None, help="algorithm of --model (None: from its file)")
    add_trust_flag(parser)
    parser.add_argument("--train-tasks", type=int, default=1500, help="train-split instructions to collect on")
    parser.add_argument("--test-tasks", type=int, default=100, help="held-out test instructions to measure on")
    parser.add_argument("--max-length", type=int, default=10,
                        help="longest instruction (long ones give later waypoints, from arms that have moved a lot)")
    parser.add_argument("--n-readings", type=int, default=ESTIMATOR_READINGS, help="readings the estimator reads")
    parser.add_argument("--heading-after", type=int, default=None,
                        help="collecting: the arm heads for the prior goal until this many readings, then for its "
                             "target (None: --n-readings, as inference='learned' moves; 4 with --n-readings 24: "
                             "readings of an arm heading for its target, as an adapted policy's arm does)")
    parser.add_argument("--estimator", choices=list(ESTIMATORS), default="regression",
                        help="what to train: the regression network, the meta-learned gradient estimator, or its "
                             "baseline without meta-learning")
    parser.add_argument("--steps", type=int, default=20, help="gradient steps the gradient estimators train for")
    parser.add_argument("--report-k", type=int, nargs="+", default=[0, 1, 2, 5, 10, 20, 50],
                        help="gradient steps at which the gradient estimators' held-out error is reported")
    parser.add_argument("--readings", type=Path, default=None,
                        help="readings.npz of an earlier run to train on instead of collecting")
    parser.add_argument("--refine-readings", type=Path, nargs="+", default=None,
                        help="with --estimator gradient(-plain): readings.npz of runs with many readings per "
                             "waypoint (e.g. --n-readings 24, with and without --heading-after 4; all with the same "
                             "number) to fit the estimator's refinement model on; their test splits measure the "
                             "refined error")
    parser.add_argument("--hidden", type=int, nargs="+", default=None,
                        help="hidden layer sizes (None: 256 256 for regression, 128 128 for the gradient estimators)")
    parser.add_argument("--epochs", type=int, default=200, help="passes over the training readings")
    parser.add_argument("--seeds", type=int, nargs="*", default=[0],
                        help="one estimator per seed (initial weights); none: only collect the readings")
    parser.add_argument("--out", type=Path, default=Path("runs/target_estimator"), help="output folder")
    args = parser.parse_args(argv)
    if args.train_tasks < 1 or args.test_tasks < 1:
        parser.error("--train-tasks and --test-tasks must be >= 1")
    if args.n_readings < 4:
        parser.error("--n-readings must be at least 4 (a point in space needs four distances)")
    if args.heading_after is not None and not 4 <= args.heading_after <= args.n_readings:
        parser.error("--heading-after must be between 4 and --n-readings")
    if args.steps < 0 or min(args.report_k) < 0:
        parser.error("--steps and --report-k must be >= 0")
    if args.refine_readings is not None and args.estimator == "regression":
        parser.error("--refine-readings fits the refinement model of the gradient estimators")
    prefix, default_hidden = ESTIMATORS[args.estimator]
    args.hidden = args.hidden or default_hidden
    torch.set_num_threads(1)
    model = None
    if args.readings is None:
        try:  # before the collection, so that a bad --model fails in seconds
            model = goal_policy(args)
        except (ValueError, FileNotFoundError) as error:
            parser.error(f"--model: {error}")
    refine_train, refine_test = ({}, {}) if args.refine_readings is None else joined_readings(args.refine_readings)
    args.out.mkdir(parents=True, exist_ok=True)
    train, test, collect_cpu_s = collect_or_load(args, model)
    report: dict[str, Any] = {
        "command": shlex.join(sys.argv), "env": args.env, "env_kwargs": args.env_kwargs,
        "model": str(args.model or "pretrained mappo (VAFN/ThreeArmReachGoal-v1)"), "max_length": args.max_length,
        "train_tasks": args.train_tasks, "test_tasks": args.test_tasks, "train_readings": len(train["points"]),
        "test_readings": len(test["points"]), "n_readings": args.n_readings, "estimator": args.estimator,
        "hidden": args.hidden, "epochs": args.epochs, "readings": str(args.readings or args.out / "readings.npz"),
        "collect_cpu_s": None if collect_cpu_s is None else round(collect_cpu_s, 1),
        "trilateration": {"train": error_stats(trilaterated(train), train["targets"]),
                          "test": error_stats(trilaterated(test), test["targets"])},
        "learned": {},
    }
    gradient = args.estimator != "regression"
    if gradient:
        report["steps"] = args.steps
    if refine_train:
        report["refinement"] = {"readings": [str(path) for path in args.refine_readings],
                                "train_readings": len(refine_train["points"]),
                                "test_readings": len(refine_test["points"]),
                                "readings_per_waypoint": refine_train["points"].shape[1], "refine_steps": REFINE_STEPS}
    for seed in args.seeds:
        start = time.process_time()
        if gradient:
            estimator = GradientTargetEstimator(args.n_readings, args.hidden, steps=args.steps, seed=seed)
            losses = estimator.fit(train["points"], train["distances"], train["targets"],
                                   meta=args.estimator == "gradient", epochs=args.epochs, seed=seed)
        else:
            estimator = LearnedTargetEstimator(args.n_readings, args.hidden, seed=seed)
            losses = estimator.fit(train["points"], train["distances"], train["targets"], epochs=args.epochs, seed=seed)
        if refine_train:
            estimator.fit_refinement(refine_train["points"], refine_train["distances"], refine_train["targets"],
                                     epochs=args.epochs, seed=seed)
        fit_cpu_s = time.process_time() - start
        estimator.save(args.out / f"{prefix}_seed{seed}.pt")
        report["learned"][str(seed)] = {
            "train": error_stats(estimator.predict(train["points"], train["distances"]), train["targets"]),
            "test": error_stats(estimator.predict(test["points"], test["distances"]), test["targets"]),
            "final_loss": losses[-1], "fit_cpu_s": round(fit_cpu_s, 1),
        }
        if gradient:
            report["learned"][str(seed)]["test_by_k"] = {
                str(k): error_stats(estimator.predict(test["points"], test["distances"], steps=k), test["targets"])
                for k in args.report_k}
        if refine_test:  # the first estimate from the first readings, then refined at every later one
            first = estimator.predict(refine_test["points"], refine_test["distances"])
            report["learned"][str(seed)]["test_refined"] = {
                "first": error_stats(first, refine_test["targets"]),
                **{f"refined_{solver}": error_stats(refined(estimator, refine_test, first, solver),
                                                    refine_test["targets"]) for solver in REFINE_SOLVERS}}
    (args.out / f"{prefix}.json").write_text(json.dumps(report, indent=2))

    if gradient:
        print(f"held-out error after K gradient steps ({args.estimator}, trained for {args.steps}): median cm, "
              f"share within the success tolerance\n")
        print("| seed | " + " | ".join(f"K = {k}" for k in args.report_k) + " |")
        print("|---|" + "---|" * len(args.report_k))
        for seed, entry in report["learned"].items():
            cells = [f"{stats['median_cm']:.2f}, {stats['within_tolerance']:.3f}"
                     for stats in entry["test_by_k"].values()]
            print(f"| {seed} | {' | '.join(cells)} |")
        print()
    if refine_train:
        print(f"refinement: {report['refinement']['test_readings']} held-out waypoints with "
              f"{report['refinement']['readings_per_waypoint']} readings each; error (median cm, share within the "
              f"success tolerance) from the first readings, and after refining at every later reading\n")
        print("| seed | first estimate | " + " | ".join(f"refined, {solver}" for solver in REFINE_SOLVERS) + " |")
        print("|---|---|" + "---|" * len(REFINE_SOLVERS))
        for seed, entry in report["learned"].items():
            cells = [f"{stats['median_cm']:.2f}, {stats['within_tolerance']:.3f}"
                     for stats in entry["test_refined"].values()]
            print(f"| {seed} | {' | '.join(cells)} |")
        print()
    print(f"{report['train_readings']} training waypoints ({args.train_tasks} train-split instructions), "
          f"{report['test_readings']} held-out waypoints ({args.test_tasks} test instructions); errors in cm\n")
    print("| estimator | split | median | 90th pct | max | within 1 cm | within the success tolerance |")
    print("|---|---|---|---|---|---|---|")
    rows = [("trilateration", report["trilateration"])]
    rows += [(f"{args.estimator}, seed {seed}", entry) for seed, entry in report["learned"].items()]
    for name, entry in rows:
        for split in ("train", "test"):
            stats = entry[split]
            cells = [f"{stats[key]:.2f}" if np.isfinite(stats[key]) else "no estimate"
                     for key in ("median_cm", "p90_cm", "max_cm")]
            print(f"| {name} | {split} | {' | '.join(cells)} | {stats['within_1cm']:.3f} "
                  f"| {stats['within_tolerance']:.3f} |")
    return report


if __name__ == "__main__":
    main()
