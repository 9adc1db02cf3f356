"""Reproduce the paper's experiments into a fresh folder: the adaptation study (Fig. 3), Fig. 4, Table 1, SUMMARY.md.

    python zoo/reproduce.py --quick      # <= 15 min: the packaged checkpoints, and one short training per method
    python zoo/reproduce.py --full       # ~14 CPU-h, 7 h on 2 free cores (--resume goes on): 5 seeds, 3 families
    python zoo/reproduce.py --smoke --out /tmp/vafn-smoke   # CI: every stage end to end in a few minutes
    python zoo/reproduce.py --summary --out results --overwrite-results   # rewrite SUMMARY.md from a results folder

The study is data (``zoo/study.py``): every method of every panel trains with ``benchmarks/learning.py`` from its YAML
for the mode's equal env-step budget, one single-threaded process per (method, seed), each a job on Ray
(``zoo/jobs.py``: a local Ray capped by ``--num-cpus``, or ``--address``'s cluster; a rerun with ``--resume`` skips the
jobs whose record in ``<work>/jobs/`` matches their config and commit); every
panel is then one ``benchmarks/adaptation.py`` call, the one evaluation protocol (the same held-out *test*
instructions, support sets and K for every method, the scripted ceiling and the random floor beside them).

1. **Fig. 3**, two panels: the hidden family (``VAFN/ThreeArmReachHidden-v1``, lengths 1-4, success / collision /
   return against K) and the order family (``VAFN/ThreeArmReach-v1``, lengths 1-10, K = 0: zero-shot generalisation);
   and the dynamics panel (``VAFN/ThreeArmReach-v1`` under the held-out dynamics variants, against K).
   ``--quick`` adds the packaged checkpoints (``vafn_sb3.available_pretrained``) to the panel of their env.
2. **Fig. 4**: 2,000 steps of ``VAFN/ThreeArmStream-v1``, five instructions from ``[1,2,3]`` to ``[2,3,1,3,2,3]``,
   :class:`vafn_sb3.OnlineController` driving each packaged ``VAFN/ThreeArmReach-v1`` policy beside the scripted
   controller.
3. **Table 1**: ``benchmarks/instruction_table.py``.
4. ``SUMMARY.md``: every panel, stream and table beside the paper's claims, with commands, seeds and CPU times.

Every run writes into ``runs/reproduce-<mode>-<timestamp>/`` (models and logs; figures and SUMMARY.md in its
``results/``) unless ``--work`` / ``--out`` say otherwise; the committed ``results/`` is only written with
``--overwrite-results``. ``--resume --work <folder>`` keeps the models already trained there at this commit.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from vafn_gym.constants import SUCCESS_TOLERANCE  # noqa: E402
from vafn_gym.files import write_csv_rows  # noqa: E402
from zoo.study import (  # noqa: E402
    BUDGETS,
    GOAL_ENV,
    HIDDEN_ENV,
    ORDER_ENV,
    PANELS,
    CURVES_PANEL,
    PACKAGED,
    Budget,
    PackagedPolicy,
    Panel,
    StudyMethod,
    support_budget,
)

#: Fig. 4's five phases, simple to complex (first and last as in the paper).
FIG4_PHASES = ("1,2,3", "3,1,2", "1,3,2,1", "3,2,1,3,2", "2,3,1,3,2,3")
FIG4_ENV = "VAFN/ThreeArmStream-v1"
PAPER_FIG4 = "the online controller completes all five phases, each arm within tolerance of its target, no collisions."
#: The paper's claim of each panel (by folder name), quoted in SUMMARY.md.
PANEL_CLAIMS = {panel.name: panel.claim for panel in PANELS}


def run_script(command: list[str], **kwargs: Any) -> subprocess.CompletedProcess:
    """Run one of the repository's scripts from the repository root, single-threaded (every stage's processes)."""
    return subprocess.run(command, cwd=REPO_ROOT, env={**os.environ, "OMP_NUM_THREADS": "1"}, **kwargs)


# --- jobs: benchmarks/learning.py, then benchmarks/adaptation.py on the model, one job per (method, seed) ---
def model_dir(work: Path, panel: Panel, method: StudyMethod) -> Path:
    """Where the models of one method of one panel are saved (one per seed)."""
    return work / "models" / panel.name / (method.models_from or method.label)


def portable(path: Path) -> Path:
    """``path`` relative to the repository root when it lies inside it (so a job's config, and whether a later run may
    reuse its record, do not depend on where the repository is checked out), else as it is."""
    try:
        return Path(path).resolve().relative_to(REPO_ROOT)
    except ValueError:
        return Path(path)


def panel_arguments(panel: Panel, budget: Budget) -> list[str]:
    """``benchmarks/adaptation.py``'s flags of a panel: the one protocol every method of it is evaluated with."""
    what = (f"{budget.name} mode: {budget.timesteps} training steps per method and seed"
            + (", plus the packaged checkpoints (pretrained_*)" if budget.pretrained else ""))
    arguments = ["--env", panel.env_id, "--min-length", str(panel.min_length), "--max-length", str(panel.max_length),
                 "--n-tasks", str(min(panel.n_tasks or budget.n_tasks, budget.n_tasks)),
                 "--k", *map(str, budget.k_values if panel.over_k else (0,)),
                 "--n-support", str(budget.n_support), "--title", what]
    if panel.dynamics is not None:
        arguments += ["--dynamics", panel.dynamics]
    return arguments


def trusted_flag(methods: list[StudyMethod]) -> list[str]:
    """``--trust-remote-code`` where a method's models are SB3 zips (an algorithm without a weights-only format) that
    this run made itself, else nothing."""
    from vafn_sb3.registry import ALGORITHMS

    return ["--trust-remote-code"] if any(not ALGORITHMS[method.algo].weights for method in methods) else []


@dataclass(frozen=True)
class TrainJob:
    """One method of one panel trained for one seed by ``benchmarks/learning.py``, then its model evaluated by
    ``benchmarks/adaptation.py`` as the panel evaluates it (and as every method evaluating its models does)."""

    panel: Panel
    method: StudyMethod
    seed: int
    budget: Budget
    work: Path

    @property
    def tag(self) -> str:
        """Suffix of learning.py's output files: the panel and the method label."""
        return f"_{self.panel.name}_{self.method.label}"

    @property
    def model_dir(self) -> Path:
        """Where this method's models (one per seed) are saved."""
        return model_dir(portable(self.work), self.panel, self.method)

    @property
    def name(self) -> str:
        """learning.py's file stem: ``<algo>_<EnvName><tag>``."""
        return f"{self.method.algo}_{self.method.train_env.split('/')[-1]}{self.tag}"

    @property
    def model_path(self) -> Path:
        """The saved model of this seed (learning.py's ``--save`` naming)."""
        return self.model_dir / f"{self.name}_seed{self.seed}.zip"

    @property
    def folder(self) -> Path:
        """This job's own outputs: its learning curve (``learning/``) and its evaluation (``eval/``)."""
        return portable(self.work) / "job_outputs" / self.job_id

    @property
    def curves_path(self) -> Path:
        """learning.py's curves file of this seed."""
        return self.folder / "learning" / f"{self.name}_curves.csv"

    @property
    def log_path(self) -> Path:
        """stdout and stderr of the job's processes."""
        return portable(self.work) / "logs" / f"{self.panel.name}_{self.method.label}_seed{self.seed}.log"

    @property
    def job_id(self) -> str:
        """The name of its Ray job and of its record ``<work>/jobs/<job_id>.json``."""
        return f"train_{self.panel.name}_{self.method.label}_seed{self.seed}"

    @property
    def evaluated(self) -> list[StudyMethod]:
        """The panel's methods that evaluate this model: the method itself and those reading its models."""
        return [m for m in self.panel.methods if self.method.label in (m.label, m.models_from)]

    def config(self) -> dict[str, Any]:
        """Its job's config for ``zoo.jobs.run_commands`` (``python``: the worker's interpreter); a rerun skips the
        job only when its record holds the same config (paths are relative to the repository where they lie in it)."""
        eval_dir = self.folder / "eval"
        return {"panel": self.panel.name, "method": self.method.label, "algo": self.method.algo, "seed": self.seed,
                "commands": [["python", *self.command()[1:]], ["python", *self.evaluation_command()[1:]]],
                "outputs": [str(self.model_path), str(eval_dir / "adaptation.csv")], "log": str(self.log_path),
                "collect": {"curves": str(self.curves_path), "adaptation.csv": str(eval_dir / "adaptation.csv"),
                            "adaptation.json": str(eval_dir / "adaptation.json")}}

    def command(self) -> list[str]:
        """learning.py's arguments: the mode's step budget, one final evaluation, the model kept."""
        steps = self.budget.timesteps
        every = self.budget.curve_every if self.panel.name == CURVES_PANEL and self.budget.curve_every else steps
        command = [sys.executable, "benchmarks/learning.py", "--algo", self.method.algo, "--env", self.method.train_env,
                   "--seeds", str(self.seed), "--steps", str(steps),
                   "--train-max-length", str(self.budget.train_max_length), "--eval-every", str(every),
                   "--n-eval", str(self.budget.n_tasks), "--n-test", str(self.budget.n_tasks),
                   "--out", str(self.folder / "learning"),
                   "--tag", self.tag, "--save", str(self.model_dir)]
        if self.method.env_kwargs:
            command += ["--env-kwargs", json.dumps(self.method.env_kwargs)]
        if self.method.hyperparams:
            command += ["--hyperparams", json.dumps(self.method.hyperparams)]
        return command

    def evaluation_command(self) -> list[str]:
        """adaptation.py on this model for every method that evaluates it, without the references (the panel adds
        them once), into this job's ``eval/``."""
        command = [sys.executable, "benchmarks/adaptation.py", *panel_arguments(self.panel, self.budget),
                   "--no-references", "--out", str(self.folder / "eval"), *trusted_flag(self.evaluated)]
        for method in self.evaluated:
            command += ["--method", *method.method_fields(str(self.model_path))]
        return command


@dataclass(frozen=True)
class PackagedJob:
    """One packaged policy trained again by ``benchmarks/learning.py`` and exported with its held-out evaluation by
    ``benchmarks/export_pretrained.py``; its record carries the exported pair."""

    policy: PackagedPolicy
    budget: Budget
    work: Path

    @property
    def job_id(self) -> str:
        """The name of its Ray job and of its record."""
        return f"packaged_{self.policy.label}"

    @property
    def folder(self) -> Path:
        """This job's own outputs (``learning/``, ``model/``, ``pretrained/``)."""
        return portable(self.work) / "job_outputs" / self.job_id

    @property
    def steps(self) -> int:
        """Its env steps: the budget's share of the shipped policy's own."""
        return max(1, round(self.policy.timesteps * self.budget.packaged_share))

    @property
    def stem(self) -> str:
        """learning.py's file stem."""
        return f"{self.policy.algo}_{self.policy.env_id.split('/')[-1]}_packaged"

    def config(self) -> dict[str, Any]:
        """Its job's config for ``zoo.jobs.run_commands``."""
        policy, folder = self.policy, self.folder
        model = folder / "model" / f"{self.stem}_seed{policy.seed}.zip"
        train = ["python", "benchmarks/learning.py", "--algo", policy.algo, "--env", policy.env_id, "--seeds",
                 str(policy.seed), "--steps", str(self.steps), "--train-max-length", str(policy.train_max_length),
                 "--eval-every", str(self.steps), "--n-test", str(self.budget.packaged_n_test),
                 "--out", str(folder / "learning"), "--tag", "_packaged", "--save", str(folder / "model")]
        if policy.hyperparams:
            train += ["--hyperparams", json.dumps(policy.hyperparams)]
        export = ["python", "benchmarks/export_pretrained.py", "--algo", policy.algo, "--env", policy.env_id,
                  "--model", str(model), "--summary", str(folder / "learning" / f"{self.stem}_summary.json"),
                  "--seed", str(policy.seed), "--n-test", str(self.budget.packaged_n_test),
                  "--out", str(folder / "pretrained")]
        from vafn_sb3.pretrained import pretrained_path

        shipped = pretrained_path(policy.algo, policy.env_id).with_suffix(".json")
        note = json.loads(shipped.read_text()).get("note") if shipped.is_file() else None
        if note:
            export += ["--note", note]
        exported = folder / "pretrained" / policy.label
        return {"packaged": policy.label, "seed": policy.seed, "commands": [train, export],
                "outputs": [str(exported.with_suffix(".zip")), str(exported.with_suffix(".json"))],
                "log": str(portable(self.work) / "logs" / f"{self.job_id}.log"),
                "collect": {"zip": str(exported.with_suffix(".zip")), "json": str(exported.with_suffix(".json")),
                            "curves": str(folder / "learning" / f"{self.stem}_curves.csv")}}


def packaged_jobs(budget: Budget, work: Path) -> list[PackagedJob]:
    """The packaged policies the mode trains again (none unless ``budget.packaged_share``)."""
    return [PackagedJob(policy, budget, work) for policy in PACKAGED] if budget.packaged_share else []


def write_packaged(jobs: list[PackagedJob], out: Path) -> Path | None:
    """Write every finished packaged job's exported pair into ``out/pretrained`` (what a maintainer copies into
    ``vafn_sb3/pretrained``); returns the folder, or None when no job finished."""
    from zoo.jobs import write_file_text

    folder = out / "pretrained"
    written = False
    for job in jobs:
        files = job_files(job)
        if not files:
            continue
        for suffix in ("zip", "json"):
            write_file_text(files[suffix], folder / f"{job.policy.label}.{suffix}")
        written = True
    return folder if written else None


def train_jobs(budget: Budget, panels: tuple[Panel, ...], work: Path) -> list[TrainJob]:
    """Every (panel, method, seed) the mode trains (not the methods that evaluate another method's models)."""
    return [TrainJob(panel, method, seed, budget, work)
            for panel in panels for method in panel.methods if method.models_from is None for seed in budget.seeds]


#: The committed training costs (``training_costs.csv`` of earlier runs) that estimate a run before it starts.
COST_FILES: tuple[str, ...] = ("results/training_costs.csv", "results/adaptation/*/training_costs.csv")
#: CPU seconds per env step of a job no committed run measured (SAC's order of magnitude at [64, 64]).
UNMEASURED_CPU_S_PER_STEP: float = 0.008


def measured_cpu_per_step(root: Path = REPO_ROOT) -> dict[tuple[str, str], float]:
    """Median CPU seconds per env step of every ``(panel, method)`` and every ``("", algo)`` in the cost files."""
    samples: dict[tuple[str, str], list[float]] = {}
    for pattern in COST_FILES:
        for path in sorted(root.glob(pattern)):
            with path.open(newline="") as handle:
                for row in csv.DictReader(handle):
                    per_step = float(row["cpu_s"]) / max(int(row["timesteps"]), 1)
                    for key in ((row["panel"], row["method"]), ("", row["algo"])):
                        samples.setdefault(key, []).append(per_step)
    return {key: float(np.median(values)) for key, values in samples.items()}


Job = TrainJob | PackagedJob


def job_labels(job: Job) -> tuple[str, str, str, int]:
    """``(panel, method, algo, seed)`` of a job (``packaged`` and the policy's stem for a packaged policy)."""
    if isinstance(job, PackagedJob):
        return "packaged", job.policy.label, job.policy.algo, job.policy.seed
    return job.panel.name, job.method.label, job.method.algo, job.seed


def estimated_cpu_s(job: Job, per_step: dict[tuple[str, str], float]) -> float:
    """CPU seconds a job should take: its method's measured rate, else its algorithm's, else a default."""
    panel, label, algo, _ = job_labels(job)
    rate = per_step.get((panel, label), per_step.get(("", algo)))
    steps = job.steps if isinstance(job, PackagedJob) else job.budget.timesteps
    return steps * (UNMEASURED_CPU_S_PER_STEP if rate is None else rate)


def makespan(costs: list[float], n_workers: int) -> float:
    """Seconds until the last of ``costs`` ends when ``n_workers`` run them longest first, as ``run_training`` does."""
    finish = [0.0] * max(n_workers, 1)
    for cost in sorted(costs, reverse=True):
        finish[finish.index(min(finish))] += cost
    return max(finish)


def run_training(jobs: list[Job], n_workers: int, address: str | None = None) -> list[dict[str, Any]]:
    """Run every job not finished at this commit on Ray (``zoo.jobs``), ``n_workers`` at a time, the longest first (by
    the committed costs, which also drive the progress bar and the estimate printed before it starts), each retried by
    Ray if it fails or its worker dies; one row per job, failed ones with their error."""
    from zoo.jobs import git_commit, is_finished, read_record, run_commands, run_jobs, start_ray

    if not jobs:
        return []
    folder, commit, per_step = jobs[0].work / "jobs", git_commit(), measured_cpu_per_step()
    cost = {job.job_id: 0.0 if is_finished(read_record(folder, job.job_id), job.config(), commit)
            else estimated_cpu_s(job, per_step) for job in jobs}
    ordered = sorted(jobs, key=lambda job: -cost[job.job_id])
    todo = [cost[job.job_id] for job in ordered if cost[job.job_id] > 0]
    if todo:
        print(f"training {len(todo)} jobs ({len(jobs) - len(todo)} already done at this commit): about "
              f"{sum(todo) / 3600:.1f} CPU-h by the committed costs, about {makespan(todo, n_workers) / 3600:.1f} h "
              f"with {n_workers} job(s) at a time on free cores as fast as theirs")
    ray = start_ray(address, None if address else n_workers)
    with tqdm(total=round(sum(todo)), desc="training (estimated CPU-s)", unit="s") as progress:
        def done(record: dict[str, Any]) -> None:
            if record["status"] != "ok":
                tqdm.write(f"{record['job_id']} FAILED: {record['error']}")
            progress.update(round(cost[record["job_id"]]))

        try:
            report = run_jobs(run_commands, [(job.job_id, job.config()) for job in ordered], folder, commit=commit,
                              max_in_flight=n_workers, on_record=done)
        finally:
            ray.shutdown()
    by_id = {record["job_id"]: (record, reused) for records, reused in
             ((report.skipped, True), (report.done, False), (report.failed, False)) for record in records}
    rows = []
    for job in jobs:
        record, reused = by_id[job.job_id]
        panel, label, _, seed = job_labels(job)
        rows.append({"panel": panel, "method": label, "seed": seed, "reused": reused, "error": record.get("error", ""),
                     "wall_s": record.get("wall_s"), "cpu_s": record.get("cpu_s")})
    return rows


def job_files(job: Job) -> dict[str, str]:
    """The texts of the files a finished job collected, by name (``curves``, ``adaptation.csv``, ...); none when the
    job has no successful record."""
    from zoo.jobs import read_record

    record = read_record(job.work / "jobs", job.job_id)
    return record["result"]["files"] if record is not None and record.get("status") == "ok" else {}


def csv_text_rows(text: str | None) -> list[dict[str, str]]:
    """The rows of a CSV file's text (none for None)."""
    return list(csv.DictReader(text.splitlines())) if text else []


def training_costs(jobs: list[Job]) -> list[dict[str, Any]]:
    """Per job: env steps, wall and CPU seconds (training and its final check), success on the training env."""
    rows = []
    for job in jobs:
        panel, label, algo, seed = job_labels(job)
        env = job.policy.env_id if isinstance(job, PackagedJob) else job.method.train_env
        final = [row for row in csv_text_rows(job_files(job).get("curves")) if int(row["seed"]) == seed][-1:]
        rows += [{"panel": panel, "method": label, "algo": algo, "env": env, "seed": seed,
                  "timesteps": int(row["timesteps"]),
                  "wall_s": float(row["wall_s"]), "cpu_s": float(row["cpu_s"]),
                  "train_env_success": float(row["success"])} for row in final]
    return rows


def learning_curves(jobs: list[TrainJob], out: Path) -> list[Path]:
    """Success, collision and return against env steps of the ``CURVES_PANEL`` jobs (mean ± 95 % CI over seeds; held-
    out validation instructions during training, the test ones at the end) as PNGs and CSV in ``out/learning``."""
    from zoo.plot import Curve, make_plots

    curves: dict[str, dict[str, list[Curve]]] = {"success": {}, "collision": {}, "return": {}}
    panel = ""
    for job in jobs:
        rows = [row for row in csv_text_rows(job_files(job).get("curves")) if int(row["seed"]) == job.seed]
        if job.panel.name != CURVES_PANEL or len(rows) < 2:
            continue
        panel = f"{job.panel.name} panel ({job.panel.env_id})"
        steps = np.array([float(row["timesteps"]) for row in rows])
        for metric, runs in curves.items():
            runs.setdefault(job.method.label, []).append(Curve(steps, np.array([float(row[metric]) for row in rows])))
    if not panel:
        return []
    return make_plots(curves, out / "learning" / CURVES_PANEL, f"Learning curves, {panel}")


# --- evaluation: a panel's job rows, plus the references (and packaged checkpoints) in one adaptation.py call ---
def pretrained_methods(panel: Panel) -> list[StudyMethod]:
    """The packaged checkpoints a panel evaluates: those of its env, and goal-observing ones through inference."""
    from vafn_sb3 import available_pretrained
    from vafn_sb3.registry import ALGORITHMS

    methods = []
    for algo, env_id in available_pretrained():
        if env_id == panel.env_id:
            adapts = panel.over_k and callable(getattr(ALGORITHMS[algo].cls, "adapt", None))  # plain SAC has no adapt
            methods.append(StudyMethod(f"pretrained_{algo}", algo, env_id, "adapt" if adapts else "zero-shot"))
        elif panel.env_id == HIDDEN_ENV and env_id == GOAL_ENV:
            methods += [StudyMethod(f"pretrained_{algo}_infer_{how}", algo, env_id, f"infer-{how}")
                        for how in ("probe", "learned", "gradient")]
    return methods


def merge_job_evaluations(jobs: list[TrainJob], folder: Path) -> bool:
    """Write the finished jobs' rows into ``folder/adaptation.csv`` and their methods (models of every seed) into
    ``folder/adaptation.json``, for adaptation.py's ``--append``; False when no job of the panel finished."""
    rows, methods, meta = [], {}, None
    for job in jobs:
        files = job_files(job)
        if "adaptation.json" not in files:
            continue
        meta = json.loads(files["adaptation.json"])
        rows += csv_text_rows(files.get("adaptation.csv"))
        for method in meta["methods"]:
            merged = methods.setdefault(method["label"], {**method, "models": []})
            merged["models"] += method["models"]
    if meta is None or not rows:
        return False
    write_csv_rows(rows, folder / "adaptation.csv")
    (folder / "adaptation.json").write_text(json.dumps({**meta, "methods": list(methods.values())}, indent=2))
    return True


def evaluate_panel(panel: Panel, budget: Budget, work: Path, out: Path, n_workers: int) -> dict[str, Any]:
    """One panel's results: the rows its jobs evaluated, the scripted ceiling and random floor (and in ``--quick`` the
    packaged checkpoints) from one ``benchmarks/adaptation.py --append`` call; returns its status."""
    from vafn_sb3.pretrained import pretrained_path

    folder = out / "adaptation" / panel.name
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("adaptation.csv", "adaptation.json"):  # a stale panel of another run must not be appended to
        (folder / name).unlink(missing_ok=True)
    trained = merge_job_evaluations(train_jobs(budget, (panel,), work), folder)
    packaged = pretrained_methods(panel) if budget.pretrained else []
    if not trained and not packaged:
        return {"ok": False, "message": "no trained model"}
    command = [sys.executable, "benchmarks/adaptation.py", *panel_arguments(panel, budget), "--append",
               "--workers", str(n_workers), "--out", str(folder)]
    for method in packaged:
        command += ["--method", *method.method_fields(str(portable(pretrained_path(method.algo, method.train_env))))]
    result = run_script(command, capture_output=True, text=True)
    return {"ok": result.returncode == 0, "message": (result.stdout + result.stderr)[-2000:]}


# --- Fig. 4 ---
def run_stream(policy: Any, budget: Budget, seed: int, k: int) -> dict[str, np.ndarray]:
    """Drive OnlineController over the five-phase stream; per-step distances, active arm and instruction sequence."""
    import gymnasium as gym

    from vafn_sb3 import OnlineController

    spacing = budget.fig4_steps // len(FIG4_PHASES)
    schedule = {index * spacing: code for index, code in enumerate(FIG4_PHASES)}
    env = gym.make(FIG4_ENV, arrivals=schedule, auto_dequeue=False, horizon=budget.fig4_steps)
    controller = OnlineController(policy, env, k=k, n_support=budget.n_support, seed=seed)
    active: list[int] = []
    try:
        for _ in tqdm(range(budget.fig4_steps), desc="Fig. 4 stream", leave=False):
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


def fig4(budget: Budget, out: Path, pretrained: Path | None = None) -> dict[str, Any]:
    """Fig. 4 for every packaged policy of the stream's world (those in ``pretrained``, a folder of exported pairs,
    else the package's) and for the scripted ceiling."""
    import gymnasium as gym

    from vafn_gym import ScriptedController
    from vafn_sb3 import available_pretrained, load_pretrained, load_weights

    probe = gym.make(FIG4_ENV)
    runs: list[tuple[str, Any, int]] = [("scripted", ScriptedController.for_env(probe), 0)]
    probe.close()
    if pretrained is not None:
        pairs = [(info["algo"], info["env_id"], path.with_suffix(".zip")) for path in sorted(pretrained.glob("*.json"))
                 for info in [json.loads(path.read_text())]]
    else:
        pairs = [(algo, env_id, None) for algo, env_id in available_pretrained()]
    for algo, env_id, path in pairs:
        if env_id == ORDER_ENV:  # the stream's world: default targets, inactive arms held
            model = load_pretrained(algo, env_id) if path is None else load_weights(path)
            runs.insert(0, (algo, model, int(getattr(model, "inner_steps", 0))))
    outcomes = {}
    for name, policy, k in runs:
        trace = run_stream(policy, budget, seed=0, k=k)
        title = (f"Fig. 4 ({budget.name}): {name} on {FIG4_ENV}, {budget.fig4_steps} steps, five phases"
                 + (f", adapted with K={k} at each boundary" if k else ""))
        plot_fig4(trace, title, out / f"fig4_online_{name}.png")
        if trace["log"]:
            write_csv_rows(trace["log"], out / f"fig4_online_{name}.csv")
        outcomes[name] = trace["log"]
    return outcomes


# --- Table 1 ---
def table1(budget: Budget, out: Path) -> dict[str, Any]:
    """Run the multimedia benchmark (Table 1); returns its status and output stem."""
    script = REPO_ROOT / "benchmarks" / "instruction_table.py"
    stem = out / ("instruction_table" if budget.name == "full" else f"table1_{budget.name}")
    if not script.is_file():
        return {"ok": False, "stem": stem, "message": f"{script} not found (multimedia issue not landed)"}
    command = [sys.executable, str(script.relative_to(REPO_ROOT)), *budget.table1_args, "--out", _relative(stem)]
    result = run_script(command, capture_output=True, text=True)
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


def _cell(entry: dict[str, Any] | None, metric: str) -> str:
    """``mean ± 95 % half width`` of one summary entry (``-`` when the method has no row at that K)."""
    if entry is None:
        return "-"
    return f"{float(entry[metric]):.2f} ± {float(entry[metric + '_ci95']):.2f}"


def panel_section(folder: Path) -> list[str]:
    """SUMMARY.md lines of one adaptation panel: its claim, command, budget and one row per method."""
    meta = json.loads((folder / "adaptation.json").read_text())
    by_method: dict[str, dict[int, dict[str, Any]]] = {}
    for entry in meta["summary"]:
        by_method.setdefault(entry["method"], {})[int(entry["k"])] = entry
    k_values = sorted({k for entries in by_method.values() for k in entries})
    shown = list(dict.fromkeys(k for k in (0, 10, k_values[-1]) if k in k_values))
    low, high = meta["test_lengths"]
    lines = [f"### `{folder.name}`: {meta['env']}" + (f" {meta['env_kwargs']}" if meta["env_kwargs"] else ""), ""]
    if folder.name in PANEL_CLAIMS:
        lines += [f"Paper / claim: {PANEL_CLAIMS[folder.name]}", ""]
    appended = " (the last of several `--append` runs; `adaptation.json` lists every method's models)"
    support = support_budget(meta["n_support_steps"], meta["support_episodes_mean"], max(k_values),
                             meta.get("support", "episodes"))
    lines += [f"{meta['n_tasks']} held-out test instructions of lengths {low}-{high}; {support}; "
              f"mean ± 95 % CI over seeds. Figure `{folder.name}/adaptation.png`; command "
              f"`python {meta['command']}`" + (appended if "--append" in meta["command"] else "") + ".", ""]
    # A method whose env shows it the targets the panel hides is a reference, not a contender.
    sighted = {m["label"] for m in meta["methods"] if m["env_kwargs"].get("observe_goal")}
    header = ["method", "seeds", *(f"success K={k}" for k in shown), "collision at its last K"]
    lines += ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for method, entries in by_method.items():
        last = entries[max(entries)]
        name = f"{method} (sees the targets)" if method in sighted else method
        cells = [name, str(next(iter(entries.values()))["n_seeds"]),
                 *(_cell(entries.get(k), "success_rate") for k in shown), _cell(last, "collision_rate")]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", _verdict(by_method, excluded={"scripted", "random", *sighted}), ""]
    return lines


def _verdict(by_method: dict[str, dict[int, dict[str, Any]]], excluded: set[str]) -> str:
    """One sentence: the best learned method of the panel, and MAML-SAC's K = 0 and best K beside it."""
    learned = {method: max(entries.values(), key=lambda e: float(e["success_rate"]))
               for method, entries in by_method.items() if method not in excluded}
    if not learned:
        return "No learned method was evaluated."
    best, entry = max(learned.items(), key=lambda item: float(item[1]["success_rate"]))
    sentence = (f"Best learned method: {best}, success {float(entry['success_rate']):.2f} at K={int(entry['k'])} "
                f"(collision {float(entry['collision_rate']):.2f}).")
    for method in (m for m in by_method if m.endswith("maml_sac")):
        entries, top = by_method[method], learned[method]
        reached = float(top["success_rate"]) >= 0.95 and float(top["collision_rate"]) == 0
        sentence += (f" {method}: {float(entries[min(entries)]['success_rate']):.2f} at K={min(entries)}, best "
                     f"{float(top['success_rate']):.2f} at K={int(top['k'])} "
                     f"({'at least' if reached else 'below'} 0.95 with zero collisions).")
    return sentence


def stream_section(out: Path) -> list[str]:
    """SUMMARY.md lines of Fig. 4 from the ``fig4_online_<policy>.csv`` logs in ``out``."""
    lines = ["## Fig. 4: long-horizon online control (`fig4_online_<policy>.png`)", "", f"Paper: {PAPER_FIG4}", "",
             f"Ours: {FIG4_ENV}, phases {', '.join(f'[{p}]' for p in FIG4_PHASES)} arriving at equal intervals.", "",
             "| policy | instructions started | succeeded | contact steps | outcomes |", "|---|---|---|---|---|"]
    logs = sorted(out.glob("fig4_online_*.csv"))
    for path in logs:
        with path.open(newline="") as handle:
            log = list(csv.DictReader(handle))
        succeeded = sum(row["success"] == "True" for row in log)
        contacts = sum(int(row["collisions"]) for row in log)
        outcomes = ", ".join(f"[{row['instruction']}] {row['outcome']}" for row in log)
        lines.append(f"| {path.stem.removeprefix('fig4_online_')} | {len(log)} | {succeeded} | {contacts} | "
                     f"{outcomes} |")
    return lines + ([""] if logs else ["", "Not produced.", ""])


def jobs_line(records: list[dict[str, Any]]) -> str:
    """What the run's jobs cost, from their records (every sitting's): CPU-hours, the longest job, and the wall time
    ``N`` free cores would take for them (longest first, as ``run_training`` schedules)."""
    costs = [float(record["cpu_s"]) for record in records if record.get("cpu_s") is not None]
    if not costs:
        return ""
    reused = sum(bool(record.get("reused")) for record in records)
    spans = ", ".join(f"{n}: {makespan(costs, n) / 3600:.1f} h" for n in (2, 8, 32))
    return (f"Jobs: {len(costs)} ({reused} finished in earlier sittings), {sum(costs) / 3600:.1f} CPU-h summed over "
            f"their records, the longest {max(costs) / 3600:.2f} h; on N free cores as fast as these ({spans}).")


def write_summary(out: Path, run: dict[str, Any] | None = None) -> Path:
    """``out/SUMMARY.md`` from what ``out`` holds: adaptation panels, stream logs, Table 1, and the run's costs."""
    lines = ["# Reproduction summary", ""]
    records = sorted(out.glob("reproduce_*.json"))
    if run is None and records:  # a folder written by a reproduce run: keep its header
        run = json.loads(records[0].read_text())
    if run is None:
        lines += [f"Written by `python zoo/reproduce.py --summary` at commit `{_git('rev-parse', '--short', 'HEAD')}` "
                  "from the results in this folder; each panel names the command that produced it.", ""]
    else:
        budget = run["budget"]
        ran = run.get("panels") or [p.name for p in PANELS]
        only = f" --panels {' '.join(ran)}" if set(ran) != {p.name for p in PANELS} else ""
        lines += [f"Command: `python zoo/reproduce.py --{budget['name']}{only}` · commit `{run['commit']}` · seeds "
                  f"{list(budget['seeds'])} · {budget['timesteps']} env steps per method and seed (equal budgets) · "
                  f"total wall time {run['times_s']['total'] / 60:.1f} min on {os.cpu_count()} cores (training "
                  f"{run['times_s']['train'] / 60:.1f}, evaluation {run['times_s']['evaluate'] / 60:.1f}, Fig. 4 "
                  f"{run['times_s']['fig4'] / 60:.1f}, Table 1 {run['times_s']['table1'] / 60:.1f} min); 1-min load "
                  f"average at start {run['times_s']['load']:.1f}.", ""]
        jobs = jobs_line(run.get("training", []))
        if jobs:
            lines += [jobs, ""]
        if budget["name"] != "full":
            lines += [f"**{budget['name']} mode**: short training, few seeds and tasks: a check that every stage runs, "
                      "not the comparison (`--full` is). The `pretrained_*` rows are the packaged checkpoints.", ""]
    lines += ["## Fig. 3: adaptation and generalisation on held-out instructions", ""]
    panels = sorted((out / "adaptation").glob("*/adaptation.json"))
    order = {panel.name: index for index, panel in enumerate(PANELS)}
    for meta in sorted(panels, key=lambda p: (order.get(p.parent.name, len(order)), p.parent.name)):
        lines += panel_section(meta.parent)
    if not panels:
        lines += ["Not produced.", ""]
    costs = out / "training_costs.csv"
    if costs.is_file():
        with costs.open(newline="") as handle:
            rows = list(csv.DictReader(handle))
        lines += ["### Training cost (`training_costs.csv`)", "",
                  "| panel | method | seeds | env steps | CPU s per seed (mean) |", "|---|---|---|---|---|"]
        groups: dict[tuple[str, str], list[dict[str, str]]] = {}
        for row in rows:
            groups.setdefault((row["panel"], row["method"]), []).append(row)
        for (panel, method), group in groups.items():
            lines.append(f"| {panel} | {method} | {len(group)} | {group[0]['timesteps']} | "
                         f"{np.mean([float(r['cpu_s']) for r in group]):.0f} |")
        lines.append("")
    lines += stream_section(out)
    lines += ["## Table 1: multimedia instruction generator", ""]
    tables = sorted(out.glob("table1_*.md")) + sorted(out.glob("instruction_table.md"))
    lines += [tables[0].read_text().strip(), ""] if tables else ["Not produced.", ""]
    path = out / "SUMMARY.md"
    path.write_text("\n".join(lines))
    return path


def main(argv: list[str] | None = None) -> Path:
    """Command-line entry point; returns the path of SUMMARY.md (or of the results folder with ``--fig4-only``)."""
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    group = parser.add_mutually_exclusive_group(required=True)
    for name in BUDGETS:
        group.add_argument(f"--{name}", dest="mode", action="store_const", const=name, help=f"{name} mode")
    group.add_argument("--summary", dest="mode", action="store_const", const="summary",
                       help="only rewrite --out's SUMMARY.md from the results already there")
    parser.add_argument("--out", type=Path, default=None,
                        help="figures, tables and SUMMARY.md (None: <work>/results)")
    parser.add_argument("--work", type=Path, default=None,
                        help="models and logs (None: a fresh runs/reproduce-<mode>-<timestamp>)")
    parser.add_argument("--overwrite-results", action="store_true",
                        help="allow --out to be the committed results/ folder (maintainers refreshing it)")
    parser.add_argument("--num-cpus", "--jobs", dest="num_cpus", type=int, default=None,
                        help="training jobs at a time on Ray (the local Ray's CPUs) and evaluation processes "
                             "(None: this machine's cores, at most 16; --jobs is an alias)")
    parser.add_argument("--address", default=None,
                        help="join this running Ray cluster (ray start --head) instead of starting a local Ray")
    parser.add_argument("--panels", nargs="+", default=None, choices=[p.name for p in PANELS],
                        help="subset of the study's panels")
    parser.add_argument("--methods", nargs="+", default=None, help="subset of the panels' method labels")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="override the mode's seeds")
    parser.add_argument("--skip-table1", action="store_true", help="do not run the multimedia benchmark")
    parser.add_argument("--resume", action="store_true", help="keep the models already trained in --work")
    parser.add_argument("--fig4-only", action="store_true",
                        help="only Fig. 4 with the packaged pretrained policies (no training; a few minutes)")
    args = parser.parse_args(argv)
    if args.num_cpus is not None and args.num_cpus < 1:
        parser.error("--num-cpus must be >= 1")
    n_workers = args.num_cpus or min(os.cpu_count() or 1, 16)
    if args.mode == "summary" and args.out is None:
        parser.error("--summary needs --out: the results folder to summarise")
    work = args.work or REPO_ROOT / "runs" / f"reproduce-{args.mode}-{time.strftime('%Y%m%d-%H%M%S')}"
    out = args.out or work / "results"
    if out.resolve() == (REPO_ROOT / "results").resolve() and not args.overwrite_results:
        parser.error(f"--out {out} is the committed reference results; pass --overwrite-results to replace them")
    if args.mode == "summary":
        path = write_summary(out)
        print(path)
        return path
    if args.resume and args.work is None:
        parser.error("--resume needs --work: the folder of the earlier run whose models to reuse")
    budget = BUDGETS[args.mode]
    if args.seeds:
        budget = replace(budget, seeds=tuple(args.seeds))
    panels = tuple(p for p in PANELS if args.panels is None or p.name in args.panels)
    if args.methods:
        unknown = set(args.methods) - {m.label for p in panels for m in p.methods}
        if unknown:
            parser.error(f"--methods: no such method in the panels: {sorted(unknown)}")
        panels = tuple(replace(p, methods=tuple(m for m in p.methods if m.label in args.methods)) for p in panels)
    out.mkdir(parents=True, exist_ok=True)
    print(f"writing models and logs to {work}, results to {out}")
    if args.fig4_only:
        for name, log in fig4(budget, out).items():
            print(f"{name}: {sum(bool(e['success']) for e in log)}/{len(FIG4_PHASES)} phases succeeded")
        return out
    if (work / "models").exists() and not args.resume:
        raise SystemExit(f"{work}/models exists from an earlier run; pass --resume to reuse its models, or another "
                         "--work")

    times: dict[str, float] = {"load": os.getloadavg()[0]}
    start = time.perf_counter()
    jobs = train_jobs(budget, panels, work)
    packaged = packaged_jobs(budget, work) if args.panels is None else []
    records = run_training([*jobs, *packaged], n_workers, args.address)
    # also the panels an earlier run here trained
    costs = training_costs([*train_jobs(budget, PANELS, work), *packaged_jobs(budget, work)])
    if costs:
        write_csv_rows(costs, out / "training_costs.csv")
    learning_curves(jobs, out)
    pretrained = write_packaged(packaged, out)
    times["train"] = time.perf_counter() - start

    start = time.perf_counter()
    status = {panel.name: evaluate_panel(panel, budget, work, out, n_workers)
              for panel in tqdm(panels, desc="evaluation")}
    for name, result in status.items():
        if not result["ok"]:
            print(f"panel {name} not evaluated: {result['message']}", file=sys.stderr)
    times["evaluate"] = time.perf_counter() - start

    start = time.perf_counter()
    fig4(budget, out, pretrained)
    times["fig4"] = time.perf_counter() - start

    start = time.perf_counter()
    table = {"ok": False, "message": "skipped (--skip-table1)"}
    if not args.skip_table1:
        table = table1(budget, out)
        if not table["ok"]:
            print(f"Table 1 not produced: {table['message']}", file=sys.stderr)
    times["table1"] = time.perf_counter() - start
    times["total"] = sum(times[key] for key in ("train", "evaluate", "fig4", "table1"))
    run = {"budget": asdict(budget), "panels": [p.name for p in panels], "times_s": times,
           "commit": _git("rev-parse", "--short", "HEAD"), "training": records,
           "failed": [r for r in records if r["error"]] + [{"panel": n, **s} for n, s in status.items() if not s["ok"]]}
    (out / f"reproduce_{budget.name}.json").write_text(json.dumps(run, indent=1, default=str))
    summary = write_summary(out, run)
    print(summary)
    if run["failed"]:
        raise SystemExit(f"{len(run['failed'])} stage(s) failed; see {out / f'reproduce_{budget.name}.json'}")
    return summary


if __name__ == "__main__":
    main()
