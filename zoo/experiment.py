"""``VAFNExperimentManager``: rl_zoo3's ExperimentManager with the few vafn-specific behaviours the zoo lacks.

* evaluation reports success *and* collision rates (``eval/collision_rate``, ``rollout/collision_rate``, Monitor
  columns);
* a sampled ``policy_kwargs`` is merged into the YAML's instead of replacing it (during ``-optimize`` and
  ``--trial-id``);
* tuning defaults to a local journal file, tags each trial with its worker, and on restart marks trials left RUNNING by
  a dead local worker as FAIL and re-queues their parameters, so a killed worker's study resumes cleanly; a rerun's
  sampler seed advances with the trials already in the study, so it draws new parameters;
* an RDB ``--storage`` URL (PostgreSQL, MySQL, SQLite) is opened with Optuna heartbeats
  (:func:`zoo.tuning.open_storage`) and the zoo's optimisation loop runs on that storage object, so a trial whose
  worker died on any host is failed and re-queued by the next worker;
* ``--env-kwargs`` update the YAML's ``env_kwargs`` key by key (rl_zoo3 replaces them whole); as in rl_zoo3, the
  YAML's ``env_kwargs`` configure the training env only, and the evaluation env gets ``--env-kwargs`` (or
  ``--eval-env-kwargs``) alone;
* ``maml_sac`` warns when ``-n`` leaves no step after ``warmup_steps`` (no meta-iteration would run).
"""

from __future__ import annotations

import contextlib
import contextvars
import warnings
from collections.abc import Iterator
from typing import Any

import optuna
import rl_zoo3.exp_manager as zoo_exp_manager
from rl_zoo3.exp_manager import ExperimentManager
from rl_zoo3.hyperparams_opt import HYPERPARAMS_SAMPLER
from stable_baselines3.common.callbacks import EvalCallback

from vafn_gym.benchmarks import COLLISION_KEY
from vafn_sb3.callbacks import RolloutCollisionCallback, SuccessCollisionEvalCallback
from zoo.tuning import (
    HEARTBEAT_INTERVAL_S,
    WORKER_ATTR,
    count_trials,
    is_journal,
    open_storage,
    recover_stale_trials,
    resumed_sampler_seed,
    worker_id,
)

#: Monitor columns written for VAFN envs (success and "any collision this episode").
VAFN_INFO_KEYWORDS = ("is_success", COLLISION_KEY)
#: Hyperparameter key carrying a stored trial's policy_kwargs until they are merged with the YAML's.
TUNED_POLICY_KWARGS = "tuned_policy_kwargs"

_yaml_policy_kwargs: contextvars.ContextVar[dict[str, Any]] = contextvars.ContextVar("yaml_policy_kwargs")


def _merge_policy_kwargs(sampler: Any) -> Any:
    """Wrap a sampler so that its ``policy_kwargs`` extend the YAML's (set per trial through a context variable)."""

    def sample(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
        params = sampler(trial, n_actions, n_envs, additional_args)
        if "policy_kwargs" in params:
            params["policy_kwargs"] = {**_yaml_policy_kwargs.get({}), **params["policy_kwargs"]}
        return params

    sample.merges_policy_kwargs = True  # type: ignore[attr-defined]
    return sample


class _OptunaWithStorage:
    """The ``optuna`` module as rl_zoo3 sees it, except that ``create_study`` uses a storage object we opened."""

    def __init__(self, storage: optuna.storages.BaseStorage) -> None:
        self._storage = storage

    def __getattr__(self, name: str) -> Any:
        return getattr(optuna, name)

    def create_study(self, *args: Any, storage: Any = None, **kwargs: Any) -> optuna.Study:
        """``optuna.create_study`` on the opened storage (rl_zoo3 passes the URL string it was given)."""
        return optuna.create_study(*args, storage=self._storage, **kwargs)


@contextlib.contextmanager
def _zoo_uses_storage(storage: optuna.storages.BaseStorage) -> Iterator[None]:
    """While active, rl_zoo3's optimisation loop creates its study on ``storage`` instead of reopening the URL."""
    original = zoo_exp_manager.optuna
    zoo_exp_manager.optuna = _OptunaWithStorage(storage)  # type: ignore[assignment]
    try:
        yield
    finally:
        zoo_exp_manager.optuna = original


def warn_if_no_meta_iteration(algo: str, hyperparams: dict[str, Any], n_timesteps: int) -> bool:
    """Warn (and return True) when ``n_timesteps`` ends inside ``warmup_steps``, so no meta-iteration would run."""
    warmup = hyperparams.get("warmup_steps")
    if warmup is None or n_timesteps > int(warmup):
        return False
    warnings.warn(
        f"{algo}: -n {n_timesteps} is not above warmup_steps={int(warmup)}: training ends in the plain-SAC warm-up "
        f"and no meta-iteration will run (raise -n above {int(warmup)} or pass -params warmup_steps:N)",
        UserWarning,
        stacklevel=2,
    )
    return True


class VAFNExperimentManager(ExperimentManager):
    """ExperimentManager with success/collision evaluation, policy_kwargs merging and resumable tuning."""

    #: Heartbeat period and grace period (s) of RDB storages during ``-optimize`` (``zoo/train.py`` sets them).
    heartbeat_interval: int = HEARTBEAT_INTERVAL_S
    heartbeat_grace: int | None = None

    @classmethod
    def with_heartbeat(cls, interval: int, grace: int | None) -> type[VAFNExperimentManager]:
        """A subclass whose RDB tuning storages use these heartbeat settings (the class itself is left unchanged)."""
        return type(cls.__name__, (cls,), {"heartbeat_interval": interval, "heartbeat_grace": grace})

    def _is_vafn_env(self) -> bool:
        return self.env_name.gym_id.startswith("VAFN/")

    # --- hyperparameters ---
    def load_trial(self, storage: str, study_name: str, trial_id: int | None = None, convert: bool = True) -> dict:
        """A stored trial's hyperparams, its policy_kwargs set aside to be merged with the YAML's later."""
        params = super().load_trial(storage, study_name, trial_id, convert)
        if convert and "policy_kwargs" in params:
            params[TUNED_POLICY_KWARGS] = params.pop("policy_kwargs")
        return params

    def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """The zoo's, with ``--env-kwargs`` merged into the YAML's training ``env_kwargs`` instead of replacing them."""
        cli, self.env_kwargs = self.env_kwargs, {}  # an empty CLI value keeps rl_zoo3 from replacing the YAML's
        try:
            hyperparams, saved_hyperparams = super().read_hyperparameters()
        finally:
            self.env_kwargs = cli
        if "env_kwargs" in hyperparams:
            merged = {**hyperparams["env_kwargs"], **cli}
            hyperparams["env_kwargs"] = saved_hyperparams["env_kwargs"] = merged
        return hyperparams, saved_hyperparams

    def _preprocess_hyperparams(self, hyperparams: dict[str, Any]) -> tuple:
        """The zoo's preprocessing, then merge tuned policy_kwargs into the YAML/CLI ones (CLI keys win)."""
        tuned = hyperparams.pop(TUNED_POLICY_KWARGS, None)
        hyperparams, env_wrapper, callbacks, vec_env_wrapper = super()._preprocess_hyperparams(hyperparams)
        if tuned:
            cli = (self.custom_hyperparams or {}).get("policy_kwargs") or {}
            cli = eval(cli) if isinstance(cli, str) else cli  # same eval as the zoo's policy_kwargs strings
            hyperparams["policy_kwargs"] = {**hyperparams.get("policy_kwargs", {}), **tuned, **cli}
        if self._is_vafn_env() and not self.monitor_kwargs:
            self.monitor_kwargs = {"info_keywords": VAFN_INFO_KEYWORDS}
        warn_if_no_meta_iteration(self.algo, hyperparams, self.n_timesteps)
        return hyperparams, env_wrapper, callbacks, vec_env_wrapper

    # --- callbacks ---
    def create_callbacks(self) -> None:
        """The zoo's callbacks, with EvalCallback upgraded to also report collisions, plus the rollout collision
        rate."""
        super().create_callbacks()
        for index, callback in enumerate(self.callbacks):
            if type(callback) is EvalCallback:
                self.callbacks[index] = SuccessCollisionEvalCallback(
                    callback.eval_env,
                    callback_on_new_best=callback.callback_on_new_best,
                    best_model_save_path=callback.best_model_save_path,
                    n_eval_episodes=callback.n_eval_episodes,
                    log_path=self.save_path,
                    eval_freq=callback.eval_freq,
                    deterministic=callback.deterministic,
                )
        if self._is_vafn_env():
            self.callbacks.append(RolloutCollisionCallback())

    # --- tuning ---
    def objective(self, trial: optuna.Trial) -> float:
        """The zoo's objective, with the worker recorded and the sampled policy_kwargs merged into the YAML's."""
        trial.set_user_attr(WORKER_ATTR, worker_id())
        sampler = HYPERPARAMS_SAMPLER[self.algo]
        if not getattr(sampler, "merges_policy_kwargs", False):
            HYPERPARAMS_SAMPLER[self.algo] = _merge_policy_kwargs(sampler)
        _yaml_policy_kwargs.set(dict(self._hyperparams.get("policy_kwargs") or {}))
        return super().objective(trial)

    def open_tuning_storage(self) -> optuna.storages.BaseStorage | None:
        """The ``--storage`` opened for tuning: a journal file, or an RDB URL with this manager's heartbeats."""
        if self.storage is None:
            return None
        return open_storage(self.storage, heartbeat_interval=self.heartbeat_interval, grace_period=self.heartbeat_grace)

    #: Trials the study held when this worker joined it (seeds the sampler: :func:`zoo.tuning.resumed_sampler_seed`).
    trials_before: int = 0

    def _create_sampler(self, sampler_method: str) -> optuna.samplers.BaseSampler:
        """The zoo's sampler, seeded so that a rerun on an existing study draws new parameters."""
        seed = self.seed
        self.seed = resumed_sampler_seed(seed, self.trials_before)
        try:
            return super()._create_sampler(sampler_method)
        finally:
            self.seed = seed

    def hyperparameters_optimization(self) -> None:
        """Recover trials of dead workers, then run the zoo's optimisation loop (on the heartbeat storage for RDB)."""
        storage = self.open_tuning_storage()
        if storage is not None and self.study_name is not None:
            recovered = recover_stale_trials(storage, self.study_name)
            if recovered and self.verbose > 0:
                print(f"Marked stale trials {recovered} (dead worker) as FAIL and re-queued their parameters")
            self.trials_before = count_trials(storage, self.study_name)
        if storage is None or is_journal(self.storage):
            super().hyperparameters_optimization()  # the zoo opens the same journal file itself
            return
        with _zoo_uses_storage(storage):
            super().hyperparameters_optimization()
