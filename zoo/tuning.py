"""Optuna search spaces for every vafn algorithm, in rl_zoo3's sampler/converter format.

A *sampler* ``(trial, n_actions, n_envs, additional_args) -> hyperparams`` suggests raw values and converts them; the
matching *converter* turns the stored ``trial.params`` back into hyperparams (``--trial-id``). Ranges are narrower than
the zoo's generic ones: they cover what is sensible for the 15-D / 9-D three-arm task on a small CPU budget.

Sampled ``policy_kwargs`` are *merged into* the YAML's ``policy_kwargs`` by :mod:`zoo.experiment` (the zoo replaces
them), so a YAML ``activation_fn`` or custom policy argument survives tuning.

Studies resume across worker restarts: each trial is tagged with its worker (host, pid and process start), and
:func:`recover_stale_trials` fails and re-queues the RUNNING trials whose worker is gone; RDB storages opened by
:func:`open_storage` also use Optuna's heartbeats, which cover workers on other hosts. A rerun's sampler is seeded with
:func:`resumed_sampler_seed`, so it continues the study with new parameters.
"""

from __future__ import annotations

import copy
import inspect
import os
import socket
import time
import uuid
import warnings
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from collections.abc import Callable
from typing import Any

import numpy as np
import optuna
from optuna.exceptions import UpdateFinishedTrialError
from optuna.storages._heartbeat import is_heartbeat_enabled
from optuna.trial import TrialState
from torch import nn

Sampler = Callable[[optuna.Trial, int, int, dict], dict[str, Any]]

#: Named network sizes a trial can pick (shared by actor and critic).
NET_ARCHS: dict[str, Any] = {"small": [64, 64], "medium": [256, 256], "large": [400, 300]}
#: MAAC's attention critic takes a single hidden width (``qf=[w]``), so it has its own table.
MAAC_NET_ARCHS: dict[str, Any] = {
    "small": {"pi": [64, 64], "qf": [64]},
    "medium": {"pi": [128, 128], "qf": [128]},
    "large": {"pi": [256, 256], "qf": [256]},
}
NET_ARCHS_BY_ALGO: dict[str, dict[str, Any]] = {"maac": MAAC_NET_ARCHS}
ACTIVATIONS: dict[str, type[nn.Module]] = {"tanh": nn.Tanh, "relu": nn.ReLU}

#: Algorithm-specific constructor arguments tuned when the class accepts them: name -> (kind, low/choices, high, log).
#: The class signature decides, so a renamed argument is simply not tuned instead of crashing every trial.
EXTRA_SPACES: dict[str, dict[str, tuple]] = {
    "maml_sac": {
        "inner_actor_lr": ("float", 1e-3, 1e-1, True),
        "inner_critic_lr": ("float", 1e-3, 5e-2, True),
        "inner_steps": ("int", 1, 3, False),
        "meta_batch_size": ("categorical", [3, 5]),
        "n_support": ("categorical", [100, 200]),
    },
    "maddpg": {"exploration_std": ("float", 0.05, 0.4, False)},
    "maac": {"attention_reg": ("float", 1e-4, 1e-2, True)},
}


def _constructor_parameters(algo_class: type | None) -> set[str]:
    if algo_class is None:
        return set()
    return set(inspect.signature(algo_class.__init__).parameters)


def _suggest_extras(trial: optuna.Trial, algo: str, algo_class: type | None) -> dict[str, Any]:
    accepted = _constructor_parameters(algo_class)
    params: dict[str, Any] = {}
    for name, space in EXTRA_SPACES.get(algo, {}).items():
        if name not in accepted:
            continue
        kind = space[0]
        if kind == "float":
            params[name] = trial.suggest_float(name, space[1], space[2], log=space[3])
        elif kind == "int":
            params[name] = trial.suggest_int(name, space[1], space[2], log=space[3])
        else:
            params[name] = trial.suggest_categorical(name, space[1])
    return params


def convert_params(params: dict[str, Any], net_archs: dict[str, Any] | None = None) -> dict[str, Any]:
    """Stored trial params -> constructor hyperparams (``one_minus_*`` -> value, ``net_arch`` name -> policy_kwargs).

    :param params: the trial's parameters as stored by Optuna.
    :param net_archs: the algorithm's table of named network sizes (default :data:`NET_ARCHS`).
    """
    hyperparams = dict(params)
    for name in ("gamma", "gae_lambda"):
        if f"one_minus_{name}" in hyperparams:
            hyperparams[name] = 1.0 - hyperparams.pop(f"one_minus_{name}")
    policy_kwargs: dict[str, Any] = {}
    if "net_arch" in hyperparams:
        policy_kwargs["net_arch"] = (net_archs or NET_ARCHS)[hyperparams.pop("net_arch")]
    if "activation_fn" in hyperparams:
        policy_kwargs["activation_fn"] = ACTIVATIONS[hyperparams.pop("activation_fn")]
    if policy_kwargs:
        hyperparams["policy_kwargs"] = policy_kwargs
    return hyperparams


def _suggest_off_policy(trial: optuna.Trial) -> dict[str, Any]:
    return {
        "learning_rate": trial.suggest_float("learning_rate", 1e-4, 3e-3, log=True),
        "one_minus_gamma": trial.suggest_float("one_minus_gamma", 0.002, 0.05, log=True),
        "batch_size": trial.suggest_categorical("batch_size", [64, 128, 256]),
        "tau": trial.suggest_float("tau", 0.002, 0.05, log=True),
        "net_arch": trial.suggest_categorical("net_arch", ["small", "medium"]),
    }


def make_converter(algo: str) -> Callable[[dict[str, Any]], dict[str, Any]]:
    """The ``--trial-id`` converter of ``algo`` (its own network-size table)."""

    def convert(params: dict[str, Any]) -> dict[str, Any]:
        return convert_params(params, NET_ARCHS_BY_ALGO.get(algo))

    return convert


def make_off_policy_sampler(algo: str, algo_class: type | None) -> Sampler:
    """Sampler for SAC and TD3 subclasses (sac, maml_sac, mtsac, maac, maddpg): common space + the algo's extras."""
    convert = make_converter(algo)

    def sample(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
        params = _suggest_off_policy(trial)
        params["learning_starts"] = trial.suggest_categorical("learning_starts", [100, 500, 1000])
        params.update(_suggest_extras(trial, algo, algo_class))
        return convert(params)

    return sample


def make_ppo_sampler(algo: str, algo_class: type | None) -> Sampler:
    """Sampler for PPO subclasses (mappo)."""
    convert = make_converter(algo)

    def sample(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
        params = {
            "learning_rate": trial.suggest_float("learning_rate", 5e-5, 3e-3, log=True),
            "one_minus_gamma": trial.suggest_float("one_minus_gamma", 0.002, 0.05, log=True),
            "one_minus_gae_lambda": trial.suggest_float("one_minus_gae_lambda", 0.01, 0.1, log=True),
            "n_steps": trial.suggest_categorical("n_steps", [256, 512, 1024, 2048]),
            "batch_size": trial.suggest_categorical("batch_size", [64, 128, 256]),
            "n_epochs": trial.suggest_categorical("n_epochs", [5, 10, 20]),
            "ent_coef": trial.suggest_float("ent_coef", 1e-8, 1e-2, log=True),
            "clip_range": trial.suggest_categorical("clip_range", [0.1, 0.2, 0.3]),
            "net_arch": trial.suggest_categorical("net_arch", ["small", "medium"]),
            "activation_fn": trial.suggest_categorical("activation_fn", ["tanh", "relu"]),
        }
        params.update(_suggest_extras(trial, algo, algo_class))
        return convert(params)

    return sample


# --- resumable studies: storages, worker identity, recovery of trials left RUNNING by dead workers ---

#: Trial user attribute naming the worker process that runs it (see :func:`worker_id`).
WORKER_ATTR = "worker"
#: Trial user attribute of a re-queued trial: the number of the stale trial it retries.
RETRY_OF_ATTR = "retry_of"
#: Heartbeat period (s) of RDB storages; Optuna fails a RUNNING trial after ``grace_period`` without a heartbeat.
HEARTBEAT_INTERVAL_S = 60
#: An untagged RUNNING trial older than this (s) is orphaned: every vafn worker tags its trial as soon as it starts.
UNTAGGED_GRACE_S = 60.0
#: A process that started this long (s) after a trial cannot be the worker that runs it (clock granularity margin).
_START_MARGIN_S = 0.5
_NONCE = uuid.uuid4().hex[:8]


@dataclass(frozen=True)
class WorkerTag:
    """A parsed worker tag: ``host:pid:start:nonce`` (``start``/``nonce`` are None in the older ``host:pid`` form)."""

    host: str
    pid: int
    start: str | None = None
    nonce: str | None = None

    @classmethod
    def parse(cls, tag: str) -> WorkerTag | None:
        """The tag's fields, or None if ``tag`` is not a worker tag."""
        parts = tag.rsplit(":", 3)
        if len(parts) == 4 and parts[0] and parts[1].isdigit():
            return cls(parts[0], int(parts[1]), parts[2] or None, parts[3])
        host, _, pid = tag.rpartition(":")
        return cls(host, int(pid)) if host and pid.isdigit() else None


def _proc_stat_fields(pid: int) -> list[str] | None:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat[stat.rindex(")") + 2 :].split()  # the command name may contain spaces and parentheses


def _boot_id() -> str:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()[:8]
    except OSError:
        return ""


def process_start_token(pid: int) -> str | None:
    """``<boot id>-<start ticks>`` of a live process (fixed for its life, unique per boot); None without /proc."""
    fields = _proc_stat_fields(pid)
    return f"{_boot_id()}-{fields[19]}" if fields else None


def _process_start_time(pid: int) -> float | None:
    """Wall-clock start (epoch seconds) of a live process, None where /proc is absent."""
    fields = _proc_stat_fields(pid)
    if not fields:
        return None
    try:
        uptime = float(Path("/proc/uptime").read_text().split()[0])
    except OSError:
        return None
    return time.time() - uptime + int(fields[19]) / os.sysconf("SC_CLK_TCK")


def worker_id() -> str:
    """``host:pid:start:nonce`` of this process; start token and nonce tell it from a later process with its pid."""
    return f"{socket.gethostname()}:{os.getpid()}:{process_start_token(os.getpid()) or ''}:{_NONCE}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _tagged_owner_alive(owner: WorkerTag, started: datetime | None) -> bool:
    """Whether a local worker (same host) still runs a trial started at ``started``."""
    if not _pid_alive(owner.pid):
        return False
    if owner.start is not None:
        current = process_start_token(owner.pid)
        if current is not None:
            return current == owner.start
    if owner.nonce is not None and owner.pid == os.getpid():
        return False  # a tag with our pid that is not ours was written by an earlier process with this pid
    # Older host:pid tags: a process that started after the trial cannot be the one running it.
    process_start = _process_start_time(owner.pid)
    return process_start is None or started is None or process_start <= started.timestamp() + _START_MARGIN_S


def is_stale(trial: optuna.trial.FrozenTrial, untagged_grace_s: float = UNTAGGED_GRACE_S) -> bool:
    """Whether a RUNNING trial's worker is known to be gone (trials of other hosts are never judged here)."""
    tag = str(trial.user_attrs.get(WORKER_ATTR, ""))
    if not tag:
        started = trial.datetime_start
        return started is not None and (datetime.now() - started).total_seconds() > untagged_grace_s
    owner = WorkerTag.parse(tag)
    if owner is None or owner.host != socket.gethostname() or tag == worker_id():
        return False
    return not _tagged_owner_alive(owner, trial.datetime_start)


def _retry_class() -> type:
    """Optuna's callback that re-queues a heartbeat-stale trial (renamed in Optuna 4.9)."""
    parameters = inspect.signature(optuna.storages.RDBStorage.__init__).parameters
    retry_class = getattr(optuna.storages, "RetryHeartbeatStaleTrialCallback", None)
    if retry_class is None or "heartbeat_stale_trial_callback" not in parameters:
        return optuna.storages.RetryFailedTrialCallback
    return retry_class


class RetryStaleTrial(_retry_class()):  # type: ignore[misc]
    """Optuna's retry of a heartbeat-stale trial, marked like a local recovery and without the dead worker's tag.

    The copy keeps Optuna's ``failed_trial``/``retry_history`` system attributes and gets ``retry_of`` (the stale
    trial's number); the dead worker's tag is dropped so the retry never looks like a trial of a dead worker while
    the next worker is picking it up.
    """

    def __call__(self, study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
        """Re-queue ``trial``'s parameters as a WAITING trial (up to ``max_retry`` times)."""
        trial = copy.deepcopy(trial)
        trial.user_attrs = {
            **{key: value for key, value in trial.user_attrs.items() if key != WORKER_ATTR},
            RETRY_OF_ATTR: trial.number,
        }
        super().__call__(study, trial)


def _heartbeat_kwargs(heartbeat_interval: int, grace_period: int | None, max_retry: int | None) -> dict[str, Any]:
    """RDBStorage's heartbeat arguments under the installed Optuna's names (renamed in 4.9)."""
    parameters = inspect.signature(optuna.storages.RDBStorage.__init__).parameters
    if "heartbeat_stale_trial_callback" in parameters:
        callback_name = "heartbeat_stale_trial_callback"
    else:
        callback_name = "failed_trial_callback"
    return {
        "heartbeat_interval": heartbeat_interval,
        "grace_period": grace_period,
        callback_name: RetryStaleTrial(max_retry=max_retry),
    }


def is_journal(storage: str) -> bool:
    """Whether ``storage`` names a journal file (rl_zoo3's rule: the path ends in ``.log``), not an RDB URL."""
    return storage.endswith(".log")


def open_storage(
    storage: str,
    heartbeat_interval: int | None = HEARTBEAT_INTERVAL_S,
    grace_period: int | None = None,
    max_retry: int | None = 3,
) -> optuna.storages.BaseStorage:
    """A ``*.log`` path as a journal-file storage, anything else as an RDB URL with Optuna heartbeats.

    :param storage: journal file path or RDB URL (sqlite/postgresql/mysql).
    :param heartbeat_interval: seconds between heartbeats of a running trial (RDB only; None disables them). A trial
        without a heartbeat for ``grace_period`` (default ``2 * heartbeat_interval``) is failed by the next worker
        that starts a trial (or starts up), and re-queued up to ``max_retry`` times, whichever host it ran on.
    """
    if is_journal(storage):
        Path(storage).parent.mkdir(parents=True, exist_ok=True)
        return optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(storage))
    if heartbeat_interval is None:
        return optuna.storages.RDBStorage(storage)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        warnings.simplefilter("ignore", FutureWarning)  # RetryFailedTrialCallback's rename notice in Optuna >= 4.9
        return optuna.storages.RDBStorage(storage, **_heartbeat_kwargs(heartbeat_interval, grace_period, max_retry))


def count_trials(storage: str | optuna.storages.BaseStorage, study_name: str) -> int:
    """How many trials (any state) the study already holds; 0 when it does not exist yet."""
    if isinstance(storage, str):
        storage = open_storage(storage)
    try:
        study = optuna.load_study(study_name=study_name, storage=storage)
    except KeyError:
        return 0
    return len(study.get_trials(deepcopy=False))


def resumed_sampler_seed(seed: int | None, n_trials: int) -> int | None:
    """The sampler seed of a worker that joins a study already holding ``n_trials`` trials.

    ``seed`` itself for a new study (a fresh run stays reproducible); otherwise a seed derived from
    ``(seed, n_trials)``, so rerunning an interrupted command draws new parameters instead of repeating the first ones,
    and differs from the plain seed another worker may have been given. ``None`` (unseeded) stays ``None``.

    :param seed: the command's ``--seed`` (>= 0), or ``None``.
    :param n_trials: trials already in the study, in any state.
    """
    if seed is None or n_trials == 0:
        return seed
    return int(np.random.SeedSequence([int(seed), int(n_trials)]).generate_state(1)[0])


def recover_trial(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> bool:
    """Fail a stale RUNNING trial and re-queue its parameters; False if another worker got there first."""
    try:
        if not study._storage.set_trial_state_values(trial._trial_id, TrialState.FAIL):
            return False
    except UpdateFinishedTrialError:  # another worker recovered (or the owner finished) it since our snapshot
        return False
    study.enqueue_trial(trial.params, user_attrs={RETRY_OF_ATTR: trial.number})
    return True


def fail_heartbeat_stale_trials(study: optuna.Study) -> list[int]:
    """Fail the RUNNING trials whose heartbeat stopped and run the storage's retry callback; their numbers.

    What Optuna does before each new trial, done at start-up too: a worker that finds the study full (rl_zoo3 counts
    RUNNING trials towards ``--max-total-trials``) would otherwise leave a dead host's trial RUNNING for ever.
    """
    storage = study._storage
    if not is_heartbeat_enabled(storage):
        return []
    callback = storage.get_heartbeat_stale_trial_callback()
    numbers = []
    for trial_id in storage._get_stale_trial_ids(study._study_id):
        try:
            if not storage.set_trial_state_values(trial_id, state=TrialState.FAIL):
                continue
        except UpdateFinishedTrialError:  # another worker failed it (or its owner finished it) first
            continue
        trial = storage.get_trial(trial_id)
        numbers.append(trial.number)
        if callback is not None:
            callback(study, copy.deepcopy(trial))
    return numbers


def recover_stale_trials(
    storage: str | optuna.storages.BaseStorage, study_name: str, untagged_grace_s: float = UNTAGGED_GRACE_S
) -> list[int]:
    """Fail the RUNNING trials of dead workers, re-queue their parameters and return their numbers.

    With heartbeats (RDB storages from :func:`open_storage`) a trial whose heartbeat stopped is failed first,
    whichever host ran it; then trials of dead local workers (pid gone or reused) are failed without waiting for
    the grace period. Safe to run from several workers at once: each stale trial is failed, and re-queued, once.
    """
    if isinstance(storage, str):
        storage = open_storage(storage)
    try:
        study = optuna.load_study(study_name=study_name, storage=storage)
    except KeyError:  # the study does not exist yet
        return []
    recovered = fail_heartbeat_stale_trials(study)
    if is_heartbeat_enabled(study._storage):
        untagged_grace_s = float("inf")  # untagged trials have heartbeats, Optuna fails them when they stop
    stale = [t for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)) if is_stale(t, untagged_grace_s)]
    return recovered + [trial.number for trial in stale if recover_trial(study, trial)]
