"""What a zoo user sees first: ``--env`` is required, maml_sac warns about a warm-up longer than the run."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

import vafn_gym  # noqa: E402
from zoo import train as zoo_train_wrapper  # noqa: E402
from zoo.experiment import warn_if_no_meta_iteration  # noqa: E402

ENV_ID = "VAFN/ThreeArmReach-v1"
SUBPROCESS_ENV = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def test_train_without_env_exits_with_a_one_line_error() -> None:
    result = subprocess.run(
        [sys.executable, str(REPO_ROOT / "zoo" / "train.py"), "--algo", "sac", "-n", "100"],
        env=SUBPROCESS_ENV, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 1
    errors = [line for line in result.stderr.splitlines() if line.startswith("zoo/train.py:")]
    assert errors == [errors[0]] and "--env is required" in errors[0] and ENV_ID in errors[0], result.stderr[-2000:]
    assert "Traceback" not in result.stderr and "CartPole" not in result.stdout


def test_main_without_env_never_reaches_the_zoo(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(zoo_train_wrapper.zoo_train, "train", lambda: pytest.fail("rl_zoo3 was started without --env"))
    with pytest.raises(SystemExit, match="--env is required"):
        zoo_train_wrapper.main(["--algo", "sac", "-optimize"])


def test_help_works_without_env_and_lists_the_wrapper_options() -> None:
    result = subprocess.run(
        [sys.executable, str(REPO_ROOT / "zoo" / "train.py"), "--help"],
        env=SUBPROCESS_ENV, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    assert "--heartbeat-interval" in result.stdout and "(default: 60)" in result.stdout
    assert "--env ENV" in result.stdout  # rl_zoo3's own options follow


@pytest.mark.parametrize(
    "argv", [["--heartbeat-interval", "0"], ["--heartbeat-interval", "5", "--heartbeat-grace", "5"]]
)
def test_bad_heartbeat_settings_are_rejected(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        zoo_train_wrapper.split_heartbeat_args(["--env", ENV_ID, *argv])
    assert "heartbeat" in capsys.readouterr().err


def test_heartbeat_flags_are_removed_before_rl_zoo3_parses_the_rest() -> None:
    argv = ["--algo", "sac", "--seed", "-1", "--heartbeat-interval", "2", "--env-kwargs", "max_length:1",
            "--heartbeat-grace=5", "-params", "batch_size:32"]  # fmt: skip
    interval, grace, rest = zoo_train_wrapper.split_heartbeat_args(argv)
    assert (interval, grace) == (2, 5)
    assert rest == ["--algo", "sac", "--seed", "-1", "--env-kwargs", "max_length:1", "-params", "batch_size:32"]


def test_docstring_examples_name_registered_envs() -> None:
    envs = re.findall(r"--env (\S+)", zoo_train_wrapper.__doc__ or "")
    assert envs, "no example command in zoo/train.py's docstring"
    for env_id in envs:
        assert env_id in gym.envs.registry, f"zoo/train.py's docstring names unregistered env {env_id}"
    assert set(envs) <= set(vafn_gym.ENV_IDS)


def test_warmup_check_fires_only_when_no_meta_iteration_runs() -> None:
    with pytest.warns(UserWarning, match=r"-n 5000 is not above warmup_steps=20000.*no meta-iteration will run"):
        assert warn_if_no_meta_iteration("maml_sac", {"warmup_steps": 20000}, 5000)
    with pytest.warns(UserWarning, match="no meta-iteration"):
        assert warn_if_no_meta_iteration("maml_sac", {"warmup_steps": 300}, 300)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not warn_if_no_meta_iteration("maml_sac", {"warmup_steps": 300}, 301)
        assert not warn_if_no_meta_iteration("sac", {"learning_starts": 100}, 50)


def test_maml_sac_with_n_below_the_yaml_warmup_warns(tmp_path: Path) -> None:
    # hyperparams/maml_sac.yml has warmup_steps 20000; -n 100 stays inside the plain-SAC warm-up.
    argv = ["--algo", "maml_sac", "--env", ENV_ID, "-n", "100", "-f", str(tmp_path), "--eval-freq", "-1",
            "--seed", "0", "--env-kwargs", "max_length:1", "-params", "learning_starts:1000", "n_train_tasks:5"]
    with pytest.warns(UserWarning, match=r"maml_sac: -n 100 is not above warmup_steps=20000"):
        zoo_train_wrapper.main(argv)
