"""Recovery of trials left RUNNING by dead tuning workers: worker identity, untagged trials, races, heartbeats."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import optuna
import pytest
from optuna.distributions import FloatDistribution
from optuna.trial import TrialState

from optuna.storages._heartbeat import is_heartbeat_enabled

from zoo.experiment import VAFNExperimentManager
from zoo.tuning import RETRY_OF_ATTR, WORKER_ATTR, WorkerTag, open_storage, recover_stale_trials, worker_id

REPO_ROOT = Path(__file__).resolve().parents[1]
SPACE = {"x": FloatDistribution(0, 1)}
HOST = socket.gethostname()

optuna.logging.set_verbosity(optuna.logging.WARNING)
pytestmark = pytest.mark.filterwarnings("ignore:Heartbeat of storage is supposed to be used with Study.optimize")


@pytest.fixture(params=["journal", "sqlite"])
def storage(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    return str(tmp_path / "study.log") if request.param == "journal" else f"sqlite:///{tmp_path / 'study.db'}"


@pytest.fixture
def journal(tmp_path: Path) -> str:
    return str(tmp_path / "study.log")


@pytest.fixture
def unrelated_process() -> Iterator[subprocess.Popen]:
    process = subprocess.Popen(["sleep", "60"])
    yield process
    process.kill()
    process.wait()


def _study(storage: str) -> optuna.Study:
    return optuna.create_study(study_name="s", storage=open_storage(storage), direction="maximize", load_if_exists=True)


def _running_trial(study: optuna.Study, tag: str | None) -> optuna.Trial:
    trial = study.ask(SPACE)
    if tag is not None:
        trial.set_user_attr(WORKER_ATTR, tag)
    return trial


def _states(storage: str) -> dict[int, TrialState]:
    return {t.number: t.state for t in _study(storage).trials}


def _retries(storage: str) -> list[optuna.trial.FrozenTrial]:
    return [t for t in _study(storage).trials if t.state == TrialState.WAITING]


def test_worker_id_names_host_pid_and_process_start() -> None:
    tag = WorkerTag.parse(worker_id())
    assert tag is not None and (tag.host, tag.pid) == (HOST, os.getpid())
    assert tag.start, "no process start time in the worker tag"
    assert WorkerTag.parse(f"{HOST}:123") == WorkerTag(HOST, 123)
    assert WorkerTag.parse("not a tag") is None


def test_a_pid_reused_by_an_unrelated_process_is_recovered(journal: str, unrelated_process: subprocess.Popen) -> None:
    study = _study(journal)
    orphan = _running_trial(study, f"{HOST}:{unrelated_process.pid}:boot-1:deadbeef")
    assert recover_stale_trials(journal, "s") == [orphan.number]
    assert _states(journal)[orphan.number] == TrialState.FAIL


def test_an_old_style_tag_whose_pid_was_reused_after_the_trial_started_is_recovered(journal: str) -> None:
    study = _study(journal)
    orphan = _running_trial(study, None)
    time.sleep(0.7)  # the pid's new owner starts clearly after the trial did
    process = subprocess.Popen(["sleep", "60"])
    try:
        orphan.set_user_attr(WORKER_ATTR, f"{HOST}:{process.pid}")
        assert recover_stale_trials(journal, "s") == [orphan.number]
    finally:
        process.kill()
        process.wait()


def test_a_trial_of_a_previous_process_with_our_pid_is_recovered_but_ours_is_not(journal: str) -> None:
    study = _study(journal)
    previous = _running_trial(study, f"{HOST}:{os.getpid()}:boot-1:deadbeef")
    ours = _running_trial(study, worker_id())
    ours_old_style = _running_trial(study, f"{HOST}:{os.getpid()}")  # started after this process did: still ours
    assert recover_stale_trials(journal, "s") == [previous.number]
    states = _states(journal)
    assert states[ours.number] == states[ours_old_style.number] == TrialState.RUNNING


def test_a_dead_workers_trial_is_recovered_and_live_or_foreign_ones_are_kept(journal: str) -> None:
    study = _study(journal)
    dead = subprocess.Popen(["true"])
    dead.wait()
    orphan = _running_trial(study, f"{HOST}:{dead.pid}:boot-1:deadbeef")
    foreign = _running_trial(study, f"another-host:{dead.pid}:boot-1:deadbeef")
    ours = _running_trial(study, worker_id())
    assert recover_stale_trials(journal, "s") == [orphan.number]
    states = _states(journal)
    assert states[foreign.number] == states[ours.number] == TrialState.RUNNING
    retries = _retries(journal)
    assert len(retries) == 1 and retries[0].user_attrs == {RETRY_OF_ATTR: orphan.number}
    assert retries[0].system_attrs["fixed_params"] == orphan.params
    assert recover_stale_trials(journal, "s") == [], "recovery is not idempotent"
    assert recover_stale_trials(journal, "missing-study") == []


def test_an_untagged_trial_is_recovered_after_the_grace_period(journal: str) -> None:
    study = _study(journal)
    untagged = _running_trial(study, None)
    assert recover_stale_trials(journal, "s") == [], "a just-started trial has not had time to be tagged"
    time.sleep(0.05)
    assert recover_stale_trials(journal, "s", untagged_grace_s=0.01) == [untagged.number]


def test_concurrent_recovery_recovers_each_trial_once(storage: str, monkeypatch: pytest.MonkeyPatch) -> None:
    study = _study(storage)
    orphan = _running_trial(study, f"{HOST}:{os.getpid()}:boot-1:deadbeef")
    snapshot = study.get_trials(states=(TrialState.RUNNING,))
    assert recover_stale_trials(storage, "s") == [orphan.number]
    # A second worker listed the trial as RUNNING just before the first one failed it.
    monkeypatch.setattr(optuna.Study, "get_trials", lambda self, *args, **kwargs: snapshot)
    assert recover_stale_trials(storage, "s") == []
    monkeypatch.undo()
    assert len(_retries(storage)) == 1


def test_a_killed_worker_process_is_recovered(journal: str) -> None:
    _study(journal)
    code = (
        "import sys, time, optuna; from zoo.tuning import WORKER_ATTR, open_storage, worker_id; "
        f"study = optuna.load_study(study_name='s', storage=open_storage({journal!r})); "
        "trial = study.ask({'x': optuna.distributions.FloatDistribution(0, 1)}); "
        "trial.set_user_attr(WORKER_ATTR, worker_id()); print(trial.number, flush=True); time.sleep(60)"
    )
    worker = subprocess.Popen([sys.executable, "-c", code], cwd=REPO_ROOT, stdout=subprocess.PIPE, text=True)
    try:
        number = int(worker.stdout.readline())
        assert recover_stale_trials(journal, "s") == [], "a live worker's trial was recovered"
    finally:
        worker.send_signal(signal.SIGKILL)
        worker.wait()
    assert recover_stale_trials(journal, "s") == [number]


def test_rdb_storages_fail_and_retry_trials_whose_heartbeat_stopped(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'study.db'}"
    storage = open_storage(url, heartbeat_interval=1, grace_period=1)
    study = optuna.create_study(study_name="s", storage=storage, direction="maximize")
    stale = study.ask(SPACE)  # e.g. a worker on another host that lost power
    stale.set_user_attr(WORKER_ATTR, "another-host:12:boot-1:deadbeef")
    stale.set_user_attr("note", "kept")
    storage.record_heartbeat(stale._trial_id)
    time.sleep(2.1)  # sqlite's clock has whole seconds
    study.optimize(lambda trial: trial.suggest_float("x", 0, 1), n_trials=1)
    trials = study.get_trials()
    assert trials[stale.number].state == TrialState.FAIL
    retry = trials[-1]
    assert retry.state == TrialState.COMPLETE and retry.params == stale.params
    assert retry.system_attrs["failed_trial"] == stale.number
    # Marked like a local recovery, and without the dead worker's tag (it would look stale while being picked up).
    assert retry.user_attrs == {"note": "kept", RETRY_OF_ATTR: stale.number}


def test_recovery_at_start_up_fails_heartbeat_stale_trials_of_any_host(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'study.db'}"
    storage = open_storage(url, heartbeat_interval=1, grace_period=1)
    study = optuna.create_study(study_name="s", storage=storage, direction="maximize")
    foreign = _running_trial(study, "another-host:12:boot-1:deadbeef")  # never judged by the local pid check
    storage.record_heartbeat(foreign._trial_id)
    live = _running_trial(study, "another-host:13:boot-1:deadbeef")
    time.sleep(2.1)
    storage.record_heartbeat(live._trial_id)
    assert recover_stale_trials(storage, "s") == [foreign.number]
    assert recover_stale_trials(storage, "s") == [], "recovery is not idempotent"
    trials = study.get_trials()
    assert [t.state for t in trials] == [TrialState.FAIL, TrialState.RUNNING, TrialState.WAITING]
    assert trials[-1].user_attrs == {RETRY_OF_ATTR: foreign.number}


@pytest.mark.parametrize("kind", ["sqlite", "journal"])
def test_the_zoo_optimisation_loop_runs_on_the_heartbeat_storage(
    kind: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from zoo.train import main as train_main

    seen: list[tuple[bool, int | None]] = []

    def objective(self: VAFNExperimentManager, trial: optuna.Trial) -> float:
        storage = trial.study._storage
        seen.append((is_heartbeat_enabled(storage), getattr(storage, "get_heartbeat_interval", lambda: None)()))
        return trial.suggest_float("x", 0, 1)

    monkeypatch.setattr(VAFNExperimentManager, "objective", objective)
    storage = f"sqlite:///{tmp_path / 'study.db'}" if kind == "sqlite" else str(tmp_path / "study.log")
    train_main(["--algo", "sac", "--env", "VAFN/ThreeArmReach-v1", "-optimize", "--n-trials", "2", "-n", "100",
                "-f", str(tmp_path), "--storage", storage, "--study-name", "s", "--heartbeat-interval", "7",
                "--no-optim-plots", "--sampler", "random"])
    assert seen == ([(True, 7)] * 2 if kind == "sqlite" else [(False, None)] * 2)


def test_journal_storages_have_no_heartbeat(journal: str) -> None:
    assert isinstance(open_storage(journal), optuna.storages.JournalStorage)
    url = f"sqlite:///{Path(journal).with_suffix('.db')}"
    assert open_storage(url, heartbeat_interval=None).heartbeat_interval is None
    assert open_storage(url).heartbeat_interval is not None, "RDB storages get heartbeats by default"
