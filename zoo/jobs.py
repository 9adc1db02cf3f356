"""Independent jobs on Ray, resumable: each finished job leaves ``<folder>/<job-id>.json`` (its config, seed, commit,
result and timings, written atomically by the driver), and a rerun skips the jobs whose record matches its config and
commit.

Ray is optional (the ``[ray]`` extra) and imported only when jobs run. A job is a picklable function of a JSON config
returning a JSON-able dict; it runs on one CPU of a Ray worker, is retried by Ray when it raises or its worker dies
(``max_retries``), and is reported as failed (never dropped) once its retries are spent. The record travels back
through Ray and is written where the driver runs, so workers on other machines need no shared file system, and a
folder of records is all a later run (on another machine too) needs to resume: :func:`run_commands` returns the
contents of the files a job makes, not their paths.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vafn_gym.files import atomic_write

REPO_ROOT = Path(__file__).resolve().parents[1]
#: The one-line error when Ray is missing.
RAY_MISSING = 'running the jobs needs Ray: pip install "vafn[ray]"'
JobFn = Callable[[dict[str, Any]], dict[str, Any]]


@dataclass
class JobReport:
    """What a run of jobs did: records of the jobs run now, of those skipped as finished, and of the failed ones."""

    done: list[dict[str, Any]] = field(default_factory=list)
    skipped: list[dict[str, Any]] = field(default_factory=list)
    failed: list[dict[str, Any]] = field(default_factory=list)


def import_ray() -> Any:
    """The ``ray`` module, or a one-line ``SystemExit`` naming the extra that installs it."""
    try:
        import ray
    except ImportError:
        raise SystemExit(RAY_MISSING) from None
    return ray


def start_ray(address: str | None = None, num_cpus: int | None = None) -> Any:
    """Connect to Ray unless already connected: ``address``'s cluster, else a local one with ``num_cpus`` CPUs."""
    ray = import_ray()
    if not ray.is_initialized():  # workers import zoo.jobs from this checkout's path (the same on every node)
        job_config = ray.job_config.JobConfig(code_search_path=[str(REPO_ROOT)])
        if address:
            ray.init(address=address, log_to_driver=False, job_config=job_config)
        else:  # jobs return small dicts: a small object store, no dashboard
            ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False,
                     object_store_memory=200 * 1024**2, job_config=job_config)
    return ray


def git_commit(root: Path = REPO_ROOT) -> str:
    """The checkout's commit, with ``-dirty`` when tracked files differ from it (``unknown`` outside git)."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (subprocess.CalledProcessError, FileNotFoundError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


def short_commit(root: Path = REPO_ROOT) -> str:
    """:func:`git_commit` with the hash cut to 7 characters, as result files name it."""
    head, dirty, _ = git_commit(root).partition("-dirty")
    return head[:7] + ("-dirty" if dirty else "")


def record_path(folder: Path, job_id: str) -> Path:
    """Where the record of one job is written."""
    return Path(folder) / f"{job_id}.json"


def read_record(folder: Path, job_id: str) -> dict[str, Any] | None:
    """The record of one job, or None when it has none (or an unreadable one)."""
    try:
        return dict(json.loads(record_path(folder, job_id).read_text()))
    except (OSError, ValueError):
        return None


def is_finished(record: dict[str, Any] | None, config: dict[str, Any], commit: str) -> bool:
    """Whether a record is of a job that succeeded with this config at this commit."""
    return (record is not None and record.get("status") == "ok" and record.get("commit") == commit
            and record.get("config") == json.loads(json.dumps(config)))


def write_record(folder: Path, record: dict[str, Any]) -> Path:
    """Write one job's record atomically (a killed writer leaves the previous record or none)."""
    text = json.dumps(record, indent=1, default=str)

    def write(tmp: Path) -> None:
        tmp.write_text(text)

    return atomic_write(record_path(folder, record["job_id"]), write)


def execute(fn: JobFn, job_id: str, config: dict[str, Any], commit: str) -> dict[str, Any]:
    """Run one job where it is called (a Ray worker) and return its record; its exceptions propagate to Ray."""
    started, wall, cpu = time.time(), time.perf_counter(), os.times()
    result = fn(config)
    end = os.times()
    cpu_s = sum(getattr(end, k) - getattr(cpu, k) for k in ("user", "system", "children_user", "children_system"))
    return {"job_id": job_id, "status": "ok", "config": config, "seed": config.get("seed"), "commit": commit,
            "result": result, "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(started)),
            "wall_s": time.perf_counter() - wall, "cpu_s": cpu_s, "host": socket.gethostname(), "pid": os.getpid()}


def run_jobs(fn: JobFn, jobs: Iterable[tuple[str, dict[str, Any]]], folder: Path, *, commit: str | None = None,
             max_in_flight: int | None = None, max_retries: int = 2,
             on_record: Callable[[dict[str, Any]], None] | None = None) -> JobReport:
    """Run on Ray (connected by :func:`start_ray`) every job not already finished, in the given order, at most
    ``max_in_flight`` at a time; each retried ``max_retries`` times; ``on_record`` sees each record as it ends."""
    ray = import_ray()
    if not ray.is_initialized():
        start_ray()
    commit = git_commit() if commit is None else commit
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    report, todo = JobReport(), []
    for job_id, config in jobs:
        record = read_record(folder, job_id)
        if is_finished(record, config, commit):
            report.skipped.append(record)  # type: ignore[arg-type]
        else:
            todo.append((job_id, config))
    remote = ray.remote(execute).options(num_cpus=1, max_retries=max_retries, retry_exceptions=True)
    pending: dict[Any, tuple[str, dict[str, Any]]] = {}
    queue = list(reversed(todo))
    try:
        while queue or pending:
            while queue and (max_in_flight is None or len(pending) < max_in_flight):
                job_id, config = queue.pop()
                pending[remote.remote(fn, job_id, config, commit)] = (job_id, config)
            ready, _ = ray.wait(list(pending), num_returns=1)
            job_id, config = pending.pop(ready[0])
            try:
                record = ray.get(ready[0])
                write_record(folder, record)
                report.done.append(record)
            except ray.exceptions.RayError as error:  # retries spent: the job raised, or its worker died
                lines = str(error).strip().splitlines() or [type(error).__name__]
                record = {"job_id": job_id, "status": "failed", "config": config, "seed": config.get("seed"),
                          "commit": commit, "error": lines[-1][:500], "error_type": type(error).__name__}
                write_record(folder, record)
                report.failed.append(record)
            if on_record is not None:
                on_record(record)
    finally:  # interrupted (Ctrl-C): stop the jobs still running; their records are not written, a rerun redoes them
        for ref in pending:
            ray.cancel(ref, force=True)
    return report


def file_text(path: Path) -> str:
    """A job's output file as record text: UTF-8 text as it is, anything else (a zip) as ``base64:`` and its bytes."""
    data = path.read_bytes()
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return "base64:" + base64.b64encode(data).decode("ascii")


def write_file_text(text: str, path: Path) -> Path:
    """Write a :func:`file_text` back to ``path`` (atomically)."""
    data = base64.b64decode(text[len("base64:"):]) if text.startswith("base64:") else text.encode("utf-8")

    def write(tmp: Path) -> None:
        tmp.write_bytes(data)

    return atomic_write(Path(path), write)


def run_commands(config: dict[str, Any]) -> dict[str, Any]:
    """A job that runs each of ``config["commands"]`` in turn (``python`` = this interpreter) from the repository root
    into ``config["log"]``, must leave every file of ``config["outputs"]`` (removed first), and returns
    ``{"files": {name: file_text}}`` of ``config["collect"]`` (``{name: path}``); raises when a command fails.
    Relative paths are the repository root's, as the commands see them."""
    outputs, log = [REPO_ROOT / path for path in config["outputs"]], REPO_ROOT / config["log"]
    for output in outputs:
        output.unlink(missing_ok=True)
        output.parent.mkdir(parents=True, exist_ok=True)
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("w") as handle:
        for command in config["commands"]:
            command = [sys.executable if part == "python" else part for part in command]
            handle.write(f"$ {' '.join(command)}\n")
            handle.flush()
            result = subprocess.run(command, cwd=REPO_ROOT, stdout=handle, stderr=subprocess.STDOUT,
                                    env={**os.environ, "OMP_NUM_THREADS": "1"})
            if result.returncode != 0:
                raise RuntimeError(f"exit {result.returncode} of {command[1] if len(command) > 1 else command}, "
                                   f"see {log}")
    missing = [str(output) for output in outputs if not output.is_file()]
    if missing:
        raise RuntimeError(f"no {', '.join(missing)}, see {log}")
    return {"files": {name: file_text(REPO_ROOT / path) for name, path in config.get("collect", {}).items()},
            "log": config["log"]}
