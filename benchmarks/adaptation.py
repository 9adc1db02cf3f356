"""Adaptation study: trained models of several methods adapt to the same held-out tasks with the same support budget.

Every method is a set of saved models, one per training seed (``benchmarks/learning.py --save DIR`` writes
``DIR/<algo>_seed<N>.zip``). For every model, every held-out test instruction of ``InstructionBenchmark`` (lengths
``--min-length``..``--max-length``, its fixed seed: the same tasks for every method) and every K in ``--k``, the model
collects ``--n-support`` transitions of the task with its stochastic policy (the same env seeds for every method and
K), takes K adaptation steps (``model.adapt``: MAML-SAC's inner rounds, the others' own gradient steps on the support
set: :func:`vafn_sb3.common.adaptation.evaluate_adaptation`) and runs the adapted policy deterministically. A support
set holds episodes of the task itself (``--support episodes``), where a policy that does not complete a waypoint never
shows the arms after it, or one single-waypoint instruction per arm of the task, the budget split between them
(``--support per-arm``). Methods
that adapt inside the episode (a history of readings, ``--method ... '{"history": 4}'``) and methods evaluated
zero-shot run at K = 0 only (``zero-shot`` as the fifth field). ``infer-probe`` runs a model trained with observed
targets through :class:`vafn_sb3.inference.TargetInferencePolicy` (probe moves, then trilateration inside the
episode; ``infer-passive``: without the probe moves; ``infer-learned``: probe moves, then the network of
``--target-estimator`` (default: the packaged one) instead of trilateration; ``infer-none``: the centre of the shared
region as every goal), also at K = 0 only. ``infer-gradient`` makes the probe moves, then infers each target by K
gradient steps of the ``--gradient-estimator`` (default: the packaged meta-learned one) on the waypoint's first
readings (:class:`vafn_sb3.GradientInferencePolicy`), refined by ``--refine-steps`` steps of ``--refine-solver`` at
every later reading: it runs at every K and collects no support set, its adaptation data are the waypoint's readings
inside the episode.
The scripted controller (the ceiling) and a uniform random policy (the floor) run on the same tasks.

``--dynamics test`` runs every task under every held-out dynamics variant of ``vafn_gym.dynamics.DYNAMICS_VARIANTS``
(the support set is collected under the variant too; a ``variant`` column names it, and
``adaptation_by_variant.csv`` gives each variant's rates): the study of adapting to a changed robot rather than to a
hidden target (docs/results.md, "Adapting to changed dynamics").

Writes to ``--out``: ``adaptation.csv`` (one row per method, seed, task and K), ``adaptation_summary.csv`` (per method
and K: mean over seeds of the per-seed task means, with a 95 % Student-t half width over seeds),
``adaptation_by_length.csv`` (the same per instruction length, with the share of the task's arms the support sets show
executing: ``support_arms``), ``adaptation.png`` and ``adaptation.json`` (the command, support budget in env steps and
in episodes, wall times); ``--replot`` redraws the figure and the length table from them. Never asserts a number.

Usage::

    python benchmarks/learning.py --algo maml_sac --env VAFN/ThreeArmReachHidden-v1 --save runs/hidden ...
    python benchmarks/adaptation.py --env VAFN/ThreeArmReachHidden-v1 --max-length 4 --n-tasks 30 \\
        --method maml_sac maml_sac 'runs/hidden/maml_sac_seed*.zip' \\
        --method mtsac mtsac 'runs/hidden/mtsac_seed*.zip' \\
        --method sac_history4 sac 'runs/hidden_h4/sac_seed*.zip' '{"history": 4}' zero-shot \\
        --out results/adaptation/hidden
"""

from __future__ import annotations

import argparse
import csv
import glob
import json
import shlex
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

import vafn_gym  # noqa: E402,F401  (registers the env IDs)
from vafn_gym import InstructionBenchmark, RandomPolicy, ScriptedController  # noqa: E402
from vafn_gym.dynamics import DYNAMICS_VARIANTS, DYNAMICS_VERSION, NOMINAL  # noqa: E402
from vafn_gym.files import write_csv_rows  # noqa: E402
from vafn_gym.instructions import Instruction  # noqa: E402
from vafn_sb3.common.adaptation import SUPPORT_MODES, evaluate_adaptation, per_arm_tasks  # noqa: E402
from vafn_sb3.common.adaptation_curves import (  # noqa: E402
    ADAPTATION_METRICS,
    AdaptationCurve,
    aggregate_adaptation,
    plot_adaptation,
)
from vafn_sb3.inference import (  # noqa: E402
    INFERENCE_MODES,
    REFINE_SOLVER,
    REFINE_SOLVERS,
    REFINE_STEPS,
    inference_policy_for_env,
    load_estimator,
)
from vafn_sb3.inference.dynamics import DynamicsCompensation  # noqa: E402
from vafn_sb3.loading import add_trust_flag, load_model, load_model_or_exit, training_seed  # noqa: E402
from zoo.jobs import short_commit  # noqa: E402
from zoo.registry import register_algorithms  # noqa: E402
from zoo.study import support_budget  # noqa: E402

DEFAULT_K = [0, 1, 2, 5, 10, 20, 50]
METRICS = tuple(ADAPTATION_METRICS)
#: How a method may be evaluated instead of by its own adaptation: as it is (K = 0), a goal-observing model run through
#: TargetInferencePolicy with one of its inference settings ("infer-<setting>"), or a nominal model whose commands are
#: turned back by the response identified on the support set ("identify", every K: the fit takes no gradient steps) or
#: on the episode's own last steps ("identify-online", K = 0).
COMPENSATION_MODES = {"identify": False, "identify-online": True}
MODES = ("zero-shot", *(f"infer-{inference}" for inference in INFERENCE_MODES), *COMPENSATION_MODES)
#: Inference settings that read an estimator file, and the flag (its ``args`` attribute) that names the file.
ESTIMATOR_FLAGS = {"learned": "target_estimator", "gradient": "gradient_estimator"}
#: The reference policies every study includes (K = 0, no training).
REFERENCES = ("scripted", "random")


@dataclass
class Method:
    """One method of the study: a label, the algorithm that loads its models, the models, and how it is evaluated."""

    label: str
    algo: str
    paths: list[Path]
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    zero_shot: bool = False
    #: None, or the inference setting of TargetInferencePolicy that runs this goal-observing model.
    target_inference: str | None = None
    #: None, or the COMPENSATION_MODES entry that wraps the model in a DynamicsCompensation.
    compensation: str | None = None

    @classmethod
    def parse(cls, fields: list[str]) -> Method:
        """``LABEL ALGO GLOB [ENV_KWARGS_JSON] [MODE]`` from the command line (``ValueError`` if malformed)."""
        if not 3 <= len(fields) <= 5:
            raise ValueError(f"--method takes LABEL ALGO GLOB [ENV_KWARGS_JSON] [{'|'.join(MODES)}], got {fields}")
        label, algo, pattern, *rest = fields
        modes = [item for item in rest if item in MODES]
        rest = [item for item in rest if item not in MODES]
        if len(modes) > 1 or len(rest) > 1:
            raise ValueError(f"{label}: at most one ENV_KWARGS_JSON and one of {MODES}, got {fields[3:]}")
        mode = modes[0] if modes else None
        env_kwargs = json.loads(rest[0]) if rest else {}
        if not isinstance(env_kwargs, dict):
            raise ValueError(f"{label}: ENV_KWARGS must be a JSON object, got {rest[0]!r}")
        paths = sorted(Path(p) for p in glob.glob(pattern))
        if not paths:
            raise ValueError(f"{label}: no model matches {pattern!r}")
        # infer-gradient and identify adapt over K; every other mode is evaluated at K = 0 only
        inference = mode.removeprefix("infer-") if mode is not None and mode.startswith("infer-") else None
        return cls(label, algo, paths, env_kwargs, zero_shot=mode not in (None, "infer-gradient", "identify"),
                   target_inference=inference, compensation=mode if mode in COMPENSATION_MODES else None)


def seed_of(path: Path) -> int:
    """The training seed in a ``<algo>_seed<N>.zip`` file name (0 when the name carries none)."""
    seed = training_seed(path)
    return 0 if seed is None else seed


def earlier_seed_models(methods: list[Method], previous: list[dict[str, Any]]) -> dict[str, list[str]]:
    """For ``--add-seeds``: each method's earlier models whose seeds it does not evaluate again.

    A method must be evaluated as before (same algorithm, env kwargs and mode), or its seeds would not be comparable.
    """
    earlier_models = {}
    for method in methods:
        record = next((m for m in previous if m["label"] == method.label), None)
        if record is None:
            continue
        now = {"algo": method.algo, "env_kwargs": method.env_kwargs, "zero_shot": method.zero_shot,
               "target_inference": method.target_inference, "compensation": method.compensation}
        before = {key: record.get(key, default) for key, default in
                  (("algo", None), ("env_kwargs", {}), ("zero_shot", False), ("target_inference", None),
                   ("compensation", None))}
        if now != before:
            raise SystemExit(f"--add-seeds: {method.label} was evaluated with {before}, now with {now}")
        seeds = {seed_of(path) for path in method.paths}
        earlier_models[method.label] = [model for model in record["models"] if seed_of(Path(model)) not in seeds]
    return earlier_models


def estimator_of(method: Method, args: argparse.Namespace) -> Any:
    """The estimator a target-inference method reads (from its flag's file, or the packaged one), or None."""
    if method.target_inference not in ESTIMATOR_FLAGS:
        return None
    return load_estimator(method.target_inference, getattr(args, ESTIMATOR_FLAGS[method.target_inference]))


def variant_settings(args: argparse.Namespace) -> list[tuple[str, dict[str, Any]]]:
    """``(variant label, env kwargs)`` of every dynamics setting the study runs: the env's own (``--dynamics none``) or
    each held-out variant."""
    if args.dynamics == "none":
        return [("", {})]
    return [(variant.label, {"dynamics": variant.as_dict()}) for variant in DYNAMICS_VARIANTS[args.dynamics]]


def adaptation_rows(policy: Any, args: argparse.Namespace, tasks: list, env_kwargs: dict[str, Any],
                    k_values: list[int], support: str = "episodes") -> list[dict]:
    """:func:`evaluate_adaptation` rows of ``policy`` on ``tasks`` under every setting of :func:`variant_settings`."""
    rows = []
    for label, dynamics in variant_settings(args):
        variant_rows = evaluate_adaptation(policy, args.env, tasks, n_support=args.n_support, k_values=k_values,
                                           n_eval_episodes=args.n_eval_episodes, seed=args.seed,
                                           env_kwargs={**env_kwargs, **dynamics}, support=support)
        rows += [{**row, "variant": label} if label else row for row in variant_rows]
    return rows


def evaluate_model(method: Method, path: Path, args: argparse.Namespace, tasks: list) -> list[dict]:
    """Adaptation rows of one saved model of ``method`` (K = 0 only when the method is zero-shot)."""
    torch.set_num_threads(1)
    register_algorithms()
    model, _ = load_model(path, method.algo, trust_remote_code=args.trust_remote_code)  # SB3 zips: trusted only
    env_kwargs = {**args.env_kwargs, **method.env_kwargs}
    if method.target_inference is not None:
        estimator = estimator_of(method, args)
        env = gym.make(args.env, **env_kwargs)
        # K = 0 is the unadapted policy; evaluate_adaptation's adapt(k=K) sets the gradient steps
        model = inference_policy_for_env(model, env, method.target_inference, estimator, steps=0,
                                         refine_steps=args.refine_steps, refine_solver=args.refine_solver)
        env.close()
    if method.compensation is not None:
        env = gym.make(args.env, **env_kwargs)
        model = DynamicsCompensation(model, env.unwrapped.n_arms, online=COMPENSATION_MODES[method.compensation])
        env.close()
    rows = adaptation_rows(model, args, tasks, env_kwargs, [0] if method.zero_shot else args.k, args.support)
    return [{"method": method.label, "seed": seed_of(path), **row} for row in rows]


def evaluate_methods(methods: list[Method], args: argparse.Namespace, tasks: list) -> list[dict]:
    """Rows of every model of every method, ``--workers`` models at a time (each in a single-threaded child)."""
    jobs = [(method, path) for method in methods for path in method.paths]
    if args.workers == 1:
        return [row for method, path in tqdm(jobs, desc="models") for row in evaluate_model(method, path, args, tasks)]
    results: dict[int, list[dict]] = {}
    with ProcessPoolExecutor(max_workers=args.workers, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(evaluate_model, method, path, args, tasks): index
                   for index, (method, path) in enumerate(jobs)}
        for future in tqdm(as_completed(futures), total=len(futures), desc="models"):
            results[futures[future]] = future.result()
    return [row for index in range(len(jobs)) for row in results[index]]


def evaluate_references(args: argparse.Namespace, tasks: list) -> list[dict]:
    """K = 0 rows of the scripted controller and of the random policy on the same tasks."""
    env = gym.make(args.env, **args.env_kwargs)
    policies = {"scripted": ScriptedController.for_env(env), "random": RandomPolicy(env.action_space, args.seed)}
    env.close()
    rows = []
    for label, policy in policies.items():
        rows += [{"method": label, "seed": 0, **row}
                 for row in adaptation_rows(policy, args, tasks, args.env_kwargs, [0])]
    return rows


def read_rows(path: Path) -> list[dict]:
    """Rows of an earlier ``adaptation.csv`` (numbers parsed; an empty cell, a column older rows lack, is NaN)."""
    integers = ("seed", "task_index", "k", "n_support")

    def parse(key: str, value: str) -> Any:
        if key in ("method", "task", "variant"):
            return value
        return int(value) if key in integers else float(value or "nan")

    with path.open(newline="") as handle:
        return [{key: parse(key, value) for key, value in row.items()} for row in csv.DictReader(handle)]


def summary_rows(curves: dict[str, dict[str, AdaptationCurve]]) -> list[dict]:
    """``adaptation_summary.csv`` rows: per method and K, each metric's mean over seeds and its 95 % t half width."""
    summary = []
    for method, first in curves[METRICS[0]].items():
        for index, k in enumerate(first.k):
            entry: dict[str, Any] = {"method": method, "k": int(k), "n_seeds": first.n_seeds, "n_tasks": first.n_tasks}
            for metric in METRICS:
                curve = curves[metric][method]
                entry[metric] = float(curve.mean[index])
                entry[f"{metric}_ci95"] = float(curve.half_width[index])
            summary.append(entry)
    return summary


def by_variant_rows(rows: list[dict]) -> list[dict]:
    """``adaptation_by_variant.csv`` rows: per method, dynamics variant and K, each rate's mean over seeds with its
    95 % t half width."""
    curves = aggregate_adaptation([{**row, "cell": (row["method"], row["variant"])} for row in rows], group="cell")
    table = []
    for (method, variant), first in curves["success_rate"].items():
        for index, k in enumerate(first.k):
            entry: dict[str, Any] = {"method": method, "variant": variant, "k": int(k), "n_seeds": first.n_seeds}
            for metric in ("success_rate", "collision_rate"):
                entry[metric] = float(curves[metric][method, variant].mean[index])
                entry[f"{metric}_ci95"] = float(curves[metric][method, variant].half_width[index])
            table.append(entry)
    return table


def by_length_rows(rows: list[dict]) -> list[dict]:
    """``adaptation_by_length.csv`` rows: per method, K and instruction length, each rate's mean over seeds with its
    95 % t half width, and the mean share of the task's arms its support sets show executing (NaN at K = 0)."""
    cells = [{**row, "cell": (row["method"], len(Instruction.parse(row["task"])))} for row in rows]
    curves = aggregate_adaptation(cells, group="cell")
    table = []
    for (method, length), first in curves["success_rate"].items():
        for index, k in enumerate(first.k):
            coverage = [row.get("support_arms", np.nan) for row in cells
                        if row["cell"] == (method, length) and row["k"] == k]
            entry: dict[str, Any] = {"method": method, "length": length, "k": int(k), "n_seeds": first.n_seeds,
                                     "n_tasks": first.n_tasks}
            for metric in ("success_rate", "collision_rate"):
                entry[metric] = float(curves[metric][method, length].mean[index])
                entry[f"{metric}_ci95"] = float(curves[metric][method, length].half_width[index])
            entry["support_arms"] = float(np.mean(coverage)) if not np.isnan(coverage).all() else float("nan")
            table.append(entry)
    return sorted(table, key=lambda entry: (entry["length"], [*curves["success_rate"]].index(
        (entry["method"], entry["length"])), entry["k"]))


def support_episodes(args: argparse.Namespace, tasks: list) -> float:
    """Mean number of episodes (started) in a support set of ``--n-support`` steps, with the tasks' step budgets (with
    ``--support per-arm``, summed over the task's single-waypoint instructions, each with its share of the steps)."""
    env = gym.make(args.env, **args.env_kwargs)
    base = env.unwrapped
    episodes = []
    for task in tasks:
        support_tasks = per_arm_tasks(task) if args.support == "per-arm" else [task]
        started = 0.0
        for index, support_task in enumerate(support_tasks):
            share = args.n_support // len(support_tasks) + (index < args.n_support % len(support_tasks))
            base.set_task(support_task)
            env.reset(seed=args.seed)
            started += np.ceil(share / base.max_episode_steps())
        episodes.append(started)
    env.close()
    return float(np.mean(episodes))


def figure_title(meta: dict[str, Any]) -> str:
    """The figure's title from ``adaptation.json``: what the run is, the tasks, the support budget."""
    low, high = meta["test_lengths"]
    prefix = f"{meta['title']}\n" if meta.get("title") else ""
    support = support_budget(meta["n_support_steps"], meta["support_episodes_mean"], max(meta.get("k", [1])),
                             meta.get("support", "episodes"))
    dynamics = meta.get("dynamics")
    variants = f" × {len(dynamics['variants'])} held-out dynamics variants" if dynamics else ""
    return (f"{prefix}{meta['env']}: {meta['n_tasks']} held-out test instructions of lengths {low}-{high}{variants}; "
            f"{support}; mean over seeds ± 95 % CI")


def replot(out: Path, title: str | None = None) -> Path:
    """Redraw ``out/adaptation.png`` from the ``adaptation.csv`` and ``adaptation.json`` already there (``title``:
    a new first line of the figure's title, also stored in ``adaptation.json``)."""
    meta = json.loads((out / "adaptation.json").read_text())
    if title is not None:
        meta["title"] = title
        (out / "adaptation.json").write_text(json.dumps(meta, indent=2))
    rows = read_rows(out / "adaptation.csv")
    write_csv_rows(by_length_rows(rows), out / "adaptation_by_length.csv")
    curves = aggregate_adaptation(rows)
    return plot_adaptation(curves, out / "adaptation.png", figure_title(meta), references=REFERENCES)


def estimator_record(method: Method, args: argparse.Namespace) -> dict[str, str]:
    """``{flag: file}`` of the estimator a target-inference method read (``"packaged"``: the default), else ``{}``."""
    if method.target_inference not in ESTIMATOR_FLAGS:
        return {}
    flag = ESTIMATOR_FLAGS[method.target_inference]
    record = {flag: str(getattr(args, flag) or "packaged")}
    if method.target_inference == "gradient":
        record["refine_steps"] = args.refine_steps
        record["refine_solver"] = args.refine_solver
    return record


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line flags."""
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--env", default="VAFN/ThreeArmReachHidden-v1", help="env ID")
    parser.add_argument("--env-kwargs", type=json.loads, default={}, help="JSON kwargs of every method's env")
    add_trust_flag(parser)
    parser.add_argument("--method", nargs="+", action="append", default=[], metavar="FIELD",
                        help=f"LABEL ALGO GLOB [ENV_KWARGS_JSON] [{'|'.join(MODES)}]; repeat for every method")
    parser.add_argument("--target-estimator", type=Path, default=None,
                        help="LearnedTargetEstimator file of infer-learned methods (benchmarks/target_estimator.py; "
                             "None: the packaged estimator)")
    parser.add_argument("--gradient-estimator", type=Path, default=None,
                        help="GradientTargetEstimator file of infer-gradient methods (benchmarks/target_estimator.py "
                             "--estimator gradient; None: the packaged estimator)")
    parser.add_argument("--refine-steps", type=int, default=None,
                        help="infer-gradient: steps per later reading that refine the estimate (0: estimate once from "
                             f"the first readings; None: the solver's, {REFINE_STEPS})")
    parser.add_argument("--refine-solver", choices=list(REFINE_SOLVERS), default=REFINE_SOLVER,
                        help="infer-gradient: how the refinement steps: Gauss-Newton or plain gradient steps")
    parser.add_argument("--min-length", type=int, default=1, help="shortest test instruction")
    parser.add_argument("--max-length", type=int, default=4, help="longest test instruction")
    parser.add_argument("--n-tasks", type=int, default=30, help="held-out test instructions")
    parser.add_argument("--k", type=int, nargs="+", default=DEFAULT_K, help="adaptation steps to evaluate")
    parser.add_argument("--n-support", type=int, default=400, help="support transitions per adaptation")
    parser.add_argument("--support", choices=SUPPORT_MODES, default="episodes",
                        help="what a support set holds: episodes of the task itself, or one single-waypoint "
                             "instruction per arm of the task (every hidden target shown; the budget split)")
    parser.add_argument("--n-eval-episodes", type=int, default=1,
                        help="deterministic episodes per task and K (the env is deterministic given the task)")
    parser.add_argument("--dynamics", choices=["none", *DYNAMICS_VARIANTS], default="none",
                        help="run every task under every dynamics variant of this split (none: the env's own)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the support rollouts and evaluation episodes")
    parser.add_argument("--append", action="store_true",
                        help="keep the other methods' rows of an earlier run in --out (same tasks and flags)")
    parser.add_argument("--add-seeds", action="store_true",
                        help="with --append: a method already in --out keeps its rows of the seeds these models do "
                             "not have (adding seeds to it); it must be evaluated as before")
    parser.add_argument("--no-references", action="store_true",
                        help="leave out the scripted ceiling and the random floor (rows to merge into a panel later, "
                             "as zoo/reproduce.py's jobs do; with --append the panel's reference rows are kept)")
    parser.add_argument("--workers", type=int, default=1, help="models evaluated in parallel (one thread each)")
    parser.add_argument("--out", type=Path, default=Path("results/adaptation"), help="output folder")
    parser.add_argument("--title", default=None,
                        help="what this run is, put first in the figure's title (with --append or --replot: "
                             "default the earlier run's)")
    parser.add_argument("--replot", action="store_true",
                        help="only redraw --out's adaptation.png and adaptation_by_length.csv from its "
                             "adaptation.csv (no evaluation)")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    """Evaluate every method's models and the references on the same held-out tasks; write CSV, summary, plot."""
    args = parse_args(argv)
    if args.replot:
        print(replot(args.out, args.title))
        return
    torch.set_num_threads(1)
    if args.refine_steps is None:
        args.refine_steps = REFINE_STEPS[args.refine_solver]
    if args.refine_steps < 0:
        raise SystemExit(f"--refine-steps must be >= 0, got {args.refine_steps}")
    methods = [Method.parse(fields) for fields in args.method]
    for method in methods:
        try:  # a bad file fails here, in one line, not in every worker
            estimator_of(method, args)
        except ValueError as error:
            flag = ESTIMATOR_FLAGS[method.target_inference].replace("_", "-")
            raise SystemExit(f"--{flag}: {error}") from None
    for method in methods:  # likewise every model file, before any evaluation runs
        for path in method.paths:
            load_model_or_exit(path, method.algo, f"--method {method.label}: ",
                               trust_remote_code=args.trust_remote_code)
    args.out.mkdir(parents=True, exist_ok=True)
    benchmark = InstructionBenchmark(args.env, args.min_length, args.max_length, n_test=args.n_tasks,
                                     env_kwargs=args.env_kwargs)
    tasks = benchmark.test_tasks
    start = time.perf_counter()
    kept, method_records, title = [], [], args.title or ""
    if args.add_seeds and not args.append:
        raise SystemExit("--add-seeds adds seeds to the methods of an earlier run in --out: it needs --append")
    labels = {method.label for method in methods}
    earlier_models: dict[str, list[str]] = {}
    if args.append and (args.out / "adaptation.json").is_file() and not (args.out / "adaptation.csv").is_file():
        raise SystemExit(f"--append: {args.out} holds an earlier run's adaptation.json but not its per-episode "
                         "adaptation.csv, so its methods cannot be kept; restore the CSV or drop --append")
    if args.append and (args.out / "adaptation.csv").is_file():
        previous_meta = json.loads((args.out / "adaptation.json").read_text())
        evaluated = {(method.label, seed_of(path)) for method in methods for path in method.paths}
        replaced = (set() if args.no_references else set(REFERENCES)) | (set() if args.add_seeds else labels)
        kept = [row for row in read_rows(args.out / "adaptation.csv")
                if row["method"] not in replaced and (row["method"], row["seed"]) not in evaluated]
        earlier = {(row["task"], row["n_support"]) for row in kept}
        earlier_dynamics = (previous_meta.get("dynamics") or {}).get("split", "none")
        if not earlier <= {(task.to_code(), args.n_support) for task in tasks} or (
                previous_meta.get("support", "episodes") != args.support) or earlier_dynamics != args.dynamics:
            raise SystemExit(f"--append: {args.out / 'adaptation.csv'} has other tasks, another --n-support, "
                             "another --support or another --dynamics")
        method_records = [m for m in previous_meta["methods"] if m["label"] not in labels]
        title = previous_meta.get("title", "") if args.title is None else args.title
        if args.add_seeds:
            earlier_models = earlier_seed_models(methods, previous_meta["methods"])
    references = [] if args.no_references else evaluate_references(args, tasks)
    rows = references + kept + evaluate_methods(methods, args, tasks)
    curves = aggregate_adaptation(rows)
    summary = summary_rows(curves)
    write_csv_rows(rows, args.out / "adaptation.csv")
    write_csv_rows(summary, args.out / "adaptation_summary.csv")
    write_csv_rows(by_length_rows(rows), args.out / "adaptation_by_length.csv")
    variant_table = by_variant_rows(rows) if args.dynamics != "none" else []
    if variant_table:
        write_csv_rows(variant_table, args.out / "adaptation_by_variant.csv")
    episodes = support_episodes(args, tasks)
    meta = {"command": shlex.join(sys.argv), "commit": short_commit(), "title": title, "env": args.env,
            "env_kwargs": args.env_kwargs,
            "test_lengths": [args.min_length, args.max_length], "n_tasks": len(tasks), "benchmark_seed": benchmark.seed,
            "dynamics": None if args.dynamics == "none" else {
                "version": DYNAMICS_VERSION, "split": args.dynamics,
                "variants": [v.as_dict() for v in DYNAMICS_VARIANTS[args.dynamics]], "nominal": NOMINAL.as_dict()},
            "n_support_steps": args.n_support, "support": args.support, "support_episodes_mean": episodes, "k": args.k,
            "methods": method_records + [{"label": m.label, "algo": m.algo,
                                          "models": earlier_models.get(m.label, []) + [str(p) for p in m.paths],
                                          "env_kwargs": m.env_kwargs, "zero_shot": m.zero_shot,
                                          "target_inference": m.target_inference, "compensation": m.compensation,
                                          **estimator_record(m, args)} for m in methods],
            "eval_wall_s": round(time.perf_counter() - start, 1), "summary": summary,
            **({"by_variant": variant_table} if variant_table else {})}
    (args.out / "adaptation.json").write_text(json.dumps(meta, indent=2))
    title = figure_title(meta)
    plot_adaptation(curves, args.out / "adaptation.png", title, references=REFERENCES)
    print(title)
    print(f"{'method':>16} {'K':>3} " + " ".join(f"{m:>22}" for m in METRICS))
    for entry in summary:
        print(f"{entry['method']:>16} {entry['k']:>3} "
              + " ".join(f"{entry[m]:>14.3f} ± {entry[m + '_ci95']:.3f}" for m in METRICS))


if __name__ == "__main__":
    main()
