"""Reproduce the paper's results into a fresh folder: Fig. 3 (adaptation), Fig. 4 (online control), Table 1.

    python zoo/reproduce.py --quick      # <= 15 min on 2 cores: 2 seeds, short budgets
    python zoo/reproduce.py --full       # <= 2 h on 2 cores: 5 seeds, 15k steps per algorithm
    python zoo/reproduce.py --smoke --out /tmp/vafn-smoke   # CI: every stage end to end in about a minute

Every run writes to ``runs/reproduce-<mode>-<timestamp>/`` (models and logs; figures and SUMMARY.md in its
``results/``) unless ``--work`` / ``--out`` say otherwise; the committed ``results/`` is only written with
``--overwrite-results``.

1. **Fig. 3**: MAML-SAC, MAAC, MAPPO, MADDPG and MTSAC each train through ``zoo/train.py`` (their
   ``hyperparams/<algo>.yml``) for the *same* number of env steps per seed, then adapt to held-out test instructions
   for K = 0..50 adaptation steps with the same support budget (``evaluate_adaptation``); average return, success
   and collision rate against K, mean ± 95 % CI over seeds. Training curves go to ``training_*.png``.
2. **Fig. 4**: 2,000 steps of ``VAFN/ThreeArmStream-v1`` with five instructions from ``[1,2,3]`` to
   ``[2,3,1,3,2,3]`` arriving at equal intervals; :class:`vafn_sb3.OnlineController` runs the packaged pretrained
   policies (``vafn_sb3.load_pretrained``; MAML-SAC adapts at each boundary) and the scripted controller runs the same
   stream as the ceiling.
3. **Table 1**: ``benchmarks/instruction_table.py`` (multimedia instruction generator).
4. ``SUMMARY.md``: every figure and table beside the paper's claims, with the commit, seeds and wall times.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from vafn_gym.benchmarks import DEFAULT_TEST_SEED  # noqa: E402
from vafn_gym.constants import SUCCESS_TOLERANCE  # noqa: E402
from vafn_sb3.common.adaptation_curves import (  # noqa: E402
    ADAPTATION_METRICS,
    AdaptationCurve,
    aggregate_adaptation,
    plot_adaptation,
)
from zoo.plot import load_tensorboard, make_plots  # noqa: E402

#: The algorithms of Fig. 3, MAML-SAC first (the paper's comparison set).
FIG3_ALGOS = ("maml_sac", "maac", "mappo", "maddpg", "mtsac")
#: Fig. 4's five phases, simple to complex (first and last as in the paper).
FIG4_PHASES = ("1,2,3", "3,1,2", "1,3,2,1", "3,2,1,3,2", "2,3,1,3,2,3")
FIG4_ENV = "VAFN/ThreeArmStream-v1"
#: Seed of the held-out instruction set (the same tasks for every algorithm and seed).
HELD_OUT_SEED = DEFAULT_TEST_SEED
#: Paper claims restated in SUMMARY.md (issue 4 and issue 3 quote them).
PAPER_FIG3 = "MAML-SAC reaches success 1.0 by adaptation step 20 with zero collisions and beats MAAC, MAPPO, MADDPG."
PAPER_FIG4 = "the online controller completes all five phases, each arm within tolerance of its target, no collisions."


@dataclass(frozen=True)
class Mode:
    """Budgets of one reproduction mode."""

    name: str
    seeds: tuple[int, ...]
    timesteps: int
    max_length: int
    n_tasks: int
    k_values: tuple[int, ...]
    n_support: int
    n_eval_episodes: int
    eval_points: int
    fig4_steps: int
    table1_args: tuple[str, ...]
    learning_starts_fraction: float = 0.1
    algos: tuple[str, ...] = FIG3_ALGOS
    env_id: str = "VAFN/ThreeArmReachHidden-v1"


MODES: dict[str, Mode] = {
    "smoke": Mode("smoke", (0,), 200, 1, 1, (0, 1, 2), 20, 1, 1, 200,
                  ("--seeds", "1", "--items", "2", "--in-distribution", "0", "--transfer-items", "0", "--workers", "1"),
                  learning_starts_fraction=0.75),
    "quick": Mode("quick", (0, 1), 3000, 2, 3, (0, 1, 2, 5, 10, 20, 50), 100, 1, 4, 2000,
                  ("--seeds", "1", "--items", "20", "--in-distribution", "0", "--transfer-items", "0")),
    # 15k steps: MAAC (~0.1 CPU-s per update) dominates; scaled from the quick run, ~3.4 CPU-h = ~1.7 h on 2 free cores.
    "full": Mode("full", (0, 1, 2, 3, 4), 15_000, 2, 5, (0, 1, 2, 3, 5, 10, 20, 30, 40, 50), 200, 2, 10, 2000, ()),
}


@dataclass
class Job:
    """One (algorithm, seed) training run followed by its adaptation evaluation."""

    algo: str
    seed: int
    mode: Mode
    work: Path
    rows: list[dict[str, Any]] = field(default_factory=list)
    resume: bool = False
    wall_s: float = 0.0
    cpu_s: float = 0.0
    error: str = ""

    @property
    def log_folder(self) -> Path:
        """Zoo log folder of this job (one per seed, so parallel jobs never race for a run id)."""
        return self.work / "logs" / f"seed{self.seed}"

    @property
    def timing_path(self) -> Path:
        """Where the training wall/CPU time of this job is kept (read back by ``--resume``)."""
        return self.log_folder / self.algo / "train_time.json"

    @property
    def model_path(self) -> Path:
        """The trained model the zoo saves."""
        env_name = self.mode.env_id.replace("/", "-")
        return self.log_folder / self.algo / f"{env_name}_1" / f"{env_name}.zip"


def short_budget_params(algo: str, mode: Mode) -> list[str]:
    """``-params`` overrides that keep each algorithm's schedule meaningful within the mode's step budget."""
    starts = int(mode.timesteps * mode.learning_starts_fraction)
    if algo == "mappo":
        return [f"n_steps:{min(1024, max(mode.timesteps // 6, 64))}", "batch_size:64"]
    params = [f"learning_starts:{starts}"]
    if algo == "maml_sac":
        # One meta-iteration consumes meta_batch_size x (n_support + n_query) steps; keep several in the budget.
        params += [f"warmup_steps:{mode.timesteps // 5}", f"n_support:{mode.n_support}", f"n_query:{mode.n_support}"]
    return params


def train_command(job: Job) -> list[str]:
    """zoo/train.py arguments of a job (equal env-step budget for every algorithm)."""
    mode = job.mode
    return [
        "--algo", job.algo, "--env", mode.env_id, "-n", str(mode.timesteps), "--seed", str(job.seed),
        "-f", str(job.log_folder), "-tb", str(job.work / "tb" / f"seed{job.seed}"),
        "--eval-freq", str(max(mode.timesteps // mode.eval_points, 1)), "--eval-episodes", "3",
        "--verbose", "0",
        "-params", *short_budget_params(job.algo, mode), "--env-kwargs", f"max_length:{mode.max_length}",
    ]


def held_out_tasks(mode: Mode) -> list[Any]:
    """The held-out test instructions every algorithm adapts to."""
    from vafn_gym import InstructionBenchmark

    return InstructionBenchmark(mode.env_id, 1, mode.max_length, n_test=mode.n_tasks, seed=HELD_OUT_SEED).test_tasks


def run_job(job: Job) -> Job:
    """Train one algorithm for one seed with zoo/train.py, then measure its adaptation curve (runs in a child)."""
    import contextlib
    import io

    import torch

    from vafn_sb3.common.adaptation import evaluate_adaptation
    from zoo.registry import register_algorithms, require_algorithm
    from zoo.train import main as train_main

    torch.set_num_threads(1)
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    trained_wall = trained_cpu = 0.0
    try:
        if job.resume and job.model_path.is_file() and job.timing_path.is_file():
            trained_wall, trained_cpu = json.loads(job.timing_path.read_text())
        else:
            with contextlib.redirect_stdout(io.StringIO()):
                train_main(train_command(job))
            job.timing_path.write_text(json.dumps([time.perf_counter() - start_wall, time.process_time() - start_cpu]))
        register_algorithms()
        model = require_algorithm(job.algo).load(job.model_path, device="cpu")
        rows = evaluate_adaptation(
            model, job.mode.env_id, held_out_tasks(job.mode), n_support=job.mode.n_support,
            k_values=job.mode.k_values, n_eval_episodes=job.mode.n_eval_episodes, seed=job.seed,
        )
        job.rows = [{"algo": job.algo, "seed": job.seed, **row} for row in rows]
    except Exception as error:  # noqa: BLE001 - one failed algorithm must not hide the others' results
        job.error = f"{type(error).__name__}: {error}"
    job.wall_s = trained_wall + time.perf_counter() - start_wall
    job.cpu_s = trained_cpu + time.process_time() - start_cpu
    return job


def run_jobs(jobs: list[Job], n_workers: int) -> list[Job]:
    """Run jobs in fresh single-threaded child processes, ``n_workers`` at a time, with a progress bar."""
    done: list[Job] = []
    context = get_context("spawn")
    with ProcessPoolExecutor(max_workers=n_workers, mp_context=context, max_tasks_per_child=1) as pool:
        futures = [pool.submit(run_job, job) for job in jobs]
        for future in tqdm(as_completed(futures), total=len(futures), desc="train + adapt"):
            job = future.result()
            status = f"FAILED: {job.error}" if job.error else f"{job.wall_s:.0f} s"
            tqdm.write(f"{job.algo} seed {job.seed}: {status}")
            done.append(job)
    return sorted(done, key=lambda j: (FIG3_ALGOS.index(j.algo) if j.algo in FIG3_ALGOS else 99, j.seed))


def plot_fig3(aggregates: dict[str, dict[str, AdaptationCurve]], mode: Mode, path: Path) -> Path:
    """Fig. 3: success, collision rate and return against adaptation steps K, one colour per algorithm."""
    seeds = ",".join(map(str, mode.seeds))
    title = (
        f"Fig. 3 ({mode.name}): adaptation on {_plural(mode.n_tasks, 'held-out test instruction')} of {mode.env_id} "
        f"(length {_lengths(mode.max_length)}); {mode.timesteps} training steps per algorithm, "
        f"{'seed' if len(mode.seeds) == 1 else 'seeds'} {seeds}, "
        f"{mode.n_support} support steps; mean ± 95% CI over seeds"
    )
    return plot_adaptation(aggregates, path, title)


def write_rows(rows: list[dict[str, Any]], path: Path) -> Path:
    """Rows of dicts as CSV (columns from the first row)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return path


def fig3_summary_rows(aggregates: dict[str, dict[str, AdaptationCurve]]) -> list[dict[str, Any]]:
    """Long table of the Fig. 3 curves: algo, k, metric, mean, ci_low, ci_high, n_seeds."""
    rows = []
    for metric, per_algo in aggregates.items():
        for algo, agg in per_algo.items():
            for k, mean, low, high in zip(agg.k, agg.mean, agg.low, agg.high):
                rows.append({"algo": algo, "k": int(k), "metric": metric, "mean": round(float(mean), 4),
                             "ci_low": round(float(low), 4), "ci_high": round(float(high), 4), "n_seeds": agg.n_seeds})
    return rows


# --- Fig. 4 ---
def run_stream(policy: Any, mode: Mode, seed: int, k: int) -> dict[str, np.ndarray]:
    """Drive OnlineController over the five-phase stream; per-step distances, active arm and instruction sequence."""
    import gymnasium as gym

    from vafn_sb3 import OnlineController

    spacing = mode.fig4_steps // len(FIG4_PHASES)
    schedule = {index * spacing: code for index, code in enumerate(FIG4_PHASES)}
    env = gym.make(FIG4_ENV, arrivals=schedule, auto_dequeue=False, horizon=mode.fig4_steps)
    controller = OnlineController(policy, env, k=k, n_support=mode.n_support, seed=seed)
    active: list[int] = []
    try:
        for _ in tqdm(range(mode.fig4_steps), desc="Fig. 4 stream", leave=False):
            info = controller.step()
            active.append(0 if info["active_arm"] is None else int(info["active_arm"]))
        log = [asdict(entry) for entry in controller.log]
    finally:
        controller.close()
        env.close()
    # Distances and running sequence come from the controller's own per-step trace.
    sequence = [-1 if s is None else int(s) for s in controller.trace["sequence"]]
    return {"distance": np.array(controller.trace["distances"], float), "active": np.array(active),
            "sequence": np.array(sequence), "boundaries": np.array(sorted(schedule)), "log": log}


def plot_fig4(trace: dict[str, Any], title: str, path: Path) -> Path:
    """Top: each arm's distance to target, tolerance line, phase boundaries; bottom: approaching vs holding."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.arange(len(trace["active"]))
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(12, 6), sharex=True, gridspec_kw={"height_ratios": [3, 1.3]})
    colours = plt.get_cmap("tab10")
    arm_ids = range(1, trace["distance"].shape[1] + 1)
    for column, arm in enumerate(arm_ids):
        top.plot(steps, trace["distance"][:, column], lw=1.0, color=colours(column), label=f"arm {arm}")
    top.axhline(SUCCESS_TOLERANCE, color="k", ls="--", lw=0.8, label=f"tolerance {SUCCESS_TOLERANCE} m")
    for boundary, code in zip(trace["boundaries"], FIG4_PHASES):
        for ax in (top, bottom):
            ax.axvline(boundary, color="grey", lw=0.8, ls=":")
        top.text(boundary + 5, top.get_ylim()[1] * 0.95, f"[{code}]", fontsize=8, va="top")
    top.set_ylabel("distance to target (m)")
    top.set_yscale("log")
    top.legend(fontsize=8, loc="upper right")
    top.set_title(title, fontsize=10)
    for row, arm in enumerate(arm_ids):
        approaching = trace["active"] == arm
        spans = _runs(approaching)
        bottom.broken_barh([(s, e - s) for s, e in _runs(~approaching)], (row - 0.35, 0.7), color="lightgrey")
        bottom.broken_barh([(s, e - s) for s, e in spans], (row - 0.35, 0.7), color=colours(row))
    bottom.set_yticks(range(len(arm_ids)), [f"arm {arm}" for arm in arm_ids])
    bottom.set_xlabel("stream step (colour: approaching its target; grey: returning / holding)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index ranges where ``mask`` is True."""
    padded = np.concatenate([[False], mask, [False]]).astype(int)
    edges = np.flatnonzero(np.diff(padded))
    return list(zip(edges[::2], edges[1::2]))


def fig4(mode: Mode, out: Path) -> dict[str, Any]:
    """Fig. 4 for every packaged pretrained policy of the stream's world and for the scripted ceiling."""
    import gymnasium as gym

    from vafn_gym import ScriptedController
    from vafn_sb3 import available_pretrained, load_pretrained

    probe = gym.make(FIG4_ENV)
    runs: list[tuple[str, Any, int]] = [("scripted", ScriptedController.for_env(probe), 0)]
    probe.close()
    for algo, env_id in available_pretrained():
        if env_id == "VAFN/ThreeArmReach-v1":  # the stream's world: default targets, inactive arms held
            model = load_pretrained(algo, env_id)
            runs.insert(0, (algo, model, int(getattr(model, "inner_steps", 0))))
    outcomes = {}
    for name, policy, k in runs:
        trace = run_stream(policy, mode, seed=0, k=k)
        title = (f"Fig. 4 ({mode.name}): {name} on {FIG4_ENV}, {mode.fig4_steps} steps, five phases"
                 + (f", adapted with K={k} at each boundary" if k else ""))
        plot_fig4(trace, title, out / f"fig4_online_{name}.png")
        if trace["log"]:
            write_rows(trace["log"], out / f"fig4_online_{name}.csv")
        outcomes[name] = trace["log"]
    return outcomes


# --- Table 1 ---
def table1(mode: Mode, out: Path) -> dict[str, Any]:
    """Run the multimedia benchmark (Table 1); returns its status and output stem."""
    script = REPO_ROOT / "benchmarks" / "instruction_table.py"
    stem = out / ("instruction_table" if mode.name == "full" else f"table1_{mode.name}")
    if not script.is_file():
        return {"ok": False, "stem": stem, "message": f"{script} not found (multimedia issue not landed)"}
    command = [sys.executable, str(script.relative_to(REPO_ROOT)), *mode.table1_args, "--out", _relative(stem)]
    result = subprocess.run(command, cwd=REPO_ROOT, capture_output=True, text=True,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    message = (result.stdout + result.stderr)[-3000:]
    return {"ok": result.returncode == 0, "stem": stem, "message": message, "command": " ".join(command[1:])}


def _relative(path: Path) -> str:
    """``path`` relative to the repository when it lies inside it (for commands quoted in SUMMARY.md)."""
    try:
        return str(Path(path).resolve().relative_to(REPO_ROOT))
    except ValueError:
        return str(path)


# --- SUMMARY.md ---
def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, check=True).stdout.strip()
    except (subprocess.CalledProcessError, FileNotFoundError):
        return "unknown"


def _plural(count: int, word: str) -> str:
    """``1 task``, ``3 tasks``."""
    return f"{count} {word}{'' if count == 1 else 's'}"


def _lengths(max_length: int) -> str:
    """``1`` or ``1-3``: the instruction lengths of a mode."""
    return "1" if max_length == 1 else f"1-{max_length}"


def _at_k(aggregates: dict[str, dict[str, AdaptationCurve]], metric: str, algo: str, k: int) -> str:
    agg = aggregates[metric].get(algo)
    if agg is None or k not in agg.k:
        return "n/a"
    i = int(np.flatnonzero(agg.k == k)[0])
    return f"{agg.mean[i]:.2f} [{agg.low[i]:.2f}, {agg.high[i]:.2f}]" if agg.n_seeds > 1 else f"{agg.mean[i]:.2f}"


def write_summary(mode: Mode, jobs: list[Job], aggregates: dict[str, dict[str, AdaptationCurve]],
                  fig4_log: dict[str, Any], table: dict[str, Any], times: dict[str, float], out: Path) -> Path:
    """results/SUMMARY.md: each result beside the paper's claim, with commit, seeds, wall times and honest gaps."""
    changed = _git("status", "--porcelain", "--", "zoo", "vafn_sb3", "vafn_gym")
    dirty = " (working tree had uncommitted changes)" if changed else ""
    k_max = max(mode.k_values)
    k_mid = 20 if 20 in mode.k_values else k_max
    lines = [
        f"# Reproduction summary ({mode.name} mode)", "",
        f"Command: `python zoo/reproduce.py --{mode.name}` · commit `{_git('rev-parse', '--short', 'HEAD')}`{dirty} · "
        f"{'seed' if len(mode.seeds) == 1 else 'seeds'} {list(mode.seeds)} · "
        + ("**resumed** (`--resume`): the models were trained by an earlier run of the same mode; per-job times below "
           "include their recorded training time, the wall times in this line cover only this run · "
           if times["resumed"] else "")
        + f"total wall time {times['total']/60:.1f} min on {os.cpu_count()} cores "
        f"(train + adapt {times['fig3']/60:.1f} min, Fig. 4 {times['fig4']/60:.1f} min, "
        f"Table 1 {times['table1']/60:.1f} min); "
        f"the training and adaptation jobs used {sum(j.cpu_s for j in jobs)/60:.1f} CPU-min in total "
        "(1-min load average "
        f"at start: {times['load']:.1f}; other users' jobs share the cores, so wall time overstates the cost).",
        "",
        "## Fig. 3: adaptation on held-out instructions (`fig3_adaptation.png`, `fig3_adaptation.csv`)", "",
        f"Paper: {PAPER_FIG3}", "",
        f"Ours: {mode.env_id}, instructions of length {_lengths(mode.max_length)} from the *test* split "
        f"({_plural(mode.n_tasks, 'task')}), "
        f"{mode.timesteps} training steps per algorithm and seed (equal budgets), {mode.n_support} support steps, "
        f"mean [95% CI] over {_plural(len(mode.seeds), 'seed')} {list(mode.seeds)}.", "",
    ]
    # One column per distinct (metric, K): with K in (0, 1, 2) the "K=20" column would repeat K=2's header.
    columns = [("success_rate", k) for k in dict.fromkeys((0, k_mid, k_max))]
    columns += [("collision_rate", k_max), ("return_mean", 0), ("return_mean", k_max)]
    names = {"success_rate": "success", "collision_rate": "collision", "return_mean": "return"}
    lines += ["| algorithm | " + " | ".join(f"{names[m]} K={k}" for m, k in columns) + " | train wall (s) |",
              "|---" * (len(columns) + 2) + "|"]
    for algo in mode.algos:
        algo_jobs = [j for j in jobs if j.algo == algo]
        wall = np.mean([j.wall_s for j in algo_jobs]) if algo_jobs else float("nan")
        failed = [f"seed {j.seed}: {j.error}" for j in algo_jobs if j.error]
        if failed:
            lines.append(f"| {algo} | FAILED: {'; '.join(failed)} |" + " |" * (len(columns) - 1) + f" {wall:.0f} |")
            continue
        cells = " | ".join(_at_k(aggregates, m, algo, k) for m, k in columns)
        lines.append(f"| {algo} | {cells} | {wall:.0f} |")
    success = aggregates["success_rate"]
    best = max((success[a].mean.max(), a) for a in success) if success else (0.0, "none")
    lines += ["", _fig3_verdict(best, aggregates, mode), ""]
    lines += ["## Fig. 4: long-horizon online control with the pretrained policies (`fig4_online_<policy>.png`)", "",
              f"Paper: {PAPER_FIG4}", "",
              f"Ours: {mode.fig4_steps} steps of {FIG4_ENV}, phases "
              f"{', '.join(f'[{p}]' for p in FIG4_PHASES)} arriving every "
              f"{mode.fig4_steps // len(FIG4_PHASES)} steps.", "",
              "| policy | instructions started | succeeded | collisions | outcomes |", "|---|---|---|---|---|"]
    for name, log in fig4_log.items():
        if isinstance(log, str):
            lines.append(f"| {name} | FAILED: {log} | | | |")
            continue
        succeeded = sum(bool(e["success"]) for e in log)
        collisions = sum(int(e["collisions"]) for e in log)
        outcomes = ", ".join(f"[{e['instruction']}] {e['outcome']}" for e in log)
        lines.append(f"| {name} | {len(log)} | {succeeded} | {collisions} | {outcomes} |")
    short = [name for name, log in fig4_log.items() if name != "scripted"
             and (isinstance(log, str) or sum(bool(e["success"]) for e in log) < len(FIG4_PHASES))]
    if short:
        lines += ["", f"We fall short with {', '.join(short)}: not all five phases completed without contact; "
                  "the scripted row shows the stream itself is solvable."]
    lines += ["", "## Table 1: multimedia instruction generator", ""]
    if table["ok"]:
        md = Path(str(table["stem"]) + ".md")
        lines += [f"Command: `python {table['command']}` (paper numbers printed beside ours by the benchmark).", ""]
        lines += [md.read_text().strip() if md.is_file() else f"(see {table['stem']}.*)"]
    else:
        lines += [f"Not produced: {table['message'].strip()[-800:]}"]
    if mode.name != "full":
        lines += ["", f"These are {mode.name}-mode numbers (short budgets, fewer seeds/items); run `--full` "
                  f"({len(MODES['full'].seeds)} seeds, {MODES['full'].timesteps} steps per algorithm, "
                  f"{_plural(MODES['full'].n_tasks, 'task')}) for the comparison the paper makes."]
    path = out / "SUMMARY.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _fig3_verdict(best: tuple[float, str], aggregates: dict[str, dict[str, AdaptationCurve]], mode: Mode) -> str:
    """One honest sentence comparing our Fig. 3 with the paper's claim."""
    success, algo = best
    maml = aggregates["success_rate"].get("maml_sac")
    if success == 0.0:
        return (f"We fall short of the paper: no algorithm completes a single held-out instruction at any K after "
                f"{mode.timesteps} training steps per algorithm (returns still differ, see the table and figure).")
    if maml is not None and maml.mean.max() >= 0.95 and success <= maml.mean.max():
        return "MAML-SAC reaches the paper's level here and is the best algorithm."
    gain = "" if maml is None else (
        f" MAML-SAC's success goes from {maml.mean[0]:.2f} at K=0 to {maml.mean[-1]:.2f} at K={int(maml.k[-1])}.")
    return (f"We fall short of the paper: the best success rate of any algorithm at any K is {success:.2f} ({algo}), "
            f"after only {mode.timesteps} training steps per algorithm on a shared 2-core CPU.{gain}")


def main(argv: list[str] | None = None) -> Path:
    """Command-line entry point; returns the path of SUMMARY.md (or of the results folder with ``--fig4-only``)."""
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    group = parser.add_mutually_exclusive_group(required=True)
    for name in MODES:
        group.add_argument(f"--{name}", dest="mode", action="store_const", const=name, help=f"{name} mode")
    parser.add_argument("--out", type=Path, default=None,
                        help="figures, tables and SUMMARY.md (None: <work>/results)")
    parser.add_argument("--work", type=Path, default=None,
                        help="models and logs (None: a fresh runs/reproduce-<mode>-<timestamp>)")
    parser.add_argument("--overwrite-results", action="store_true",
                        help="allow --out to be the committed results/ folder (maintainers refreshing it)")
    parser.add_argument("--jobs", type=int, default=min(os.cpu_count() or 1, 16), help="parallel training processes")
    parser.add_argument("--algos", nargs="+", default=None, choices=FIG3_ALGOS, help="subset of Fig. 3's algorithms")
    parser.add_argument("--skip-table1", action="store_true", help="do not run the multimedia benchmark")
    parser.add_argument("--resume", action="store_true",
                        help="reuse models already trained in --work (their recorded training time counts) "
                        "and re-evaluate")
    parser.add_argument("--fig4-only", action="store_true",
                        help="only Fig. 4 with the packaged pretrained policies (no training; a few minutes)")
    args = parser.parse_args(argv)
    mode = MODES[args.mode]
    if args.algos:
        mode = replace(mode, algos=tuple(args.algos))
    if args.jobs < 1:
        parser.error("--jobs must be >= 1")
    if args.resume and args.work is None:
        parser.error("--resume needs --work: the folder of the earlier run whose models to reuse")
    work = args.work or REPO_ROOT / "runs" / f"reproduce-{mode.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    out = args.out or work / "results"
    if out.resolve() == (REPO_ROOT / "results").resolve() and not args.overwrite_results:
        parser.error(f"--out {out} is the committed reference results; pass --overwrite-results to replace them")
    out.mkdir(parents=True, exist_ok=True)
    print(f"writing models and logs to {work}, results to {out}")
    if args.fig4_only:
        for name, log in fig4(mode, out).items():
            outcomes = ", ".join(f"[{e['instruction']}] {e['outcome']}, {e['collisions']} contact steps" for e in log)
            print(f"{name}: {sum(bool(e['success']) for e in log)}/{len(FIG4_PHASES)} phases succeeded: {outcomes}")
        return out
    if (work / "logs").exists() and not args.resume:
        raise SystemExit(
            f"{work}/logs exists from an earlier run; pass --resume to reuse its models, or another --work"
        )

    from zoo.registry import UNAVAILABLE, register_algorithms

    register_algorithms()
    missing = {a: UNAVAILABLE[a] for a in mode.algos if a in UNAVAILABLE}
    if missing:
        raise SystemExit(f"cannot reproduce Fig. 3, algorithms missing: {missing}")

    times: dict[str, float] = {"load": os.getloadavg()[0], "resumed": float(args.resume)}
    start = time.perf_counter()
    jobs = run_jobs(
        [Job(algo, seed, mode, work, resume=args.resume) for algo in mode.algos for seed in mode.seeds], args.jobs
    )
    rows = [row for job in jobs for row in job.rows]
    aggregates = aggregate_adaptation(rows, group="algo") if rows else {metric: {} for metric in ADAPTATION_METRICS}
    if rows:
        write_rows(rows, out / "fig3_adaptation.csv")
        write_rows(fig3_summary_rows(aggregates), out / "fig3_adaptation_summary.csv")
        plot_fig3(aggregates, mode, out / "fig3_adaptation.png")
    tb_curves = load_tensorboard([work / "tb"], ["return", "success", "collision"]) if (work / "tb").exists() else {}
    if tb_curves:
        make_plots(tb_curves, out / "training", f"training on {mode.env_id} ({mode.name}), seeds {list(mode.seeds)}")
    write_rows([{"algo": j.algo, "seed": j.seed, "wall_s": round(j.wall_s, 1), "cpu_s": round(j.cpu_s, 1),
                 "error": j.error} for j in jobs], out / "fig3_jobs.csv")
    times["fig3"] = time.perf_counter() - start

    start = time.perf_counter()
    fig4_log: dict[str, Any] = {}
    try:
        fig4_log = fig4(mode, out)
    except Exception as error:  # noqa: BLE001 - report in SUMMARY.md, keep going
        fig4_log["pretrained"] = f"{type(error).__name__}: {error}"
    times["fig4"] = time.perf_counter() - start

    start = time.perf_counter()
    table = {"ok": False, "stem": "", "message": "skipped (--skip-table1)"}
    if not args.skip_table1:
        table = table1(mode, out)
    times["table1"] = time.perf_counter() - start
    times["total"] = times["fig3"] + times["fig4"] + times["table1"]
    (out / f"reproduce_{mode.name}.json").write_text(json.dumps(
        {"mode": asdict(mode), "times_s": times, "commit": _git("rev-parse", "HEAD")}, indent=1, default=str))
    summary = write_summary(mode, jobs, aggregates, fig4_log, table, times, out)
    print(summary)
    return summary


if __name__ == "__main__":
    main()
