"""benchmarks/adaptation.py: several methods' saved models adapt to the same held-out tasks; references included."""

from __future__ import annotations

import csv
import json
import runpy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vafn_sb3 import MTSAC, SAC, GradientTargetEstimator, LearnedTargetEstimator, save_weights
from vafn_sb3.inference import REFINE_SOLVER, REFINE_STEPS

ROOT = Path(__file__).resolve().parents[1]
HIDDEN = "VAFN/ThreeArmReachHidden-v1"


@pytest.fixture(scope="module")
def study():
    """The script's namespace (imported once, not run)."""
    return runpy.run_path(str(ROOT / "benchmarks" / "adaptation.py"), run_name="adaptation_study")


def tiny(algo: type, env_kwargs: dict, seed: int, path: Path) -> Path:
    import gymnasium as gym

    env = gym.make(HIDDEN, max_length=1, **env_kwargs)
    model = algo("SharedAgentPolicy", env, learning_starts=10, batch_size=8, policy_kwargs={"net_arch": [8]}, seed=seed)
    model.learn(20)
    save_weights(model, path)  # a weights-only file: the study loads it without --trust-remote-code
    env.close()
    return path


def test_method_parse_fails_clearly(study, tmp_path):
    method = study["Method"]
    with pytest.raises(ValueError, match="LABEL ALGO GLOB"):
        method.parse(["only", "two"])
    with pytest.raises(ValueError, match="no model matches"):
        method.parse(["x", "sac", str(tmp_path / "none_*.zip")])
    (tmp_path / "sac_seed3.zip").write_bytes(b"")
    with pytest.raises(ValueError, match="JSON object"):
        method.parse(["x", "sac", str(tmp_path / "*.zip"), "[1]"])
    parsed = method.parse(["x", "sac", str(tmp_path / "*.zip"), '{"history": 2}', "zero-shot"])
    assert parsed.env_kwargs == {"history": 2} and parsed.zero_shot and study["seed_of"](parsed.paths[0]) == 3
    assert parsed.target_inference is None
    inferred = method.parse(["x", "sac", str(tmp_path / "*.zip"), "infer-probe"])
    assert inferred.zero_shot and inferred.target_inference == "probe" and inferred.env_kwargs == {}
    assert method.parse(["x", "sac", str(tmp_path / "*.zip"), "infer-none"]).target_inference == "none"
    with pytest.raises(ValueError, match="at most one"):
        method.parse(["x", "sac", str(tmp_path / "*.zip"), "zero-shot", "infer-probe"])


def test_summary_is_a_mean_over_seeds_of_task_means_with_a_t_interval(study):
    rows = [{"method": "m", "seed": s, "k": 0, "success_rate": v, "collision_rate": 0.0, "return_mean": 1.0}
            for s, values in ((0, (1.0, 0.0)), (1, (1.0, 1.0))) for v in values]
    (entry,) = study["summary_rows"](study["aggregate_adaptation"](rows))
    assert entry["success_rate"] == pytest.approx(0.75) and entry["n_seeds"] == 2 and entry["n_tasks"] == 2
    assert entry["success_rate_ci95"] == pytest.approx(12.706 * 0.25, rel=1e-3)  # t(0.975, 1) * std / sqrt(2)
    assert entry["collision_rate_ci95"] == 0.0


def test_by_length_table_splits_tasks_by_instruction_length(study):
    rows = [{"method": "m", "seed": seed, "k": k, "task": task, "success_rate": success, "collision_rate": 0.0,
             "return_mean": 1.0, "support_arms": arms if k else float("nan")}
            for seed in (0, 1) for k in (0, 5)
            for task, success, arms in (("2", 1.0, 1.0), ("3", 0.0, 1.0), ("2,3,1", 0.0, 1 / 3))]
    table = {(e["length"], e["k"]): e for e in study["by_length_rows"](rows)}
    assert set(table) == {(1, 0), (1, 5), (3, 0), (3, 5)}
    assert table[1, 5]["success_rate"] == 0.5 and table[1, 5]["n_tasks"] == 2 and table[1, 5]["n_seeds"] == 2
    assert table[3, 5]["success_rate"] == 0.0 and table[3, 5]["support_arms"] == pytest.approx(1 / 3)
    assert table[1, 0]["support_arms"] != table[1, 0]["support_arms"]  # NaN: K = 0 collects no support


@pytest.mark.parametrize("workers", [1, 2])
def test_study_end_to_end(study, tmp_path, monkeypatch, workers):
    models = tmp_path / "models"
    models.mkdir()
    for seed in (0, 1):
        tiny(MTSAC, {}, seed, models / f"mtsac_seed{seed}.zip")
    tiny(SAC, {"history": 2}, 0, models / "sac_seed0.zip")
    tiny(SAC, {"observe_goal": True}, 0, models / "goal_seed0.zip")
    LearnedTargetEstimator(n_readings=4, hidden=(8,)).save(models / "estimator.pt")  # untrained: only the plumbing
    GradientTargetEstimator(hidden=(8,), steps=2).save(models / "gradient.pt")
    out = tmp_path / "out"
    argv = ["adaptation.py", "--max-length", "1", "--n-tasks", "2", "--k", "0", "1", "--n-support", "12",
            "--method", "mtsac", "mtsac", str(models / "mtsac_seed*.zip"),
            "--method", "history", "sac", str(models / "sac_seed*.zip"), '{"history": 2}', "zero-shot",
            "--method", "inferred", "sac", str(models / "goal_seed*.zip"), "infer-passive",
            "--method", "learned", "sac", str(models / "goal_seed*.zip"), "infer-learned",
            "--method", "gradient", "sac", str(models / "goal_seed*.zip"), "infer-gradient",
            "--target-estimator", str(models / "estimator.pt"), "--gradient-estimator", str(models / "gradient.pt"),
            "--workers", str(workers), "--out", str(out)]
    if workers == 1:
        monkeypatch.setattr(sys, "argv", argv)
        study["main"](argv[1:])
    else:  # child processes need the script as a real __main__, as a user runs it
        subprocess.run([sys.executable, str(ROOT / "benchmarks" / "adaptation.py"), *argv[1:]], check=True,
                       capture_output=True)
    with (out / "adaptation.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    methods = ("scripted", "random", "mtsac", "history", "inferred", "learned", "gradient")
    counts = {m: sum(1 for r in rows if r["method"] == m) for m in methods}
    assert counts == {"scripted": 2, "random": 2, "mtsac": 2 * 2 * 2, "history": 2, "inferred": 2, "learned": 2,
                      "gradient": 2 * 2}  # gradient inference runs at every K
    assert all(float(r["success_rate"]) == 1.0 for r in rows if r["method"] == "scripted")
    meta = json.loads((out / "adaptation.json").read_text())
    assert meta["n_support_steps"] == 12 and meta["support_episodes_mean"] == 1.0
    assert {(e["method"], e["k"]) for e in meta["summary"]} >= {("mtsac", 0), ("mtsac", 1), ("history", 0)}
    assert (out / "adaptation.png").stat().st_size > 0
    with (out / "adaptation_by_length.csv").open() as handle:
        by_length = list(csv.DictReader(handle))
    assert {(r["method"], r["length"]) for r in by_length} >= {("mtsac", "1"), ("scripted", "1")}
    assert all(float(r["support_arms"]) == 1.0 for r in by_length if r["method"] == "mtsac" and r["k"] == "1")
    assert [m.get("target_estimator") for m in meta["methods"]] == [None, None, None, str(models / "estimator.pt"),
                                                                     None]
    assert meta["methods"][-1]["gradient_estimator"] == str(models / "gradient.pt")
    # recorded: they change what infer-gradient does
    assert meta["methods"][-1]["refine_steps"] == REFINE_STEPS[REFINE_SOLVER]
    assert meta["methods"][-1]["refine_solver"] == REFINE_SOLVER
    assert all(r["support_arms"] == "nan" for r in rows if r["method"] == "gradient")  # adapts on no support set


def test_learned_inference_needs_a_readable_estimator(study, tmp_path):
    (tmp_path / "goal_seed0.zip").write_bytes(b"")
    method = ["--method", "learned", "sac", str(tmp_path / "goal_seed*.zip"), "infer-learned"]
    with pytest.raises(SystemExit, match="--target-estimator"):
        study["main"]([*method, "--target-estimator", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "out")])
    (tmp_path / "estimator.pt").write_text("not an estimator")
    with pytest.raises(SystemExit, match="LearnedTargetEstimator.save"):
        study["main"]([*method, "--target-estimator", str(tmp_path / "estimator.pt"), "--out", str(tmp_path / "out")])
    gradient = ["--method", "gradient", "sac", str(tmp_path / "goal_seed*.zip"), "infer-gradient"]
    with pytest.raises(SystemExit, match="--gradient-estimator: .*GradientTargetEstimator.save"):
        study["main"]([*gradient, "--gradient-estimator", str(tmp_path / "estimator.pt"), "--out", str(tmp_path / "o")])
    with pytest.raises(SystemExit, match="--refine-steps must be >= 0"):
        study["main"]([*gradient, "--refine-steps", "-1", "--out", str(tmp_path / "o")])


def test_a_file_that_is_not_a_model_stops_the_study_before_it_evaluates(study, tmp_path):
    (tmp_path / "broken_seed0.zip").write_text("not a model")
    with pytest.raises(SystemExit, match="--method m: .*broken_seed0.zip is not a saved model"):
        study["main"](["--method", "m", "mtsac", str(tmp_path / "broken_seed*.zip"), "--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()


def test_append_keeps_other_methods_and_refuses_other_tasks(study, tmp_path, monkeypatch):
    models = tmp_path / "models"
    models.mkdir()
    tiny(MTSAC, {}, 0, models / "mtsac_seed0.zip")
    out = tmp_path / "out"
    common = ["--max-length", "1", "--n-tasks", "1", "--k", "0", "--n-support", "8", "--out", str(out)]
    study["main"]([*common, "--method", "a", "mtsac", str(models / "*.zip")])
    study["main"]([*common, "--method", "b", "mtsac", str(models / "*.zip"), "--append"])
    meta = json.loads((out / "adaptation.json").read_text())
    assert [m["label"] for m in meta["methods"]] == ["a", "b"]
    assert {e["method"] for e in meta["summary"]} == {"scripted", "random", "a", "b"}
    with pytest.raises(SystemExit, match="other tasks"):
        study["main"]([*common[:-2], "--n-support", "9", "--out", str(out), "--append",
                       "--method", "c", "mtsac", str(models / "*.zip")])
    (out / "adaptation.csv").unlink()  # an earlier run without its episodes: appending would silently drop a and b
    with pytest.raises(SystemExit, match="not its per-episode"):
        study["main"]([*common, "--method", "c", "mtsac", str(models / "*.zip"), "--append"])
    assert [m["label"] for m in json.loads((out / "adaptation.json").read_text())["methods"]] == ["a", "b"]


def test_title_is_kept_by_append_and_set_by_replot(study, tmp_path):
    tiny(MTSAC, {}, 0, tmp_path / "mtsac_seed0.zip")
    out = tmp_path / "out"
    common = ["--max-length", "1", "--n-tasks", "1", "--k", "0", "--n-support", "8", "--out", str(out)]
    study["main"]([*common, "--method", "a", "mtsac", str(tmp_path / "*.zip"), "--title", "first run"])
    study["main"]([*common, "--method", "b", "mtsac", str(tmp_path / "*.zip"), "--append"])

    def title() -> str:
        return json.loads((out / "adaptation.json").read_text())["title"]

    assert title() == "first run"
    study["main"](["--replot", "--out", str(out), "--title", "150k steps"])
    meta = json.loads((out / "adaptation.json").read_text())
    assert meta["title"] == "150k steps" and study["figure_title"](meta).startswith("150k steps\n")
    study["main"](["--replot", "--out", str(out)])
    assert title() == "150k steps"


def test_add_seeds_keeps_a_methods_earlier_seeds_and_refuses_another_evaluation(study, tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    for seed in (0, 1):
        tiny(MTSAC, {}, seed, models / f"mtsac_seed{seed}.zip")
    out = tmp_path / "out"
    common = ["--max-length", "1", "--n-tasks", "1", "--k", "0", "--n-support", "8", "--out", str(out)]
    study["main"]([*common, "--method", "a", "mtsac", str(models / "mtsac_seed0.zip")])
    first = [r for r in csv.DictReader((out / "adaptation.csv").open()) if r["method"] == "a"]
    study["main"]([*common, "--method", "a", "mtsac", str(models / "mtsac_seed1.zip"), "--append", "--add-seeds"])
    rows = [r for r in csv.DictReader((out / "adaptation.csv").open()) if r["method"] == "a"]
    assert sorted(r["seed"] for r in rows) == ["0", "1"] and [r for r in rows if r["seed"] == "0"] == first
    meta = json.loads((out / "adaptation.json").read_text())
    assert [Path(m).name for m in meta["methods"][0]["models"]] == ["mtsac_seed0.zip", "mtsac_seed1.zip"]
    assert [e["n_seeds"] for e in meta["summary"] if e["method"] == "a"] == [2]
    # without --add-seeds the method's rows are replaced, as before
    study["main"]([*common, "--method", "a", "mtsac", str(models / "mtsac_seed1.zip"), "--append"])
    assert [r["seed"] for r in csv.DictReader((out / "adaptation.csv").open()) if r["method"] == "a"] == ["1"]
    with pytest.raises(SystemExit, match="was evaluated with"):
        study["main"]([*common, "--method", "a", "mtsac", str(models / "mtsac_seed0.zip"), "zero-shot", "--append",
                       "--add-seeds"])
    with pytest.raises(SystemExit, match="needs --append"):
        study["main"]([*common, "--method", "a", "mtsac", str(models / "mtsac_seed0.zip"), "--add-seeds"])


def test_failures_after_adaptation_are_the_study_episodes(study, tmp_path, monkeypatch, capsys):
    """benchmarks/failures.py --k runs the adaptation study's episodes: the same success and collision rates."""
    tiny(MTSAC, {}, 0, tmp_path / "mtsac_seed0.zip")
    out = tmp_path / "out"
    study["main"](["--max-length", "1", "--n-tasks", "2", "--k", "2", "--n-support", "8", "--out", str(out),
                   "--method", "m", "mtsac", str(tmp_path / "mtsac_seed0.zip")])
    rows = [r for r in csv.DictReader((out / "adaptation.csv").open()) if r["method"] == "m" and r["k"] == "2"]
    success = sum(float(r["success_rate"]) for r in rows) / 2
    collision = sum(float(r["collision_rate"]) for r in rows) / 2
    capsys.readouterr()  # the study's own printout
    monkeypatch.setattr(sys, "argv", ["failures.py", str(tmp_path / "mtsac_seed0.zip"), "--env", HIDDEN,
                                      "--max-length", "1", "--n-test", "2", "--k", "2", "--n-support", "8"])
    runpy.run_path(str(ROOT / "benchmarks" / "failures.py"), run_name="__main__")
    printed = capsys.readouterr().out
    assert printed.startswith(f"2 held-out instructions after 2 adaptation steps on 8 support transitions: success "
                              f"{success:.2f}, collision rate {collision:.2f}")


@pytest.fixture(scope="module")
def direction():
    """benchmarks/adaptation_direction.py's namespace."""
    return runpy.run_path(str(ROOT / "benchmarks" / "adaptation_direction.py"), run_name="adaptation_direction")


def test_move_toward_measures_the_move_against_the_way_to_the_target(direction):
    move_toward = direction["move_toward"]
    start, target = np.zeros(3), np.array([0.2, 0.0, 0.0])
    assert move_toward(start, np.array([0.1, 0.0, 0.0]), target) == pytest.approx((10.0, 1.0))
    assert move_toward(start, np.array([0.0, 0.05, 0.0]), target) == pytest.approx((5.0, 0.0))
    assert move_toward(start, np.array([-0.1, 0.0, 0.0]), target)[1] == pytest.approx(-1.0)
    moved, cosine = move_toward(start, start, target)
    assert moved == 0.0 and np.isnan(cosine)


def test_direction_adapts_on_the_one_waypoint_tasks_and_needs_k_zero(direction, tmp_path):
    tiny(MTSAC, {}, 0, tmp_path / "mtsac_seed0.zip")
    common = [str(tmp_path / "*.zip"), "--max-length", "1", "--n-tasks", "2", "--n-support", "12"]
    lines = direction["main"]([*common, "--k", "0", "1", "--out", str(tmp_path / "rows.csv")])
    rows = list(csv.DictReader((tmp_path / "rows.csv").open()))
    assert [r["k"] for r in rows] == ["0", "1", "0", "1"]  # two tasks, each unadapted then after one step
    assert all(float(r["moved_cm"]) == 0.0 for r in rows if r["k"] == "0")
    assert all(-1.0 <= float(r["cosine"]) <= 1.0 for r in rows if r["k"] == "1" and r["cosine"] != "nan")
    assert lines[2].startswith("| K | final_cm") and len(lines) == 6
    for k in (["1"], ["0", "-1"]):
        with pytest.raises(SystemExit, match="must be >= 0 and include 0"):
            direction["main"]([*common, "--k", *k])
    with pytest.raises(SystemExit, match="no model matches"):
        direction["main"]([str(tmp_path / "missing*.zip")])
    (tmp_path / "broken_seed1.zip").write_text("not a model")
    with pytest.raises(SystemExit, match="broken_seed1.zip is not a saved model"):
        direction["main"]([*common, "--k", "0"])


def test_failures_names_a_file_that_is_not_a_model(tmp_path, monkeypatch):
    (tmp_path / "broken.zip").write_text("not a model")
    monkeypatch.setattr(sys, "argv", ["failures.py", str(tmp_path / "broken.zip")])
    with pytest.raises(SystemExit, match="broken.zip is not a saved model"):
        runpy.run_path(str(ROOT / "benchmarks" / "failures.py"), run_name="__main__")
