"""zoo/online_control.py --model: any saved SB3 model with predict runs, and a task-family mismatch is warned about."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from zoo import online_control  # noqa: E402


@pytest.mark.parametrize("algo", ["SAC", "MTSAC"])
def test_online_control_runs_any_sb3_model_and_warns_on_another_task_family(algo: str, tmp_path: Path) -> None:
    import gymnasium as gym

    import vafn_gym  # noqa: F401
    import vafn_sb3

    env = gym.make("VAFN/ThreeArmReachHidden-v1", max_length=1)
    model = getattr(vafn_sb3, algo)("MlpPolicy", env, policy_kwargs={"net_arch": [16, 16]}, seed=0)
    model.save(tmp_path / "model.zip")
    env.close()
    (tmp_path / "model.json").write_text(json.dumps({"env_id": "VAFN/ThreeArmReachHidden-v1"}))
    with pytest.warns(UserWarning, match="targets: trained with 'per_arm', running with 'default'"):
        online_control.main(["--model", str(tmp_path / "model.zip"), "--trust-remote-code", "--schedule", "0:1",
                             "--steps", "20", "--out", str(tmp_path / "out")])
    assert (tmp_path / "out" / "online_log.csv").read_text().count("\n") == 2, "one instruction logged"


def test_online_control_refuses_an_unloadable_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "junk.zip").write_bytes(b"not a zip")
    with pytest.raises(SystemExit) as exit_info:
        online_control.main(["--model", str(tmp_path / "junk.zip"), "--schedule", "0:1", "--steps", "5"])
    assert exit_info.value.code == 2 and "not a saved model" in capsys.readouterr().err


def test_online_control_infers_hidden_targets_for_a_goal_observing_model(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import warnings

    import gymnasium as gym

    import vafn_gym  # noqa: F401
    from vafn_sb3 import SAC, save_weights

    env = gym.make("VAFN/ThreeArmReachGoal-v1", max_length=1)
    save_weights(SAC("MlpPolicy", env, policy_kwargs={"net_arch": [16, 16]}, seed=0), tmp_path / "goal.zip")
    env.close()
    (tmp_path / "goal.json").write_text(json.dumps({"env_id": "VAFN/ThreeArmReachGoal-v1"}))
    common = ["--schedule", "0:1", "--steps", "20", "--targets", "per_arm", "--out", str(tmp_path / "out")]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same task family once the targets are inferred: no warning
        online_control.main(["--model", str(tmp_path / "goal.zip"), "--infer-targets", "probe", *common])
    assert (tmp_path / "out" / "online_log.csv").read_text().count("\n") == 2
    with pytest.raises(SystemExit) as exit_info:
        online_control.main(["--policy", "scripted", "--infer-targets", "probe", *common])
    assert exit_info.value.code == 2 and "--infer-targets needs --model" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        online_control.main(["--model", str(tmp_path / "goal.zip"), "--infer-targets", "probe", "--target-estimator",
                             str(tmp_path / "goal.zip"), *common])
    assert exit_info.value.code == 2 and "--target-estimator needs --infer-targets learned" in capsys.readouterr().err


@pytest.mark.parametrize("algo, inference", [("mappo", "probe"), ("mappo", "learned"), ("mappo", "gradient"),
                                             ("mtsac", "gradient")])  # learned, gradient: the packaged estimators
def test_online_control_runs_the_packaged_goal_observing_policy_on_hidden_targets(
    tmp_path: Path, algo: str, inference: str
) -> None:
    import csv

    online_control.main(["--pretrained", algo, "--infer-targets", inference, "--targets", "per_arm",
                         "--schedule", "0:3,1", "--steps", "250", "--out", str(tmp_path)])
    with (tmp_path / "online_log.csv").open() as handle:
        (row,) = csv.DictReader(handle)
    assert row["outcome"] == "completed" and row["success"] == "True" and row["collisions"] == "0"
    if inference == "gradient":
        with pytest.raises(SystemExit) as exit_info:
            online_control.main(["--pretrained", "mappo", "--infer-targets", "gradient", "--refine-steps", "-1",
                                 "--out", str(tmp_path)])
        assert exit_info.value.code == 2


def test_append_to_gathers_labelled_runs_in_one_table_and_a_rerun_replaces_its_rows(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import csv

    from vafn_sb3 import pretrained_info
    from vafn_sb3.loading import training_seed

    table = tmp_path / "table.csv"
    run = ["--policy", "scripted", "--schedule", "0:1;1:2,1", "--steps", "200", "--out", str(tmp_path / "run"),
           "--append-to", str(table)]
    for label in ("first", "second", "first"):  # the third run replaces the first one's rows
        online_control.main([*run, "--label", label])
    with table.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [(row["inference"], row["model_seed"], row["instruction"]) for row in rows] == [
        ("second", "0", "1"), ("second", "0", "2,1"), ("first", "0", "1"), ("first", "0", "2,1")]
    assert list(rows[0]) == online_control.TABLE_COLUMNS and all(row["success"] == "True" for row in rows)
    # a table of other columns is refused before the run, and left as it was
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    with pytest.raises(SystemExit) as exit_info:
        online_control.main([*run[:-1], str(tmp_path / "other.csv")])
    assert exit_info.value.code == 2 and "not a table of online_control.py runs" in capsys.readouterr().err
    assert (tmp_path / "other.csv").read_text() == "a,b\n1,2\n"
    # a model whose file name gives no seed needs --model-seed
    with pytest.raises(SystemExit) as exit_info:
        online_control.main(["--model", str(tmp_path / "model.zip"), *run[2:], "--label", "x"])
    assert exit_info.value.code == 2 and "--model-seed" in capsys.readouterr().err
    assert training_seed(Path("runs/mtsac_ThreeArmReachGoal-v1_seed3.zip")) == 3
    # a packaged policy's seed is its training seed
    online_control.main(["--pretrained", "mtsac", "--infer-targets", "gradient", "--targets", "per_arm",
                         "--schedule", "0:1", "--steps", "100", "--out", str(tmp_path / "run"), "--append-to",
                         str(table)])
    with table.open(newline="") as handle:
        last = list(csv.DictReader(handle))[-1]
    seed = str(pretrained_info("mtsac", "VAFN/ThreeArmReachGoal-v1")["training_seed"])
    assert (last["inference"], last["model_seed"]) == ("gradient", seed) and last["success"] == "True"


def test_task_family_covers_the_frame_and_what_a_waiting_arm_observes() -> None:
    from vafn_sb3.loading import family_mismatch, task_family

    assert task_family("VAFN/ThreeArmReachGoal-v1") == {
        "n_arms": 3, "targets": "per_arm", "observe_goal": True, "inactive_arms": "hold", "robot": "kuka",
        "frame": "world", "waiting_goal": "target"}
    trained = ("VAFN/ThreeArmReach-v1", {"inactive_arms": "policy", "waiting_goal": "home", "frame": "base"})
    assert family_mismatch(*trained, "VAFN/ThreeArmStream-v1") == [
        "inactive_arms: trained with 'policy', running with 'hold'",
        "frame: trained with 'base', running with 'world'",
        "waiting_goal: trained with 'home', running with 'target'"]
    assert family_mismatch(*trained, "VAFN/ThreeArmReach-v1", trained[1]) == []
