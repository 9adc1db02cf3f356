"""``benchmarks/learning.py``'s curves file: seeds trained by parallel processes with ``--append`` share it."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def fake_rows(seed: int) -> list[dict]:
    return [{"seed": seed, "timesteps": 10, "n_tasks": 2, "wall_s": 1.0, "cpu_s": 1.0, "success": 0.5,
             "collision": 0.0, "episode_steps": 50.0, "waypoint_fraction": 0.5}]


def test_parallel_appends_keep_every_seed(tmp_path, monkeypatch, load_benchmark):
    """Process A (seed 0) starts; B (seed 1) finishes while A trains; A's write must keep B's seed."""
    learning = load_benchmark("learning")
    argv = [str(ROOT / "benchmarks" / "learning.py"), "--out", str(tmp_path), "--append", "--n-test", "2"]

    def other_process_finishes():
        monkeypatch.setattr(sys, "argv", argv + ["--seeds", "1"])
        learning.main()

    def train_one(args, seed, benchmark):
        if seed == 0:
            other_process_finishes()
        return fake_rows(seed), None

    monkeypatch.setattr(learning, "train_one", train_one)
    monkeypatch.setattr(sys, "argv", argv + ["--seeds", "0"])
    learning.main()
    name = "sac_ThreeArmReach-v1"
    with (tmp_path / f"{name}_curves.csv").open(newline="") as handle:
        assert sorted(int(row["seed"]) for row in csv.DictReader(handle)) == [0, 1]
    assert json.loads((tmp_path / f"{name}_summary.json").read_text())["seeds"] == [0, 1]
    assert not list(tmp_path.glob(".*")), "no partial file left behind"


def test_recurrent_baseline_trains_and_is_evaluated_on_the_hidden_family(tmp_path, monkeypatch, load_benchmark):
    """sb3-contrib's RecurrentPPO (zoo key ppo_lstm) runs through the benchmark from hyperparams/ppo_lstm.yml."""
    learning = load_benchmark("learning")
    monkeypatch.setattr(sys, "argv", [
        str(ROOT / "benchmarks" / "learning.py"), "--algo", "ppo_lstm", "--env", "VAFN/ThreeArmReachHidden-v1",
        "--seeds", "0", "--steps", "64", "--eval-every", "64", "--n-eval", "1", "--n-test", "1",
        "--hyperparams", '{"n_steps": 64, "batch_size": 32, "n_epochs": 1}', "--out", str(tmp_path),
        "--save", str(tmp_path / "models")])
    learning.main()
    summary = json.loads((tmp_path / "ppo_lstm_ThreeArmReachHidden-v1_summary.json").read_text())
    assert summary["algo"] == "ppo_lstm" and summary["n_test"] == 1 and 0.0 <= summary["success"]["mean"] <= 1.0
    # the adaptation study and online_control.py load what it saved, named or detected
    from sb3_contrib import RecurrentPPO

    from vafn_sb3.loading import load_model

    (saved,) = (tmp_path / "models").glob("*.zip")
    for algo in ("ppo_lstm", None):
        model, key = load_model(saved, algo, trust_remote_code=True)
        assert isinstance(model, RecurrentPPO) and key == "ppo_lstm"
