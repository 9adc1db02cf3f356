"""zoo/reproduce.py: the study as data, every stage end to end (smoke mode), SUMMARY.md from a results folder."""

from __future__ import annotations

import json
from dataclasses import replace
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from zoo.reproduce import TrainJob, main as reproduce_main, write_summary  # noqa: E402
from zoo.study import BUDGETS, HIDDEN_PANEL, PACKAGED, PANELS  # noqa: E402

SUBPROCESS_ENV = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def test_every_panel_method_has_its_algorithm_yaml_and_a_known_evaluation() -> None:
    for panel in PANELS:
        labels = [method.label for method in panel.methods]
        assert len(labels) == len(set(labels)), f"{panel.name}: duplicated labels"
        for method in panel.methods:
            assert (REPO_ROOT / "hyperparams" / f"{method.algo}.yml").is_file(), method
            assert method.evaluation in ("adapt", "zero-shot", "infer-probe", "infer-learned", "infer-gradient",
                                         "identify", "identify-online"), method
            assert panel.over_k or method.evaluation != "adapt", f"{panel.name} is evaluated at K = 0 only"
            if method.models_from is not None:  # evaluates models another method of the panel trains
                source = next(m for m in panel.methods if m.label == method.models_from)
                assert source.models_from is None and (source.algo, source.train_env) == (method.algo,
                                                                                          method.train_env)


def test_a_method_evaluating_another_methods_models_trains_nothing_and_finds_them(tmp_path: Path) -> None:
    from zoo.reproduce import model_dir, train_jobs

    learned = next(m for m in HIDDEN_PANEL.methods if m.models_from is not None)
    source = next(m for m in HIDDEN_PANEL.methods if m.label == learned.models_from)
    labels = {job.method.label for job in train_jobs(BUDGETS["smoke"], (HIDDEN_PANEL,), tmp_path)}
    assert source.label in labels and learned.label not in labels
    assert model_dir(tmp_path, HIDDEN_PANEL, learned) == model_dir(tmp_path, HIDDEN_PANEL, source)


def test_train_job_command_saves_where_the_evaluation_looks(tmp_path: Path) -> None:
    method = next(m for m in HIDDEN_PANEL.methods if m.env_kwargs)
    job = TrainJob(HIDDEN_PANEL, method, 3, BUDGETS["full"], tmp_path)
    command = job.command()
    assert command[command.index("--steps") + 1] == "50000" and command[command.index("--seeds") + 1] == "3"
    assert json.loads(command[command.index("--env-kwargs") + 1]) == method.env_kwargs
    assert Path(command[command.index("--save") + 1]) == job.model_path.parent
    assert job.model_path.name.endswith(f"{job.tag}_seed3.zip")
    assert method.method_fields("M")[-2:] == [json.dumps(method.env_kwargs), method.evaluation]
    # the same job evaluates that model, for every method reading it, without the references the panel adds once
    evaluation = job.evaluation_command()
    assert "--no-references" in evaluation and evaluation.count(str(job.model_path)) == len(job.evaluated) >= 1
    assert {m.label for m in job.evaluated} == {method.label} | {
        m.label for m in HIDDEN_PANEL.methods if m.models_from == method.label}
    inside = TrainJob(HIDDEN_PANEL, method, 3, BUDGETS["full"], REPO_ROOT / "runs" / "full")
    assert inside.config()["log"].startswith("runs/full/"), "a record must not depend on the checkout's path"


def test_a_packaged_policy_job_exports_a_pair_that_fig4_drives(tmp_path: Path) -> None:
    from zoo.jobs import run_commands, write_record
    from zoo.reproduce import PackagedJob, fig4, write_packaged
    budget = replace(BUDGETS["smoke"], packaged_share=0.002, packaged_n_test=1)
    job = PackagedJob(next(p for p in PACKAGED if p.algo == "sac"), budget, tmp_path / "work")
    assert job.steps == 60 and job.job_id == "packaged_sac__VAFN-ThreeArmReach-v1"
    result = run_commands(job.config())
    write_record(job.work / "jobs", {"job_id": job.job_id, "status": "ok", "result": result})
    folder = write_packaged([job], tmp_path / "results")
    assert folder is not None
    info = json.loads((folder / "sac__VAFN-ThreeArmReach-v1.json").read_text())
    assert info["training_env_steps"] == 60 and info["evaluation"]["protocol"].endswith("n_test=1).evaluate")
    assert info["commit"] and "export_pretrained.py" in info["export_command"]
    assert fig4(budget, tmp_path / "results", folder).keys() == {"sac", "scripted"}


def test_a_run_is_estimated_from_the_committed_training_costs(tmp_path: Path) -> None:
    from zoo.reproduce import UNMEASURED_CPU_S_PER_STEP, estimated_cpu_s, makespan, measured_cpu_per_step, train_jobs

    # Five equal jobs on two workers take three rounds, not 2.5; a long job bounds the run however many short ones
    assert makespan([600.0] * 5, 2) == 1800.0 and makespan([1000.0, 10.0, 10.0], 2) == 1000.0
    assert makespan([3.0, 3.0, 2.0, 2.0, 2.0], 2) == 7.0 and makespan([], 2) == 0.0  # longest first, as run_training
    from zoo.reproduce import jobs_line

    line = jobs_line([{"cpu_s": 3600.0, "reused": True}, {"cpu_s": 1800.0}, {"cpu_s": 1800.0}, {"error": "x"}])
    assert line.startswith("Jobs: 3 (1 finished in earlier sittings), 2.0 CPU-h") and "2: 1.0 h, 8: 1.0 h" in line
    assert jobs_line([]) == ""

    costs = tmp_path / "results" / "adaptation" / "hidden" / "training_costs.csv"
    costs.parent.mkdir(parents=True)
    costs.write_text("panel,method,algo,env,seed,timesteps,wall_s,cpu_s,train_env_success\n"
                     "hidden,maac,maac,E,0,50000,800,700,0\nhidden,maac,maac,E,1,50000,800,740,0\n"
                     "order,maac,maac,E,0,10000,300,300,0\nhidden,mappo,mappo,E,0,50000,90,80,0\n")
    per_step = measured_cpu_per_step(tmp_path)
    assert per_step[("hidden", "maac")] == pytest.approx(720 / 50000)  # the median of its panel's seeds
    assert per_step[("", "maac")] == pytest.approx(740 / 50000)  # the median over every panel's seeds
    jobs = {job.method.label: job for job in train_jobs(BUDGETS["full"], (HIDDEN_PANEL,), tmp_path)}
    assert estimated_cpu_s(jobs["maac"], per_step) == pytest.approx(720)  # its own panel's rate, not order's
    assert estimated_cpu_s(jobs["mappo"], per_step) == pytest.approx(80)
    assert estimated_cpu_s(jobs["mtsac"], per_step) == pytest.approx(50000 * UNMEASURED_CPU_S_PER_STEP)
    committed = measured_cpu_per_step()  # the repository's own files: every trained method of Fig. 3 has a rate
    assert all((panel.name, method.label) in committed for panel in PANELS for method in panel.methods
               if method.models_from is None)


def test_summary_is_written_from_a_results_folder(tmp_path: Path) -> None:
    shutil.copytree(REPO_ROOT / "results" / "adaptation" / "hidden_long", tmp_path / "adaptation" / "hidden_long")
    summary = write_summary(tmp_path).read_text()
    row = next(line for line in summary.splitlines() if line.startswith("| goal_mappo_infer_probe |"))
    meta = json.loads((tmp_path / "adaptation" / "hidden_long" / "adaptation.json").read_text())
    entry = next(e for e in meta["summary"] if e["method"] == "goal_mappo_infer_probe")
    assert f"{entry['success_rate']:.2f} ± {entry['success_rate_ci95']:.2f}" in row
    assert "Best learned method" in summary and "Fig. 4" in summary
    assert "lengths 1-10; no adaptation (K = 0);" in summary, "a K = 0 panel spends no support set"
    shutil.copytree(REPO_ROOT / "results" / "adaptation" / "hidden", tmp_path / "adaptation" / "hidden")
    assert "lengths 1-4; a support set of 400 env steps" in write_summary(tmp_path).read_text()
    with pytest.raises(SystemExit):
        reproduce_main(["--summary", "--out", str(REPO_ROOT / "results")])  # the committed folder needs a flag


def _reproduce_smoke(tmp_path: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(REPO_ROOT / "zoo" / "reproduce.py"), "--smoke", "--methods", "maml_sac", "mappo",
         "--jobs", "2", "--work", str(tmp_path / "work"), "--out", str(tmp_path / "results"), *extra],
        env=SUBPROCESS_ENV, capture_output=True, text=True, timeout=900,
    )


def test_reproduce_smoke_writes_every_artefact(tmp_path: Path) -> None:
    result = _reproduce_smoke(tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    out = tmp_path / "results"
    for name in ("adaptation/hidden/adaptation.png", "adaptation/order/adaptation.png", "training_costs.csv",
                 "fig4_online_sac.png", "fig4_online_scripted.png", "table1_smoke.md", "SUMMARY.md"):
        assert (out / name).is_file(), f"{name} missing; stderr: {result.stderr[-2000:]}"
    # hidden: scripted, random, the packaged goal-observing MAPPO and MTSAC with probe and learned inference at K = 0;
    # the packaged hidden-family MAML-SAC and MTSAC, the trained maml_sac and mappo and the packaged goal-observing
    # MAPPO and MTSAC with gradient inference at K = 0 and 1 (1 task, 1 seed)
    assert len((out / "adaptation" / "hidden" / "adaptation.csv").read_text().splitlines()) == 1 + 6 + 6 * 2
    # order: scripted, random, maml_sac, mappo, the two packaged order-family policies, all at K = 0
    assert len((out / "adaptation" / "order" / "adaptation.csv").read_text().splitlines()) == 1 + 6
    # dynamics: every row under each of the 12 held-out variants: scripted, random and the packaged SAC at K = 0, the
    # packaged MAML-SAC at K = 0 and 1 (1 task)
    assert len((out / "adaptation" / "dynamics" / "adaptation.csv").read_text().splitlines()) == 1 + 12 * (3 + 2)
    costs = (out / "training_costs.csv").read_text().splitlines()
    trained = [row for row in costs[1:] if not row.startswith("packaged,")]
    assert len(trained) == 4 and all(",300," in row or ",1024," in row for row in trained), costs
    # the packaged policies trained again (a tiny share of their steps) and exported; Fig. 4 drove the new ones
    assert len(costs) == 1 + 4 + len(PACKAGED) and len(list((out / "pretrained").glob("*.json"))) == len(PACKAGED)
    assert (out / "learning" / "order_success.png").is_file(), "the order panel's learning curves"
    summary = (out / "SUMMARY.md").read_text()
    assert "FAILED" not in summary and "Not produced" not in summary, summary
    assert "| maml_sac |" in summary and "| pretrained_sac |" in summary and "| scripted |" in summary
    for header in (line for line in summary.splitlines() if line.startswith("| method |")):
        cells = [cell.strip() for cell in header.strip("|").split("|")]
        assert len(cells) == len(set(cells)), f"duplicated column: {header}"

    again = _reproduce_smoke(tmp_path)
    assert again.returncode != 0 and "--resume" in again.stderr + again.stdout, "an earlier run must not be overwritten"
    resumed = _reproduce_smoke(tmp_path, "--resume", "--skip-table1", "--panels", "order")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    records = json.loads((out / "reproduce_smoke.json").read_text())["training"]
    assert records and all(record["reused"] for record in records), "--resume retrained"
    assert "`python zoo/reproduce.py --smoke --panels order`" in (out / "SUMMARY.md").read_text()
