"""Distributed tuning on a real PostgreSQL server: two ``zoo/train.py -optimize`` workers, one killed and restarted.

Runs only where ``VAFN_TEST_POSTGRES_URL`` names a server (``.ci/run`` starts one on loopback), e.g.
``VAFN_TEST_POSTGRES_URL=postgresql+psycopg2://vafn:vafn@127.0.0.1/vafn_test``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import optuna
import pytest
from optuna.trial import TrialState

from zoo.tuning import RETRY_OF_ATTR, WORKER_ATTR, WorkerTag, open_storage

REPO_ROOT = Path(__file__).resolve().parents[1]
POSTGRES_URL = os.environ.get("VAFN_TEST_POSTGRES_URL")
ENV_ID = "VAFN/ThreeArmReach-v1"
TRIALS_PER_WORKER = 2
#: The killed worker completes nothing; its restart and the survivor run TRIALS_PER_WORKER each.
TOTAL_TRIALS = 2 * TRIALS_PER_WORKER
HEARTBEAT_INTERVAL_S = 1
HEARTBEAT_GRACE_S = 4
SUBPROCESS_ENV = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

pytestmark = [
    pytest.mark.skipif(
        not POSTGRES_URL, reason="VAFN_TEST_POSTGRES_URL is unset: no PostgreSQL server to tune on (.ci/run starts one)"
    ),
    pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning"),
]


def _worker(study_name: str, folder: Path, seed: int) -> subprocess.Popen:
    command = [
        sys.executable, str(REPO_ROOT / "zoo" / "train.py"), "--algo", "sac", "--env", ENV_ID, "-optimize",
        "--n-trials", str(TRIALS_PER_WORKER), "-n", "200", "--n-evaluations", "1", "--eval-episodes", "1",
        "-f", str(folder), "--sampler", "random", "--pruner", "none", "--no-optim-plots", "--seed", str(seed),
        "--storage", POSTGRES_URL, "--study-name", study_name, "--heartbeat-interval", str(HEARTBEAT_INTERVAL_S),
        "--heartbeat-grace", str(HEARTBEAT_GRACE_S), "-params", "batch_size:32", "--env-kwargs", "max_length:1",
    ]  # fmt: skip
    log = open(folder / f"worker_{seed}.txt", "w")  # noqa: SIM115 (closed with the process, read on failure)
    return subprocess.Popen(command, cwd=folder, env=SUBPROCESS_ENV, stdout=log, stderr=subprocess.STDOUT)


def _training_trial_of(study: optuna.Study, pid: int) -> optuna.trial.FrozenTrial | None:
    """The RUNNING trial of worker ``pid`` once all its parameters are sampled (it is building or training SAC)."""
    for trial in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        tag = WorkerTag.parse(str(trial.user_attrs.get(WORKER_ATTR, "")))
        if tag is not None and tag.pid == pid and "learning_starts" in trial.params:  # the sampler's last parameter
            return trial
    return None


def _wait(process: subprocess.Popen, folder: Path, seed: int, timeout: float) -> None:
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
    log = (folder / f"worker_{seed}.txt").read_text()
    assert process.returncode == 0, f"worker {seed} exited with {process.returncode}:\n{log[-3000:]}"


def test_two_workers_one_killed_and_restarted_complete_the_study_without_loss(tmp_path: Path) -> None:
    study_name = f"vafn-test-{uuid.uuid4().hex[:12]}"
    storage = open_storage(POSTGRES_URL, heartbeat_interval=None)
    study = optuna.create_study(study_name=study_name, storage=storage, direction="maximize")
    workers: list[subprocess.Popen] = []
    try:
        workers = [_worker(study_name, tmp_path, seed) for seed in (1, 2)]
        killed, survivor = workers
        deadline = time.monotonic() + 120
        victim = survivor_trial = None
        # Both workers mid-trial before the kill: a survivor still starting up would recover the dead worker's trial
        # by its local pid check before the heartbeat goes stale (seen under load), and this test is about heartbeats.
        while victim is None or survivor_trial is None:
            assert time.monotonic() < deadline, "a worker never started a trial"
            for number, worker in ((1, killed), (2, survivor)):
                assert worker.poll() is None, (
                    f"worker {number} exited early:\n{(tmp_path / f'worker_{number}.txt').read_text()[-3000:]}"
                )
            victim = _training_trial_of(study, killed.pid)
            survivor_trial = _training_trial_of(study, survivor.pid)
            time.sleep(0.1)
        killed.send_signal(signal.SIGKILL)  # mid-trial: sampled, heartbeat running, model not yet evaluated
        killed.wait()
        # Restart only once the heartbeat is stale, so the heartbeat (not the local pid check) recovers the trial.
        time.sleep(HEARTBEAT_GRACE_S + 1.5)
        restarted = _worker(study_name, tmp_path, 3)
        workers.append(restarted)
        _wait(survivor, tmp_path, 2, timeout=180)
        _wait(restarted, tmp_path, 3, timeout=180)

        trials = optuna.load_study(study_name=study_name, storage=storage).get_trials()
        states = [t.state for t in trials]
        complete = [t for t in trials if t.state == TrialState.COMPLETE]
        assert len(complete) == TOTAL_TRIALS, f"states {states}"
        assert states.count(TrialState.FAIL) == 1 and trials[victim.number].state == TrialState.FAIL, f"states {states}"
        assert len(trials) == TOTAL_TRIALS + 1, f"lost or extra trials: {states}"
        retries = [t for t in trials if t.user_attrs.get(RETRY_OF_ATTR) == victim.number]
        assert len(retries) == 1, f"the killed trial was retried {len(retries)} times"
        retry = retries[0]
        assert retry.state == TrialState.COMPLETE and retry.params == trials[victim.number].params == victim.params
        assert retry.system_attrs.get("failed_trial") == victim.number, "not recovered by Optuna's heartbeat"
        params = [tuple(sorted(t.params.items())) for t in complete]
        assert len(set(params)) == TOTAL_TRIALS, "a trial ran twice"
        tags = {WorkerTag.parse(t.user_attrs[WORKER_ATTR]).pid for t in complete}
        assert killed.pid not in tags and tags <= {survivor.pid, restarted.pid}
    finally:
        for worker in workers:
            if worker.poll() is None:
                worker.kill()
                worker.wait()
        optuna.delete_study(study_name=study_name, storage=storage)
