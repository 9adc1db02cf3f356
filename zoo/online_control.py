"""Run the online adaptive controller (Algorithm 1) on the instruction stream; write the per-instruction CSV and a plot.

Examples::

    # the packaged learned policy on a scripted schedule (step:instruction; ...)
    python zoo/online_control.py --pretrained sac --steps 1500 --schedule "0:2,3,1;10:1,2;600:3,1,2" --out runs/online

    # the same with the scripted controller as the policy (no adaptation)
    python zoo/online_control.py --policy scripted --steps 1500 --schedule "0:2,3,1;10:1,2;600:3,1,2" --out runs/online

    # any saved SB3 model (SAC, MTSAC, MAML-SAC, ...); Poisson arrivals of held-out instructions, K=5 rounds each
    python zoo/online_control.py --model runs/model.zip --targets per_arm --max-length 2 --split test \\
        --poisson-rate 0.004 --steps 3000 --k 5 --out runs/online

    # a model trained with observed targets (observe_goal=True) on hidden targets, through target inference
    python zoo/online_control.py --model runs/goal_mappo.zip --infer-targets probe --targets per_arm \\
        --schedule "0:1,2,3;400:3,1,2" --steps 800 --out runs/online_hidden

    # ... and its rows added to a table of several runs, labelled (a rerun replaces its own rows)
    python zoo/online_control.py --model runs/goal_mappo_seed3.zip --infer-targets gradient --targets per_arm \\
        --schedule "0:1,2,3;400:3,1,2" --steps 800 --out runs/online_hidden \\
        --append-to results/online_hidden/stream_gradient_vs_probe.csv --label mappo_gradient
"""

from __future__ import annotations

import argparse
import csv
import sys
import warnings
from dataclasses import asdict, fields
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # `python zoo/online_control.py` puts zoo/ first on the path, not the repo root
    sys.path.insert(0, str(REPO_ROOT))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import vafn_gym  # noqa: E402,F401  (registers the env IDs)
from vafn_gym import TARGET_MODES, RandomPolicy, ScriptedController  # noqa: E402
from vafn_gym.files import write_csv_rows  # noqa: E402
from vafn_gym.queue import PoissonArrivals, ScheduledArrivals  # noqa: E402
from vafn_sb3 import load_pretrained, pretrained_info  # noqa: E402
from vafn_media.cli import OneLineParser  # noqa: E402
from vafn_sb3.loading import add_trust_flag, family_mismatch, load_model, training_env, training_seed  # noqa: E402
from vafn_sb3.online import InstructionLog, OnlineController  # noqa: E402
from vafn_sb3.inference import (  # noqa: E402
    ESTIMATOR_MODES,
    INFERENCE_MODES,
    REFINE_SOLVER,
    REFINE_SOLVERS,
    REFINE_STEPS,
    inference_policy_for_env,
    load_estimator,
)
from zoo.plot import plot_online_distances  # noqa: E402
from zoo.study import GOAL_ENV, ORDER_ENV  # noqa: E402


def parse_schedule(text: str) -> dict[int, list[str]]:
    """``"0:2,3,1;400:1,2"`` -> ``{0: ["2,3,1"], 400: ["1,2"]}`` (several entries may share a step)."""
    schedule: dict[int, list[str]] = {}
    for part in filter(None, (p.strip() for p in text.split(";"))):
        step, separator, code = part.partition(":")
        if not separator or not step.strip().isdigit():
            raise argparse.ArgumentTypeError(f"schedule entries look like 'STEP:INSTRUCTION', got {part!r}")
        schedule.setdefault(int(step), []).append(code.strip())
    if not schedule:
        raise argparse.ArgumentTypeError("the schedule is empty")
    return schedule


#: Columns a new table of several runs (``--append-to``) gets: the run's label and model seed, then the log's columns.
TABLE_COLUMNS = ["inference", "model_seed", *(field.name for field in fields(InstructionLog))]


def read_table(table: Path) -> tuple[list[str], list[dict[str, str]]]:
    """The columns and rows of a table of several runs (:data:`TABLE_COLUMNS` and none if it does not exist).

    An existing table keeps its own columns (``inference``, ``model_seed``, then any of the log's); ``ValueError`` if
    they are not such columns.
    """
    if not table.is_file():
        return TABLE_COLUMNS, []
    with table.open(newline="") as handle:
        reader = csv.DictReader(handle)
        columns = list(reader.fieldnames or [])
        if columns[:2] != TABLE_COLUMNS[:2] or not set(columns) <= set(TABLE_COLUMNS):
            raise ValueError(f"{table} has the columns {columns}: not a table of online_control.py runs (inference, "
                             f"model_seed, then any of {TABLE_COLUMNS[2:]})")
        return columns, list(reader)


def append_run(table: Path, log: list[InstructionLog], label: str, model_seed: int) -> int:
    """Add one run's per-instruction ``log`` (the rows of its ``online_log.csv``) to ``table`` as
    ``inference=label, model_seed=model_seed``.

    Rows of ``table`` with the same label and model seed (an earlier run of the same thing) are replaced, others kept;
    returns the number of rows added.
    """
    columns, rows = read_table(table)
    kept = [row for row in rows if (row["inference"], row["model_seed"]) != (label, str(model_seed))]
    added = [{"inference": label, "model_seed": str(model_seed), **asdict(entry)} for entry in log]
    merged = [{column: row[column] for column in columns} for row in kept + added]
    if merged:
        write_csv_rows(merged, table)
    return len(added)


def main(argv: list[str] | None = None) -> None:
    """Parse arguments, run the controller for ``--steps`` steps, write ``online_log.csv`` and
    ``online_distances.png``."""
    parser = OneLineParser(
        prog="online_control.py", description=__doc__.splitlines()[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        epilog='Example: python zoo/online_control.py --pretrained sac --schedule "0:2,3,1;10:1,2" --steps 600',
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--model", type=Path,
                        help="a saved model: a weights-only file (vafn_sb3.save_weights), or any SB3 .zip (SAC, "
                             "MTSAC, MAML-SAC, MAAC, ...) with --trust-remote-code")
    source.add_argument("--policy", choices=["scripted", "random"], help="a reference policy instead of a model")
    source.add_argument("--pretrained", help="a packaged policy by algorithm (e.g. sac): no training needed")
    parser.add_argument("--algo", default=None,
                        help="algorithm of --model when it cannot be told from the file (None: detected)")
    add_trust_flag(parser)
    arrivals = parser.add_mutually_exclusive_group(required=True)
    arrivals.add_argument("--schedule", type=parse_schedule, help="scripted arrivals 'STEP:INSTR;STEP:INSTR'")
    arrivals.add_argument("--poisson-rate", type=float, help="random arrivals per step, instructions from --split")
    parser.add_argument("--steps", type=int, default=2000, help="control steps to run")
    parser.add_argument(
        "--targets", default="default", choices=list(TARGET_MODES), help="where waypoint targets come from"
    )
    parser.add_argument("--split", default="test", choices=["train", "validation", "test"],
                        help="task split the Poisson arrivals sample from")
    parser.add_argument("--max-length", type=int, default=3, help="longest sampled instruction")
    parser.add_argument("--k", type=int,
                        help="adaptation rounds per instruction (None: the model's inner_steps, 0 without adapt)")
    parser.add_argument("--infer-targets", choices=list(INFERENCE_MODES), default=None,
                        help="run a model trained with observed targets (observe_goal=True) on the stream's hidden "
                             "targets through TargetInferencePolicy with this inference setting")
    parser.add_argument("--target-estimator", type=Path, default=None,
                        help="estimator file for --infer-targets learned or gradient (benchmarks/target_estimator.py, "
                             "its --estimator regression or gradient; None: the packaged estimator)")
    parser.add_argument("--refine-steps", type=int, default=None,
                        help="--infer-targets gradient: steps per later reading that refine the estimate (0: estimate "
                             f"once; None: the solver's, {REFINE_STEPS})")
    parser.add_argument("--refine-solver", choices=list(REFINE_SOLVERS), default=REFINE_SOLVER,
                        help="--infer-targets gradient: how the refinement steps: Gauss-Newton or plain gradient steps")
    parser.add_argument("--n-support", type=int, default=25, help="support transitions per instruction (twin env)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the arrivals, support rollouts and env")
    parser.add_argument("--out", type=Path, default=Path("runs/online"),
                        help="folder for online_log.csv and online_distances.png")
    parser.add_argument("--append-to", type=Path, default=None,
                        help="also add this run's rows to this CSV of several runs, with the columns inference "
                             "(--label) and model_seed first; rows of an earlier run with the same label and seed "
                             "are replaced")
    parser.add_argument("--label", default=None,
                        help="--append-to: the run's label (None: --infer-targets, --policy or --pretrained)")
    parser.add_argument("--model-seed", type=int, default=None,
                        help="--append-to: the model's training seed (None: from a '..._seedN.zip' --model name, "
                             "the packaged policy's training seed, 0 for --policy)")
    args = parser.parse_args(argv)
    # with --infer-targets: the packaged policy trained where the targets are observed
    pretrained_env = GOAL_ENV if args.infer_targets else ORDER_ENV
    if args.append_to is not None:
        args.label = args.label or args.infer_targets or args.policy or args.pretrained
        try:
            if args.model_seed is None:
                if args.model is not None:
                    args.model_seed = training_seed(args.model)
                elif args.pretrained is not None:
                    args.model_seed = pretrained_info(args.pretrained, pretrained_env)["training_seed"]
                else:
                    args.model_seed = 0  # a reference policy
            read_table(args.append_to)  # before the run, not after it
        except ValueError as error:
            parser.fail(error)
        for name, value in (("--label", args.label), ("--model-seed", args.model_seed)):
            if value is None:
                parser.fail(f"--append-to needs {name} (it cannot be told from the other arguments)")
    torch.set_num_threads(1)
    if args.steps < 1:
        parser.error(f"--steps must be >= 1, got {args.steps}")
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        env = gym.make(
            "VAFN/ThreeArmStream-v1", arrivals=None, auto_dequeue=False, horizon=args.steps, targets=args.targets,
            split=args.split, max_length=args.max_length,
        )
        stream = env.unwrapped
        if args.schedule is not None:  # every instruction checked against the env's arms before the run starts
            stream.arrival_process = ScheduledArrivals(args.schedule, n_arms=stream.n_arms)
        else:
            stream.arrival_process = PoissonArrivals(args.poisson_rate, sampler=stream.sampler.sample, seed=args.seed)
    except OSError as error:
        parser.fail(f"--out {args.out}: {error.strerror or error}")
    except ValueError as error:
        parser.fail(error)
    trained: tuple[str | None, dict] = (None, {})
    if args.pretrained is not None:
        trained = (pretrained_env, {})
        try:
            model = load_pretrained(args.pretrained, env_id=trained[0])
        except ValueError as error:
            parser.fail(error)
    elif args.model is not None:
        try:
            model, algo = load_model(args.model, args.algo, trust_remote_code=args.trust_remote_code)
            trained = training_env(args.model)
        except (ValueError, OSError) as error:
            parser.fail(error)
        print(f"loaded {args.model} as {type(model).__name__} ({algo})")
    elif args.policy == "scripted":
        model = ScriptedController.for_env(env)
    else:
        model = RandomPolicy(env.action_space, args.seed)
    if args.target_estimator is not None and args.infer_targets not in ESTIMATOR_MODES:
        parser.fail("--target-estimator needs --infer-targets learned or gradient")
    if args.infer_targets is not None:
        if args.policy is not None:
            parser.fail("--infer-targets needs --model or --pretrained")
        try:
            estimator = None if args.target_estimator is None else load_estimator(args.infer_targets,
                                                                                   args.target_estimator)
            # gradient: the estimator's own step count, refined at every later reading
            model = inference_policy_for_env(model, env, args.infer_targets, estimator,
                                             refine_steps=args.refine_steps, refine_solver=args.refine_solver)
        except ValueError as error:
            parser.fail(error)
    if args.policy is None:
        expected = env.observation_space.shape
        if getattr(model, "observation_space", None) is not None and model.observation_space.shape != expected:
            parser.fail(f"the model observes {model.observation_space.shape}, the stream env gives {expected}: it "
                        "was trained on another task family")
        observed = {"targets": args.targets, "observe_goal": args.infer_targets is not None}
        for difference in family_mismatch(*trained, "VAFN/ThreeArmStream-v1", observed):
            warnings.warn(f"the model was trained on {trained[0]} and runs on VAFN/ThreeArmStream-v1 with another "
                          f"task family ({difference}); expect it to miss targets", stacklevel=1)
    if args.model is not None and trained[0] is None:
        warnings.warn(f"no training config beside {args.model} (zoo config.yml or .json): cannot check that it was "
                      "trained on this task family", stacklevel=1)
    controller = OnlineController(model, env, k=args.k, n_support=args.n_support, seed=args.seed)
    controller.run(args.steps)
    controller.close()
    csv_path = controller.write_csv(args.out / "online_log.csv")
    png_path = plot_online_distances(controller, args.out / "online_distances.png")

    log = controller.log
    finished = [entry for entry in log if entry.outcome in ("completed", "timeout")]
    latencies = np.array([entry.service_latency_s for entry in log if np.isfinite(entry.service_latency_s)])
    print(f"{len(log)} instructions started, {len(finished)} finished, "
          f"{sum(entry.success for entry in finished)} succeeded, {len(controller.errors)} rejected")
    cpu = np.array([entry.service_cpu_s for entry in log if np.isfinite(entry.service_cpu_s)])
    if len(latencies):
        print(f"dequeue -> first action: median {1e3 * np.median(latencies):.1f} ms, "
              f"p95 {1e3 * np.percentile(latencies, 95):.1f} ms, max {1e3 * latencies.max():.1f} ms (K={controller.k}, "
              f"support {controller.n_support})")
        print(f"dequeue -> first action, controller-thread CPU time: median {1e3 * np.median(cpu):.1f} ms, "
              f"p95 {1e3 * np.percentile(cpu, 95):.1f} ms, max {1e3 * cpu.max():.1f} ms")
    for error in controller.errors:
        print("error:", error)
    print(f"wrote {csv_path} and {png_path}")
    if args.append_to is not None:
        added = append_run(args.append_to, log, args.label, args.model_seed)
        print(f"added {added} rows to {args.append_to} as inference={args.label}, model_seed={args.model_seed}")


if __name__ == "__main__":
    main()
