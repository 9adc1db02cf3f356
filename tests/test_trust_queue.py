"""Issue 61, "commands that vanish": every command ends completed, failed with a reason, dropped with a record, or
still queued; bad arrivals, stream stops and tuning reruns lose nothing and repeat nothing."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import optuna
import pytest

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_gym import ScriptedController
from vafn_gym.queue import DROPPED_HISTORY, InstructionQueue, PoissonArrivals, QueuedInstruction, QueueFullError
from vafn_gym.queue import ScheduledArrivals
from vafn_media.stream import MultimediaStream, StreamEvent
from vafn_sb3.online import OnlineController

STREAM = "VAFN/ThreeArmStream-v1"
PRODUCERS, PER_PRODUCER, CONTROLLER_STEPS = 8, 40, 3000
#: What the producers send: valid commands, and (unvalidated) ones the stream must reject with a reason.
GOOD, BAD = ("1", "2,3", "3,1", "2"), ("[4]", "1,9")


@dataclass
class Producer:
    """One producer thread's own account: what the queue accepted, and how often it was refused."""

    accepted: list[QueuedInstruction] = field(default_factory=list)
    refused: int = 0
    errors: list[BaseException] = field(default_factory=list)


def _produce(queue: InstructionQueue, index: int, account: Producer, start: threading.Barrier) -> None:
    rng = random.Random(index)
    start.wait()
    try:
        for number in range(PER_PRODUCER):
            bad = number % 10 == 9
            code = rng.choice(BAD if bad else GOOD)
            try:
                # Half the producers wait briefly for room (backpressure with a timeout), half ask once.
                timeout = 0.05 if index % 2 else 0.0
                account.accepted.append(queue.enqueue(code, source=f"p{index}", validate=not bad, timeout=timeout))
            except QueueFullError:
                account.refused += 1
            time.sleep(rng.uniform(0.0, 0.004))
    except BaseException as error:  # noqa: BLE001 - reported by the test
        account.errors.append(error)


def _run_books(overflow: str) -> tuple[dict[str, set[int]], list[Producer], OnlineController, list[QueuedInstruction]]:
    """8 producers enqueue while the controller runs 3,000 steps (one episode end at 2,000); each command's fate."""
    seen_drops: list[QueuedInstruction] = []
    env = gym.make(STREAM, arrivals=None, auto_dequeue=False, overflow=overflow, on_drop=seen_drops.append)
    controller = OnlineController(ScriptedController.for_env(env), env)
    queue = env.unwrapped.queue
    accounts = [Producer() for _ in range(PRODUCERS)]
    start = threading.Barrier(PRODUCERS + 1)
    threads = [threading.Thread(target=_produce, args=(queue, i, accounts[i], start)) for i in range(PRODUCERS)]
    for thread in threads:
        thread.start()
    start.wait()
    controller.run(CONTROLLER_STEPS)
    for thread in threads:
        thread.join(timeout=10)
    assert not any(thread.is_alive() for thread in threads), "a producer hung"
    assert not [error for account in accounts for error in account.errors]
    last_row = {entry.sequence: entry for entry in controller.log}  # a command cut by the episode end runs again
    fates = {
        "completed": {s for s, entry in last_row.items() if entry.outcome == "completed"},
        "failed": {s for s, entry in last_row.items() if entry.outcome == "timeout"}
        | {row["sequence"] for row in controller.rejected},
        "dropped": {entry.sequence for entry in controller.dropped},
        "queued": {entry.sequence for entry in queue.snapshot() + queue.unacked()},
    }
    return fates, accounts, controller, seen_drops


def _assert_books_balance(fates: dict[str, set[int]], accounts: list[Producer], controller: OnlineController) -> None:
    queue = controller.stream.queue
    accepted = [entry.sequence for account in accounts for entry in account.accepted]
    assert sorted(accepted) == list(range(queue.enqueued))  # every accepted command has its own sequence number
    counts = {name: len(sequences) for name, sequences in fates.items()}
    assert sum(counts.values()) == queue.enqueued, counts  # to the item: no command twice, none missing
    assert set().union(*fates.values()) == set(accepted)
    for row in controller.rejected:
        assert row["reason"] and row["source"].startswith("p")
    last_row = {entry.sequence: entry for entry in controller.log}
    unfinished = {s for s, entry in last_row.items() if entry.outcome not in ("completed", "timeout")}
    assert unfinished <= fates["queued"]  # running or cut by the episode end: still the queue's


def test_default_queue_applies_backpressure_and_the_books_balance():
    fates, accounts, controller, seen_drops = _run_books("raise")
    counts = {name: len(sequences) for name, sequences in fates.items()}
    refused = sum(account.refused for account in accounts)
    print(f"raise: enqueued {controller.stream.queue.enqueued}, {counts}, refused to producers {refused}")
    _assert_books_balance(fates, accounts, controller)
    assert counts["dropped"] == 0 and seen_drops == [] and controller.stream.queue.dropped == 0
    assert refused > 0, "the producers never hit a full queue: the test did not exercise backpressure"
    assert refused + controller.stream.queue.enqueued == PRODUCERS * PER_PRODUCER  # refused ones were told so
    assert counts["completed"] > 0 and counts["failed"] > 0


def test_drop_oldest_records_every_eviction_uncapped_and_the_books_balance():
    fates, accounts, controller, seen_drops = _run_books("drop_oldest")
    queue = controller.stream.queue
    counts = {name: len(sequences) for name, sequences in fates.items()}
    print(f"drop_oldest: enqueued {queue.enqueued}, {counts}")
    _assert_books_balance(fates, accounts, controller)
    assert sum(account.refused for account in accounts) == 0 and queue.enqueued == PRODUCERS * PER_PRODUCER
    assert queue.dropped > DROPPED_HISTORY, "too few evictions to show the record is uncapped"
    assert [e.sequence for e in seen_drops] == [e.sequence for e in controller.dropped]  # on_drop saw every one
    assert len(controller.dropped) == queue.dropped


# --- the queue itself ---
def test_enqueue_timeout_waits_for_room_then_refuses():
    queue = InstructionQueue(capacity=1)
    queue.enqueue("1")
    started = time.perf_counter()
    with pytest.raises(QueueFullError, match="full"):
        queue.enqueue("2", timeout=0.1)
    assert 0.09 <= time.perf_counter() - started < 2.0
    assert (queue.enqueued, len(queue)) == (1, 1)
    threading.Timer(0.05, queue.dequeue).start()
    assert queue.enqueue("3", timeout=5.0).sequence == 1  # woken by the consumer
    with pytest.raises(ValueError, match="timeout"):
        queue.enqueue("1", timeout=-1)


def test_on_drop_gets_every_eviction_and_its_errors_are_kept():
    seen: list[QueuedInstruction] = []
    queue = InstructionQueue(capacity=2, overflow="drop_oldest", on_drop=seen.append)
    entries = [queue.enqueue("1") for _ in range(DROPPED_HISTORY + 30)]
    assert seen == entries[:-2] and queue.dropped == len(seen)
    assert len(queue.dropped_items) == DROPPED_HISTORY  # the queue's own view stays capped; on_drop is the record

    def broken(entry: QueuedInstruction) -> None:
        raise RuntimeError("disk full")

    queue = InstructionQueue(capacity=1, overflow="drop_oldest", on_drop=broken)
    queue.enqueue("1")
    kept = queue.enqueue("2")  # the producer's entry is queued even though the callback failed
    assert queue.snapshot() == [kept] and "disk full" in queue.drop_callback_errors[0]
    with pytest.raises(ValueError, match="on_drop"):
        InstructionQueue(on_drop=5)


def test_stream_env_defaults_to_backpressure():
    env = gym.make(STREAM, arrivals=None, queue_capacity=2)
    queue = env.unwrapped.queue
    assert queue.overflow == "raise"
    queue.enqueue("1")
    queue.enqueue("2")
    with pytest.raises(QueueFullError):
        queue.enqueue("3")
    env.close()


# --- arrival processes ---
def test_arrivals_are_validated_when_attached():
    env = gym.make(STREAM, arrivals=None)
    stream = env.unwrapped
    with pytest.raises(ValueError, match=r"schedule step 5: waypoint 0: arm 4"):
        stream.arrival_process = ScheduledArrivals({0: "1", 5: "4"})
    with pytest.raises(ValueError, match=r"schedule step 2, instruction 1: waypoint 1: arm 5"):
        stream.arrival_process = ScheduledArrivals({2: ["1", "2,5"]})
    with pytest.raises(ValueError, match=r"instructions\[1\]"):
        stream.arrival_process = PoissonArrivals(0.1, instructions=["1", "3,4"])
    with pytest.raises(ValueError, match="ArrivalProcess"):
        stream.arrival_process = {0: "1"}
    assert stream.arrival_process is None  # nothing was attached
    with pytest.raises(ValueError, match="schedule step 5"):
        gym.make(STREAM, arrivals=ScheduledArrivals({5: "4"}))
    env.close()


def test_a_bad_arrival_at_run_time_is_recorded_and_skipped():
    def sampler(rng: np.random.Generator) -> str:
        return "2,4" if rng.random() < 0.5 else "1"  # arm 4: only knowable when it arrives

    env = gym.make(STREAM, arrivals=None, auto_dequeue=False)
    stream = env.unwrapped
    env.reset(seed=0)
    stream.arrival_process = PoissonArrivals(1.0, sampler=sampler, seed=3)
    queued = 0
    for _ in range(40):
        _, _, _, _, info = env.step(np.zeros(env.action_space.shape, np.float32))  # never raises
        queued = info["queue_length"]
    skipped = [line for line in stream.errors if "skipped" in line]
    assert skipped and all("arm 4" in line and "step" in line for line in skipped)
    assert queued == stream.queue.enqueued > 0  # the good arrivals of the same steps were queued
    assert all(entry.instruction.arms == (1,) for entry in stream.queue.snapshot())
    env.close()


def test_arrivals_refused_by_a_full_queue_are_recorded():
    env = gym.make(STREAM, arrivals={0: ["1", "2", "3"]}, queue_capacity=2, auto_dequeue=False)
    env.reset(seed=0)
    stream = env.unwrapped
    assert len(stream.queue) == 2
    assert len(stream.errors) == 1 and "full" in stream.errors[0] and "step 0" in stream.errors[0]
    env.close()


# --- reset options ---
def test_reset_with_an_instruction_option_changes_nothing():
    env = gym.make(STREAM, arrivals=None)
    stream = env.unwrapped
    env.reset(seed=0)
    stream.queue.enqueue("2,3")
    for _ in range(30):
        env.step(env.action_space.sample())
    def state() -> tuple:
        return stream.total_steps, stream.current, stream.instruction, len(stream.records), stream.queue.in_flight

    before = state()
    positions = {arm: p.copy() for arm, p in stream._positions().items()}
    for option in ("1", "9", None):
        with pytest.raises(ValueError, match="from its queue"):
            env.reset(options={"instruction": option})
    assert state() == before and before[1] is not None  # an instruction was running and still is
    assert all(np.array_equal(positions[arm], p) for arm, p in stream._positions().items())  # arms were not homed
    env.close()


# --- MultimediaStream.stop ---
class _CodeReader:
    """Reads ``code=`` like the generator's code path; ``delay`` seconds per request."""

    def __init__(self, delay: float = 0.0) -> None:
        self.delay = delay

    def transcribe(self, audio=None, image=None, code=None, sample_rate=None):
        time.sleep(self.delay)
        from vafn_gym.instructions import Instruction

        return SimpleNamespace(instruction=Instruction.coerce(code), confidence=1.0, confidences=(1.0,),
                               low_confidence=False, method="code", warnings=(), modalities=("code",))


def _in_thread(call, timeout: float = 5.0) -> float:
    """Run ``call`` on a thread and return its duration; fail (instead of hanging) past ``timeout``."""
    thread = threading.Thread(target=call, daemon=True)
    started = time.perf_counter()
    thread.start()
    thread.join(timeout)
    assert not thread.is_alive(), f"{call} did not return within {timeout} s"
    return time.perf_counter() - started


def _statuses(stream: MultimediaStream) -> Counter:
    tickets = [event.ticket for event in stream.events]
    assert len(tickets) == len(set(tickets)), "a request got two events"
    return Counter(event.status for event in stream.events)


@pytest.mark.parametrize("drain", [True, False])
def test_stop_from_its_own_callback_returns_and_every_request_gets_an_event(drain):
    returned: list[float] = []

    def on_event(event: StreamEvent) -> None:
        if event.ticket == 0:
            started = time.perf_counter()
            stream.stop(drain=drain)
            returned.append(time.perf_counter() - started)

    queue = InstructionQueue()
    stream = MultimediaStream(queue, _CodeReader(delay=0.01), on_event=on_event).start()
    tickets = [stream.submit(code="1") for _ in range(20)]
    deadline = time.perf_counter() + 5.0
    while stream.alive and time.perf_counter() < deadline:
        time.sleep(0.01)
    assert not stream.alive, "the worker did not wind down after stop() in its callback"
    assert returned and returned[0] < 0.5
    late = stream.submit(code="2")  # after the stop: answered at once, never left pending
    assert sorted(event.ticket for event in stream.events) == tickets + [late]
    counts = _statuses(stream)
    assert counts["cancelled"] == (1 if drain else 20)
    assert counts["enqueued"] == len(queue) == (20 if drain else 1)
    assert stream.wait(timeout=0) is True


def test_stop_without_drain_cancels_every_pending_request():
    queue = InstructionQueue()
    stream = MultimediaStream(queue, _CodeReader(delay=0.02)).start()
    for _ in range(100):
        stream.submit(code="3")
    assert _in_thread(lambda: stream.stop(drain=False, timeout=5.0)) < 1.0
    counts = _statuses(stream)
    assert sum(counts.values()) == 100 and counts["cancelled"] >= 90
    assert counts["enqueued"] == len(queue) and not stream.alive


def test_stop_with_an_expired_drain_timeout_cancels_the_rest():
    stream = MultimediaStream(InstructionQueue(), _CodeReader(delay=0.02)).start()
    for _ in range(50):
        stream.submit(code="1")
    _in_thread(lambda: stream.stop(timeout=0.1))
    deadline = time.perf_counter() + 5.0
    while stream.alive and time.perf_counter() < deadline:
        time.sleep(0.01)
    counts = _statuses(stream)
    assert sum(counts.values()) == 50 and counts["cancelled"] > 0 and counts["enqueued"] > 0


def test_a_never_started_stream_cancels_on_stop_and_restarts():
    stream = MultimediaStream(InstructionQueue(), _CodeReader())
    stream.submit(code="1")
    _in_thread(stream.stop)
    assert [event.status for event in stream.events] == ["cancelled"]
    stream.start()
    stream.submit(code="2")
    assert stream.wait(timeout=5.0)
    stream.stop()
    assert [event.status for event in stream.events] == ["cancelled", "enqueued"]


# --- tuning reruns ---
def test_rerunning_a_tuning_command_continues_with_new_parameters(tmp_path, monkeypatch):
    from zoo.experiment import VAFNExperimentManager
    from zoo.train import main as train_main
    from zoo.tuning import make_off_policy_sampler, open_storage

    sample = make_off_policy_sampler("sac", None)

    def objective(self: VAFNExperimentManager, trial: optuna.Trial) -> float:
        return float(sample(trial, 9, 1, {})["learning_rate"])  # the real search space, no training

    monkeypatch.setattr(VAFNExperimentManager, "objective", objective)
    storage = str(tmp_path / "study.log")
    command = ["--algo", "sac", "--env", "VAFN/ThreeArmReach-v1", "-optimize", "--n-trials", "2", "-n", "100",
               "-f", str(tmp_path), "--storage", storage, "--study-name", "s", "--no-optim-plots",
               "--sampler", "random", "--seed", "1"]
    train_main(command)
    train_main(command)  # the interrupted command, run again as docs/tuning.md says
    train_main(command)
    trials = optuna.load_study(study_name="s", storage=open_storage(storage)).trials
    params = [tuple(sorted(trial.params.items())) for trial in trials]
    assert len(params) == 6 and len(set(params)) == 6, "a rerun drew parameters the study already had"
    assert params[:2] == _first_run_params(tmp_path, command)  # the first run is still reproducible from its seed


def _first_run_params(tmp_path, command: list[str]) -> list[tuple]:
    from zoo.train import main as train_main
    from zoo.tuning import open_storage

    storage = str(tmp_path / "fresh.log")
    train_main([*command[:command.index("--storage")], "--storage", storage, *command[command.index("--study-name"):]])
    trials = optuna.load_study(study_name="s", storage=open_storage(storage)).trials
    return [tuple(sorted(trial.params.items())) for trial in trials]


# --- atomic saves ---
def test_a_killed_save_leaves_a_temp_file_that_the_next_save_removes(tmp_path):
    from vafn_gym.files import atomic_write

    target = tmp_path / "model.zip"
    atomic_write(target, lambda tmp: tmp.write_bytes(b"old"))
    killed = (
        "import os, signal, sys\n"
        "from vafn_gym.files import atomic_write\n"
        "def write(tmp):\n"
        "    tmp.write_bytes(b'half')\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
        "atomic_write(sys.argv[1], write)\n"
    )
    result = subprocess.run([sys.executable, "-c", killed, str(target)], timeout=60)
    assert result.returncode == -signal.SIGKILL
    leftovers = [p for p in tmp_path.iterdir() if p.name.endswith(".tmp.zip")]
    assert len(leftovers) == 1 and target.read_bytes() == b"old"
    live = tmp_path / f".model.zip.{os.getpid()}-{'a' * 16}.tmp.zip"  # a save in progress (this process): kept
    live.write_bytes(b"writing")
    other = tmp_path / ".model.zip.bak.tmp.zip"  # not a temporary file of ours: kept
    other.write_bytes(b"x")

    def fail(tmp):
        tmp.write_bytes(b"partial")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, fail)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([target.name, live.name, other.name])
    assert target.read_bytes() == b"old"
