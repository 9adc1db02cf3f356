"""Tests of the RL-Zoo front end.

Algorithm registration, training from the YAMLs, tuning, plots, recording.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import optuna
import pytest
import yaml
from optuna.trial import TrialState

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from vafn_gym.constants import SUCCESS_TOLERANCE  # noqa: E402
from zoo import plot as zoo_plot  # noqa: E402
from zoo.experiment import _merge_policy_kwargs, _yaml_policy_kwargs  # noqa: E402
from zoo.run_config import load_run_config  # noqa: E402
from zoo.tuning import WORKER_ATTR, open_storage, recover_stale_trials  # noqa: E402
from zoo.registry import UNAVAILABLE, VAFN_ALGOS, register_algorithms  # noqa: E402
from zoo.train import complete_argv, main as train_main  # noqa: E402

ENV_ID = "VAFN/ThreeArmReach-v1"
ENV_NAME = "VAFN-ThreeArmReach-v1"
ALL_ALGOS = ["sac", *VAFN_ALGOS]
#: Per-family overrides that keep a test run to a few hundred steps (everything else comes from the YAML).
FAST_PARAMS = {
    "mappo": ["n_steps:128", "batch_size:64", "n_epochs:1"],
    "default": ["learning_starts:200", "batch_size:64"],
}
FAST_ENV_KWARGS = ["max_length:1"]
PYTHON = sys.executable
SUBPROCESS_ENV = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def fast_params(algo: str) -> list[str]:
    """The -params overrides of a short test run of ``algo``."""
    return FAST_PARAMS.get(algo, FAST_PARAMS["default"])


def test_every_algorithm_is_registered_with_a_yaml_entry_for_every_env() -> None:
    import vafn_gym

    registered = register_algorithms()
    assert not UNAVAILABLE, f"vafn algorithms missing from the zoo: {UNAVAILABLE}"
    assert set(registered) == set(ALL_ALGOS)
    for algo in ALL_ALGOS:
        config = yaml.safe_load((REPO_ROOT / "hyperparams" / f"{algo}.yml").read_text())
        for env_id in vafn_gym.ENV_IDS:
            assert env_id in config, f"hyperparams/{algo}.yml has no entry for {env_id}"
            assert {"policy", "n_timesteps"} <= set(config[env_id]), f"{algo}/{env_id} lacks policy or n_timesteps"


def test_missing_algorithm_gives_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    register_algorithms()
    monkeypatch.setitem(UNAVAILABLE, "mappo", "vafn_sb3 does not export MAPPO (not implemented yet?)")
    with pytest.raises(SystemExit, match="'mappo' is not available: vafn_sb3 does not export MAPPO"):
        complete_argv(["--algo", "mappo", "--env", ENV_ID])


def test_wrapper_fills_vafn_defaults_only_when_absent() -> None:
    register_algorithms()
    argv = complete_argv(["--algo", "sac", "--env", ENV_ID, "-optimize"])
    assert argv[argv.index("--conf-file") + 1].endswith("hyperparams/sac.yml")
    assert argv[argv.index("--num-threads") + 1] == "1"
    assert argv[argv.index("--storage") + 1] == f"logs/sac/optuna/{ENV_NAME}.log"
    assert argv[argv.index("--study-name") + 1] == f"sac_{ENV_NAME}"
    assert argv[-2:] == ["--gym-packages", "vafn_gym"]
    user = complete_argv(["--algo", "sac", "--num-threads", "2", "--storage", "x.db", "--gym-packages", "vafn_gym"])
    assert user.count("--num-threads") == 1 and user.count("--storage") == 1 and user.count("--gym-packages") == 1


@pytest.mark.parametrize("algo", ALL_ALGOS)
def test_train_every_algorithm_from_its_yaml(algo: str, tmp_path: Path) -> None:
    register_algorithms()
    if algo in UNAVAILABLE:
        pytest.fail(f"{algo} is not available: {UNAVAILABLE[algo]}")
    train_main([
        "--algo", algo, "--env", ENV_ID, "-n", "300", "-f", str(tmp_path), "--seed", "0", "--eval-freq", "300",
        "--eval-episodes", "1", "-params", *fast_params(algo), "--env-kwargs", *FAST_ENV_KWARGS,
    ])
    run = tmp_path / algo / f"{ENV_NAME}_1"
    assert (run / f"{ENV_NAME}.zip").is_file()
    evaluations = np.load(run / "evaluations.npz")
    assert {"successes", "collisions"} <= set(evaluations.files), evaluations.files
    assert evaluations["collisions"].shape == evaluations["successes"].shape == (1, 1)
    assert (run / "0.monitor.csv").read_text().splitlines()[1].split(",")[-2:] == ["is_success", "collided"]


def test_yaml_env_kwargs_configure_the_training_env_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from vafn_gym.envs import MultiArmEnv

    register_algorithms()
    built = []
    original = MultiArmEnv.__init__

    def recording_init(self, *args, **kwargs):
        original(self, *args, **kwargs)
        built.append((self.task.success_tolerance, self.sampler.max_length))

    monkeypatch.setattr(MultiArmEnv, "__init__", recording_init)
    train_main([
        "--algo", "sac", "--env", ENV_ID, "-n", "200", "-f", str(tmp_path), "--seed", "0", "--eval-freq", "200",
        "--eval-episodes", "1", "-params", *fast_params("sac"), "--env-kwargs", *FAST_ENV_KWARGS,
    ])
    yaml_tolerance = yaml.safe_load((REPO_ROOT / "hyperparams" / "sac.yml").read_text())[ENV_ID]["env_kwargs"]
    assert yaml_tolerance["success_tolerance"] < SUCCESS_TOLERANCE
    # the training env: the YAML's tolerance and the command line's max_length; the evaluation env: the command line's
    assert set(built) == {(yaml_tolerance["success_tolerance"], 1), (SUCCESS_TOLERANCE, 1)}
    saved = load_run_config(tmp_path / "sac" / f"{ENV_NAME}_1" / ENV_NAME / "config.yml")
    assert saved["env_kwargs"] == {**yaml_tolerance, "max_length": 1}


def test_sampled_policy_kwargs_merge_with_the_yaml() -> None:
    register_algorithms()
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_SAMPLER
    from torch import nn

    sampler = _merge_policy_kwargs(HYPERPARAMS_SAMPLER["sac"])
    trial = optuna.trial.FixedTrial({
        "learning_rate": 1e-3, "one_minus_gamma": 0.02, "batch_size": 64, "tau": 0.01, "net_arch": "small",
        "learning_starts": 100,
    })
    _yaml_policy_kwargs.set({"activation_fn": nn.ReLU, "net_arch": [400, 300]})
    params = sampler(trial, 9, 1, {})
    assert params["policy_kwargs"] == {"activation_fn": nn.ReLU, "net_arch": [64, 64]}
    assert params["gamma"] == pytest.approx(0.98)


def test_optimize_two_trials_then_reuse_a_trial_with_merged_policy_kwargs(tmp_path: Path) -> None:
    storage = tmp_path / "study.log"
    conf = tmp_path / "sac.yml"
    conf.write_text(
        f"{ENV_ID}:\n  n_timesteps: 200\n  policy: MlpPolicy\n  learning_starts: 50\n"
        "  policy_kwargs: \"dict(net_arch=[256, 256], log_std_init=-2.5)\"\n"
    )
    common = ["--algo", "sac", "--env", ENV_ID, "-f", str(tmp_path), "-conf", str(conf),
              "--env-kwargs", *FAST_ENV_KWARGS]
    train_main([*common, "-optimize", "--n-trials", "2", "-n", "150", "--n-evaluations", "1", "--eval-episodes", "1",
                "--storage", str(storage), "--study-name", "s", "--sampler", "random", "--pruner", "none",
                "--seed", "3", "--no-optim-plots"])
    study = optuna.load_study(study_name="s", storage=open_storage(str(storage)))
    assert [t.state for t in study.trials] == [TrialState.COMPLETE] * 2
    # rl_zoo3 ignores `--trial-id 0` (it tests the id for truthiness), so reuse trial 1.
    trained_arch = [64, 64] if study.trials[1].params["net_arch"] == "small" else [256, 256]

    train_main([*common, "-n", "100", "--eval-freq", "-1", "--storage", str(storage), "--study-name", "s",
                "--trial-id", "1", "--seed", "0"])
    from stable_baselines3 import SAC

    model = SAC.load(tmp_path / "sac" / f"{ENV_NAME}_2" / f"{ENV_NAME}.zip")
    assert model.policy_kwargs["log_std_init"] == -2.5, "the YAML's policy_kwargs were replaced by the trial's"
    assert model.policy_kwargs["net_arch"] == trained_arch
    assert model.lr_schedule(1.0) == pytest.approx(study.trials[1].params["learning_rate"])


def test_two_concurrent_workers_share_one_journal_study(tmp_path: Path) -> None:
    command = [
        PYTHON, str(REPO_ROOT / "zoo" / "train.py"), "--algo", "sac", "--env", ENV_ID, "-optimize", "--n-trials", "1",
        "-n", "120", "--n-evaluations", "1", "--eval-episodes", "1", "-f", str(tmp_path), "--sampler", "random",
        "--pruner", "none", "--no-optim-plots", "-params", "learning_starts:50", "batch_size:32",
        "--env-kwargs", *FAST_ENV_KWARGS,
    ]
    workers = [
        subprocess.Popen([*command, "--seed", str(seed)], cwd=tmp_path, env=SUBPROCESS_ENV,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for seed in (1, 2)
    ]
    outputs = [worker.communicate(timeout=240)[0] for worker in workers]
    for worker, output in zip(workers, outputs):
        assert worker.returncode == 0, output[-3000:]
    storage = tmp_path / "sac" / "optuna" / f"{ENV_NAME}.log"
    study = optuna.load_study(study_name=f"sac_{ENV_NAME}", storage=open_storage(str(storage)))
    assert [t.state for t in study.trials] == [TrialState.COMPLETE] * 2
    assert len({t.user_attrs[WORKER_ATTR] for t in study.trials}) == 2, "both trials ran in the same worker"


def test_a_killed_workers_trial_is_failed_and_requeued(tmp_path: Path) -> None:
    storage = str(tmp_path / "study.log")
    study = optuna.create_study(study_name="s", storage=open_storage(storage), direction="maximize")
    done = study.ask({"x": optuna.distributions.FloatDistribution(0, 1)})
    study.tell(done, 1.0)
    orphan = study.ask({"x": optuna.distributions.FloatDistribution(0, 1)})
    dead = subprocess.Popen(["true"])
    dead.wait()
    import socket

    orphan.set_user_attr(WORKER_ATTR, f"{socket.gethostname()}:{dead.pid}")
    alive = study.ask({"x": optuna.distributions.FloatDistribution(0, 1)})
    alive.set_user_attr(WORKER_ATTR, f"{socket.gethostname()}:{os.getpid()}")

    assert recover_stale_trials(storage, "s") == [orphan.number]
    states = {t.number: t.state for t in optuna.load_study(study_name="s", storage=open_storage(storage)).trials}
    assert states[orphan.number] == TrialState.FAIL
    assert states[alive.number] == TrialState.RUNNING
    requeued = [t for t in study.get_trials() if t.state == TrialState.WAITING]
    assert len(requeued) == 1 and requeued[0].system_attrs["fixed_params"] == orphan.params
    assert recover_stale_trials(storage, "missing-study") == []


def _write_runs(root: Path, algo: str, seeds: int, offset: float) -> None:
    from torch.utils.tensorboard import SummaryWriter

    for seed in range(seeds):
        writer = SummaryWriter(str(root / f"{algo}_{seed + 1}"))
        for step in range(0, 1001, 100):
            writer.add_scalar("eval/mean_reward", offset + seed + step / 1000, step)
            writer.add_scalar("eval/success_rate", min(1.0, step / 1000), step)
            writer.add_scalar("rollout/collision_rate", 0.1 * seed, step)
        writer.close()


def test_plot_synthetic_event_files(tmp_path: Path) -> None:
    _write_runs(tmp_path / "tb", "SAC", seeds=3, offset=0.0)
    _write_runs(tmp_path / "tb", "MAMLSAC", seeds=2, offset=5.0)
    written = zoo_plot.main(["--tb", str(tmp_path / "tb"), "--out", str(tmp_path / "out" / "cmp")])
    names = sorted(p.name for p in written)
    assert names == ["cmp_collision.png", "cmp_curves.csv", "cmp_return.png", "cmp_success.png"]
    for path in written:
        assert path.stat().st_size > 1000
    rows = [line.split(",") for line in (tmp_path / "out" / "cmp_curves.csv").read_text().splitlines()[1:]]
    first_sac = next(r for r in rows if r[0] == "return" and r[1] == "SAC")
    # seeds 0, 1, 2 at step 0: mean 1, t(0.975, 2) * std 1 / sqrt(3) = 2.484
    assert float(first_sac[3]) == pytest.approx(1.0)
    assert float(first_sac[5]) - float(first_sac[3]) == pytest.approx(2.484, abs=1e-3)
    assert {r[6] for r in rows if r[1] == "MAMLSAC"} == {"2"}


def test_plot_without_evaluations_explains_eval_freq(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "logs" / "sac" / "VAFN-ThreeArmReach-v1_1").mkdir(parents=True)
    with pytest.raises(SystemExit) as exit_info:
        zoo_plot.main(["--logs", str(tmp_path / "logs"), "--out", str(tmp_path / "out/")])
    assert exit_info.value.code == 1
    message = capsys.readouterr().err
    assert "no evaluations yet" in message and "--eval-freq larger than -n" in message
    assert "VAFN-ThreeArmReach-v1_1" in message and "Traceback" not in message


def test_plot_keeps_few_evaluations_as_points_and_names_the_env(tmp_path: Path) -> None:
    run = tmp_path / "logs" / "sac" / "VAFN-ThreeArmReach-v1_1"
    run.mkdir(parents=True)
    np.savez(run / "evaluations.npz", timesteps=np.array([100, 200, 300]), results=np.ones((3, 2)),
             successes=np.zeros((3, 2)), collisions=np.zeros((3, 2)))
    written = zoo_plot.main(["--logs", str(tmp_path / "logs"), "--out", str(tmp_path / "out") + "/"])
    assert {p.name for p in written} >= {"training_return.png", "training_curves.csv"}
    rows = [r for r in (tmp_path / "out" / "training_curves.csv").read_text().splitlines()[1:] if r.startswith("ret")]
    assert [float(r.split(",")[2]) for r in rows] == [100.0, 200.0, 300.0], "3 evaluations stay 3 points"
    assert zoo_plot.env_names([], tmp_path / "logs") == ["VAFN-ThreeArmReach-v1"]


def test_enjoy_records_a_gif_of_the_scripted_controller(tmp_path: Path) -> None:
    from zoo import enjoy

    episodes = enjoy.main(["--scripted", "--instruction", "1", "--frame-skip", "5", "--record",
                           str(tmp_path / "a.gif"), "--env-kwargs", "render_width:160", "render_height:120"])
    assert len(episodes) == 1 and episodes[0]["success"] == 1.0, "one episode per instruction by default"
    assert (tmp_path / "a.gif").stat().st_size > 5_000


def test_meta_eval_callback_logs_post_adaptation_performance(tmp_path: Path) -> None:
    import gymnasium as gym
    from stable_baselines3.common.logger import configure

    import vafn_gym  # noqa: F401
    from vafn_sb3 import MTSAC
    from vafn_sb3.callbacks import MetaEvalCallback

    env = gym.make("VAFN/ThreeArmReachHidden-v1", max_length=1)
    model = MTSAC("MlpPolicy", env, learning_starts=50, batch_size=32, policy_kwargs={"net_arch": [32, 32]}, seed=0)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    callback = MetaEvalCallback(eval_freq=60, k_values=(0, 2), n_tasks=1, n_support=16, max_length=1, seed=0)
    model.learn(60, callback=callback)
    assert [row["k"] for row in callback.rows] == [0, 2]
    assert {row["timesteps"] for row in callback.rows} == {60}
    assert callback.tasks[0].to_code() and len(callback.tasks) == 1
    lines = (tmp_path / "meta_evaluations.csv").read_text().splitlines()
    assert lines[0] == "timesteps,k,return,success,collision" and len(lines) == 3
    logged = (tmp_path / "progress.csv").read_text().splitlines()[0].split(",")
    assert {"meta/return_k0", "meta/success_k2", "meta/collision_k2"} <= set(logged)
    with pytest.raises(ValueError, match="k_values"):
        MetaEvalCallback(k_values=(-1,))


@pytest.mark.parametrize("algo", ALL_ALGOS)
def test_every_sampler_builds_a_valid_model_and_its_converter_agrees(algo: str) -> None:
    import gymnasium as gym
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
    from rl_zoo3.utils import ALGOS

    register_algorithms()
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    env = gym.make(ENV_ID, max_length=1)
    for _ in range(3):
        trial = study.ask()
        sampled = HYPERPARAMS_SAMPLER[algo](trial, 9, 1, {"using_her_replay_buffer": False, "her_kwargs": {}})
        assert HYPERPARAMS_CONVERTER[algo](trial.params) == sampled, "--trial-id would not rebuild the trial's values"
        model = ALGOS[algo]("MlpPolicy", env, **sampled)
        assert model.gamma == pytest.approx(sampled["gamma"])
        study.tell(trial, 0.0)
    env.close()
