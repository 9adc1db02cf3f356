"""zoo/jobs.py: independent jobs on a local Ray with 2 workers; a worker killed mid-job is retried, an interrupted run
resumes without redoing finished jobs, a changed config or commit reruns."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

ray = pytest.importorskip("ray")

from zoo.jobs import read_record, run_jobs  # noqa: E402


@pytest.fixture(scope="module")
def local_ray():
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the cheap job, on workers that cannot import us
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, object_store_memory=100 * 1024**2)
    yield ray
    ray.shutdown()


def cheap_job(config: dict[str, Any]) -> dict[str, Any]:
    """Leaves one marker file per execution; kills its own worker on its first attempt when asked to."""
    marks = Path(config["marks"])
    runs = len(list(marks.glob(f"{config['name']}.*")))
    (marks / f"{config['name']}.{runs}").touch()
    if config.get("kill_first") and runs == 0:
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(config.get("sleep", 0.0))
    return {"value": config["seed"] * 10}


def _jobs(marks: Path, n: int, **extra: Any) -> list[tuple[str, dict[str, Any]]]:
    """A --full-shaped list: two panels x methods x seeds, one job each."""
    names = [f"{panel}-{method}-seed{seed}" for panel in ("hidden", "order") for method in ("sac", "mappo")
             for seed in range(n)]
    return [(name, {"name": name, "seed": index, "marks": str(marks), **extra}) for index, name in enumerate(names)]


def _runs(marks: Path, name: str) -> int:
    return len(list(marks.glob(f"{name}.*")))


def test_a_killed_worker_is_retried_and_nothing_is_lost(local_ray: Any, tmp_path: Path) -> None:
    marks, folder = tmp_path / "marks", tmp_path / "jobs"
    marks.mkdir()
    jobs = _jobs(marks, 2)
    jobs[1][1]["kill_first"] = True
    report = run_jobs(cheap_job, jobs, folder, commit="c1", max_in_flight=2)
    assert not report.failed and len(report.done) == len(jobs)
    assert _runs(marks, jobs[1][0]) == 2, "the killed job ran again"
    for name, config in jobs:
        record = read_record(folder, name)
        assert record is not None and record["status"] == "ok" and record["result"] == {"value": config["seed"] * 10}
        assert record["commit"] == "c1" and record["seed"] == config["seed"] and record["wall_s"] >= 0

    again = run_jobs(cheap_job, jobs, folder, commit="c1")  # all finished: nothing runs
    assert not again.done and len(again.skipped) == len(jobs)
    assert all(_runs(marks, name) == (2 if name == jobs[1][0] else 1) for name, _ in jobs)
    changed = [(name, {**config, "seed": 99}) if index == 0 else (name, config) for index, (name, config) in
               enumerate(jobs)]
    assert [r["job_id"] for r in run_jobs(cheap_job, changed, folder, commit="c1").done] == [jobs[0][0]]
    assert len(run_jobs(cheap_job, jobs, folder, commit="c2").done) == len(jobs), "another commit reruns all"


def test_failed_jobs_are_reported_and_an_interrupted_run_resumes(local_ray: Any, tmp_path: Path) -> None:
    marks, folder = tmp_path / "marks", tmp_path / "jobs"
    marks.mkdir()
    jobs = _jobs(marks, 2, sleep=0.3)
    broken = [(name, {**config, "marks": str(tmp_path / "missing")}) if index == 2 else (name, config)
              for index, (name, config) in enumerate(jobs)]
    report = run_jobs(cheap_job, broken[:4], folder, commit="c1", max_retries=1)
    assert [r["job_id"] for r in report.failed] == [jobs[2][0]] and len(report.done) == 3
    assert read_record(folder, jobs[2][0])["status"] == "failed" and report.failed[0]["error"]

    seen: list[str] = []

    def interrupt(record: dict[str, Any]) -> None:  # Ctrl-C after the second job of this run ends
        seen.append(record["job_id"])
        if len(seen) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_jobs(cheap_job, jobs, folder, commit="c1", max_in_flight=2, on_record=interrupt)
    finished = {name for name, config in jobs if (read_record(folder, name) or {}).get("status") == "ok"}
    assert len(finished) >= 5 and len(finished) < len(jobs)
    counts = {name: _runs(marks, name) for name, _ in jobs}
    resumed = run_jobs(cheap_job, jobs, folder, commit="c1", max_in_flight=2)
    assert not resumed.failed and {r["job_id"] for r in resumed.done} == {n for n, _ in jobs} - finished
    assert all(_runs(marks, name) == counts[name] for name in finished), "a finished job ran again"
    assert all(read_record(folder, name)["status"] == "ok" for name, _ in jobs)


def test_missing_ray_is_one_line_naming_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    import zoo.jobs

    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(SystemExit, match=r'pip install "vafn\[ray\]"') as error:
        zoo.jobs.import_ray()
    assert "\n" not in str(error.value)
