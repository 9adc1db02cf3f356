"""Tests of the Dynamic Instruction Queue and its arrival processes."""

from __future__ import annotations

import itertools
import threading
import time

import numpy as np
import pytest

from vafn_gym.instructions import Instruction
from vafn_gym.queue import (
    DROPPED_HISTORY,
    ArrivalProcess,
    InstructionQueue,
    PoissonArrivals,
    QueuedInstruction,
    QueueFullError,
    ScheduledArrivals,
)


def codes(entries) -> list[str]:
    return [entry.instruction.to_code() for entry in entries]


class FakeClock:
    """A clock that advances by one second per reading."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        self.now += 1.0
        return self.now


# --- FIFO basics ---
def test_fifo_order_and_counters():
    queue = InstructionQueue()
    for code in ["1", "2,3", "3,1,2", "2"]:
        queue.enqueue(code)
    assert len(queue) == 4
    assert codes(queue.dequeue() for _ in range(4)) == ["1", "2,3", "3,1,2", "2"]
    assert queue.dequeue() is None
    assert (queue.enqueued, queue.dequeued, queue.dropped) == (4, 4, 0)


def test_peek_does_not_remove():
    queue = InstructionQueue()
    assert queue.peek() is None
    first = queue.enqueue([2, 3])
    queue.enqueue([1])
    assert queue.peek() is first
    assert queue.peek() is first
    assert len(queue) == 2
    assert queue.dequeue() is first
    assert queue.peek().instruction == Instruction.from_arms([1])


def test_snapshot_and_iteration_are_copies():
    queue = InstructionQueue()
    queue.enqueue("1,2")
    queue.enqueue("3")
    snap = queue.snapshot()
    assert codes(snap) == ["1,2", "3"]
    snap.clear()
    assert len(queue) == 2
    iterator = iter(queue)
    queue.enqueue("2")  # must not disturb an iteration in progress
    queue.dequeue()
    assert codes(iterator) == ["1,2", "3"]
    assert codes(queue) == ["3", "2"]


def test_hold_state():
    queue = InstructionQueue()
    assert queue.holding
    queue.enqueue("1")
    assert not queue.holding
    queue.dequeue()
    assert queue.holding


def test_clear_returns_everything():
    queue = InstructionQueue()
    entries = [queue.enqueue(str(arm)) for arm in (1, 2, 3)]
    assert queue.clear() == entries
    assert len(queue) == 0 and queue.holding
    assert queue.cleared == 3 and queue.dequeued == 0
    assert queue.clear() == []


def test_entry_fields_and_metadata_copy():
    queue = InstructionQueue(clock=FakeClock())
    meta = {"latency": 0.25, "confidence": 0.9}
    entry = queue.enqueue("2,3,1", source="speech", metadata=meta)
    meta["latency"] = 99.0
    assert isinstance(entry, QueuedInstruction)
    assert entry.payload == Instruction.from_arms([2, 3, 1])  # validate=True stores the Instruction
    assert isinstance(entry.payload, Instruction)
    assert entry.source == "speech"
    assert entry.metadata == {"latency": 0.25, "confidence": 0.9}
    assert entry.arrival_time == 101.0 and entry.sequence == 0
    assert queue.enqueue("1").metadata == {}
    with pytest.raises(AttributeError):
        entry.sequence = 5  # type: ignore[misc]
    hash(queue.enqueue([1, 2], validate=False, metadata={"k": [1]}))  # unhashable payload/metadata still hash


def test_timestamps_and_sequence_are_monotonic():
    queue = InstructionQueue(capacity=1000)
    entries = [queue.enqueue("1") for _ in range(200)]
    assert [entry.sequence for entry in entries] == list(range(200))
    times = [entry.arrival_time for entry in entries]
    assert times == sorted(times)
    before = time.perf_counter()
    latest = queue.enqueue("2")
    assert before <= latest.arrival_time <= time.perf_counter()  # default clock is perf_counter


# --- validation ---
@pytest.mark.parametrize(
    "kwargs", [{"capacity": 0}, {"capacity": -3}, {"capacity": 2.5}, {"capacity": True}, {"overflow": "drop_newest"},
               {"overflow": None}, {"clock": 5}]
)
def test_constructor_validation(kwargs):
    with pytest.raises(ValueError):
        InstructionQueue(**kwargs)


def test_read_only_configuration():
    queue = InstructionQueue(capacity=3, overflow="drop_oldest")
    assert (queue.capacity, queue.overflow) == (3, "drop_oldest")
    with pytest.raises(AttributeError):
        queue.capacity = 10  # type: ignore[misc]


@pytest.mark.parametrize(
    "bad",
    ["2,4", [0], "1,x", [1] * 11, "[1,2", None, 7, [1.5], {"arm": 1}, "2,,3", {1, 2}, b"\xff", "[" * 1000,
     '[{"arm":2,"target":[0,0,1' + "0" * 310 + "]}]", '[{"arm": 2, "targt": [0, 0, 0.3]}]', [True], ["1"]],
)
def test_malformed_input_raises_and_leaves_queue_unchanged(bad):
    queue = InstructionQueue(clock=FakeClock(), n_arms=3)
    queue.enqueue("1")
    before = queue.snapshot()
    with pytest.raises(ValueError) as error:
        queue.enqueue(bad)
    assert type(error.value) is ValueError and len(str(error.value)) < 200
    assert queue.snapshot() == before
    assert queue.enqueued == 1
    assert queue.enqueue("2").sequence == 1  # the rejected item consumed no sequence number


def test_validate_false_defers_the_error_to_the_consumer():
    queue = InstructionQueue()
    raw = [0, 4]
    entry = queue.enqueue(raw, validate=False, source="stream")
    assert entry.payload is raw
    good = queue.enqueue("3 1", validate=False)
    assert good.payload == "3 1"
    assert len(queue) == 2
    with pytest.raises(ValueError, match="arm"):
        _ = queue.dequeue().instruction
    with pytest.raises(ValueError):
        _ = queue.enqueue(None, validate=False).instruction  # not a sequence of arm ids
    assert queue.dequeue().instruction == Instruction.from_arms([3, 1])


def test_n_arms_is_checked_on_enqueue_and_on_deferred_parsing():
    queue = InstructionQueue(n_arms=3)
    assert queue.n_arms == 3 and InstructionQueue().n_arms is None
    with pytest.raises(ValueError, match=r"waypoint 1: arm 4 is outside the allowed range 1\.\.3"):
        queue.enqueue(Instruction.parse("2,4"))
    assert InstructionQueue().enqueue("2,4").instruction.arms == (2, 4)
    entry = queue.enqueue("2,4", validate=False)
    with pytest.raises(ValueError, match="arm 4"):
        _ = entry.instruction
    for bad in (0, True, 2.5, "3"):
        with pytest.raises(ValueError, match="n_arms"):
            InstructionQueue(n_arms=bad)


@pytest.mark.parametrize("payload", ['[{"arm":2,"target":[0,0,1' + "0" * 310 + "]}]", "[" * 1000, b"\xff\xfe", {3, 1},
                                     "２,３", object(), [[1] * 3] * 2, [10**5000]], ids=range(8))
def test_deferred_parsing_raises_only_short_value_errors(payload):
    entry = InstructionQueue().enqueue(payload, validate=False)
    with pytest.raises(ValueError) as error:
        _ = entry.instruction
    assert type(error.value) is ValueError and len(str(error.value)) < 200


@pytest.mark.parametrize("kwargs", [{"source": 5}, {"metadata": [("a", 1)]}, {"metadata": "x"}])
def test_enqueue_rejects_bad_source_and_metadata(kwargs):
    queue = InstructionQueue()
    with pytest.raises(ValueError):
        queue.enqueue("1", **kwargs)
    assert queue.enqueued == 0


def test_queue_full_message_is_short_even_for_huge_payloads():
    queue = InstructionQueue(capacity=1)
    queue.enqueue("1")
    with pytest.raises(QueueFullError) as error:
        queue.enqueue("[" + ",".join(["1"] * 5) + "]" + " " * 50_000, source="s" * 10_000)
    assert len(str(error.value)) < 250


@pytest.mark.parametrize("timeout", [-1.0, float("nan"), "1", True, -float("inf")])
def test_dequeue_rejects_bad_timeouts(timeout):
    queue = InstructionQueue()
    for get in (queue.dequeue, queue.get_unacked):
        with pytest.raises(ValueError, match="timeout"):
            get(timeout=timeout)


@pytest.mark.parametrize("forever", [float("inf"), 1e300, np.float64("inf")])
def test_infinite_timeout_waits_forever(forever):
    queue = InstructionQueue()
    got: list = []
    consumer = threading.Thread(target=lambda: got.append(queue.dequeue(timeout=forever)))
    consumer.start()
    time.sleep(0.05)
    assert consumer.is_alive() and got == []
    queue.enqueue("2")
    consumer.join(timeout=5.0)
    assert not consumer.is_alive() and got[0].instruction.arms == (2,)


# --- overflow ---
def test_overflow_raise_changes_nothing():
    queue = InstructionQueue(capacity=2, overflow="raise")
    first, second = queue.enqueue("1"), queue.enqueue("2")
    with pytest.raises(QueueFullError):
        queue.enqueue("3")
    assert issubclass(QueueFullError, RuntimeError)
    assert queue.snapshot() == [first, second]
    assert (queue.enqueued, queue.dropped, queue.dropped_items) == (2, 0, [])
    queue.dequeue()
    assert queue.enqueue("3").sequence == 2


def test_overflow_drop_oldest_counts_and_keeps_evicted():
    queue = InstructionQueue(capacity=3, overflow="drop_oldest")
    entries = [queue.enqueue(code) for code in ["1", "2", "3", "1,2", "2,3"]]
    assert queue.snapshot() == entries[2:]
    assert queue.dropped == 2
    assert queue.dropped_items == entries[:2]
    assert queue.enqueued == 5
    queue.dropped_items.clear()  # a copy
    assert len(queue.dropped_items) == 2


def test_dropped_items_history_is_bounded():
    queue = InstructionQueue(capacity=1, overflow="drop_oldest")
    entries = [queue.enqueue("1", validate=False) for _ in range(DROPPED_HISTORY + 50)]
    assert queue.dropped == DROPPED_HISTORY + 49
    assert queue.dropped_items == entries[49:-1]
    assert queue.snapshot() == entries[-1:]


# --- blocking dequeue ---
def test_blocking_dequeue_wakes_on_enqueue_from_another_thread():
    queue = InstructionQueue()
    got: list = []
    consumer = threading.Thread(target=lambda: got.append((queue.dequeue(timeout=10.0), time.perf_counter())))
    consumer.start()
    time.sleep(0.1)
    assert consumer.is_alive() and got == []  # it really blocks
    sent = queue.enqueue("2,1")
    consumer.join(timeout=5.0)
    assert not consumer.is_alive()
    entry, woke = got[0]
    assert entry is sent
    assert woke - sent.arrival_time < 1.0  # woken by the notify, not by the 10 s timeout


def test_dequeue_forever_waits_for_an_item():
    queue = InstructionQueue()
    got: list = []
    consumer = threading.Thread(target=lambda: got.append(queue.dequeue(timeout=None)))
    consumer.start()
    time.sleep(0.05)
    assert consumer.is_alive()
    queue.enqueue("3")
    consumer.join(timeout=5.0)
    assert not consumer.is_alive() and got[0].instruction.arms == (3,)


def test_dequeue_timeout_expires_with_none():
    queue = InstructionQueue()
    start = time.perf_counter()
    assert queue.dequeue(timeout=0.05) is None
    assert 0.045 <= time.perf_counter() - start < 1.0
    start = time.perf_counter()
    assert queue.dequeue() is None  # default: non-blocking
    assert time.perf_counter() - start < 0.04


# --- acknowledged dequeue ---
def _accounted(queue: InstructionQueue) -> bool:
    return queue.enqueued == queue.dequeued + queue.dropped + queue.cleared + len(queue) + queue.in_flight


def test_take_acknowledges_when_the_block_completes():
    queue = InstructionQueue()
    first, second = queue.enqueue("1"), queue.enqueue("2")
    with queue.take() as entry:
        assert entry is first
        assert (len(queue), queue.in_flight, queue.unacked(), queue.peek()) == (1, 1, [first], second)
        assert queue.snapshot() == [second] and list(queue) == [second] and _accounted(queue)
    assert (len(queue), queue.in_flight, queue.dequeued, queue.requeued) == (1, 0, 1, 0)
    assert _accounted(queue)


def test_take_puts_the_entry_back_at_the_head_when_the_block_raises():
    queue = InstructionQueue(clock=FakeClock())
    entries = [queue.enqueue(code) for code in ("1", "2", "3")]
    for error in (RuntimeError("boom"), KeyboardInterrupt(), SystemExit(1)):
        with pytest.raises(type(error)):
            with queue.take() as entry:
                assert entry is entries[0]
                raise error
        assert queue.snapshot() == entries and queue.peek() is entries[0]  # same object: sequence and stamp kept
        assert queue.in_flight == 0 and _accounted(queue)
    assert (queue.requeued, queue.dequeued) == (3, 0)
    assert queue.dequeue() is entries[0] and entries[0].arrival_time == 101.0 and entries[0].sequence == 0


def test_take_on_an_empty_queue_yields_none_and_may_wait():
    queue = InstructionQueue()
    with queue.take() as entry:
        assert entry is None
    start = time.perf_counter()
    with queue.take(timeout=0.05) as entry:
        assert entry is None
    assert time.perf_counter() - start >= 0.045
    threading.Timer(0.05, lambda: queue.enqueue("3")).start()
    with queue.take(timeout=float("inf")) as entry:
        assert entry.instruction.arms == (3,)
    assert queue.dequeued == 1 and _accounted(queue)


def test_the_block_may_settle_the_entry_itself():
    queue = InstructionQueue()
    queue.enqueue("1")
    with queue.take() as entry:
        queue.nack(entry)
    assert len(queue) == 1 and queue.dequeued == 0
    with pytest.raises(ValueError, match="bad instruction"):
        with queue.take() as entry:
            queue.ack(entry)
            raise ValueError("bad instruction")
    assert len(queue) == 0 and queue.dequeued == 1 and queue.requeued == 1 and _accounted(queue)


def test_ack_and_nack_need_an_entry_in_flight():
    queue = InstructionQueue()
    ready = queue.enqueue("1")
    with pytest.raises(ValueError, match="not in flight"):
        queue.ack(ready)  # never taken
    entry = queue.get_unacked()
    assert entry is ready
    queue.ack(entry)
    for settle in (queue.ack, queue.nack):
        with pytest.raises(ValueError, match="not in flight"):
            settle(entry)  # already acknowledged
    other = InstructionQueue()
    other.enqueue("1")
    foreign = other.get_unacked()
    queue.enqueue("2")
    queue.get_unacked()
    with pytest.raises(ValueError, match="not in flight"):
        queue.ack(foreign)  # same sequence number, other queue
    with pytest.raises(ValueError):
        queue.nack("1")  # type: ignore[arg-type]
    assert queue.in_flight == 1 and _accounted(queue)


def test_nacked_entries_keep_arrival_order_among_themselves():
    queue = InstructionQueue()
    entries = [queue.enqueue(str(arm)) for arm in (1, 2, 3, 1)]
    a, b, c = (queue.get_unacked() for _ in range(3))
    queue.nack(a)
    queue.nack(c)
    queue.nack(b)
    assert queue.snapshot() == entries
    assert [e.sequence for e in queue.unacked()] == []


def test_nack_on_a_full_queue_never_loses_the_entry():
    for overflow in ("raise", "drop_oldest"):
        queue = InstructionQueue(capacity=2, overflow=overflow)
        first = queue.enqueue("1")
        taken = queue.get_unacked()
        queue.enqueue("2")
        queue.enqueue("3")  # in-flight entries do not count toward the capacity
        queue.nack(taken)
        assert len(queue) == 3 and queue.snapshot()[0] is first and queue.dropped == 0
        if overflow == "raise":
            with pytest.raises(QueueFullError):
                queue.enqueue("1,2")
            assert len(queue) == 3
        else:
            queue.enqueue("1,2")
            assert queue.dropped_items[0] is first and queue.dropped == 2 and len(queue) == 2
        assert _accounted(queue)


def test_clear_and_discard_leave_in_flight_entries_alone():
    queue = InstructionQueue()
    taken = queue.enqueue("1", source="process")
    queue.enqueue("2", source="process")
    assert queue.get_unacked() is taken
    assert len(queue.discard(lambda e: e.source == "process")) == 1
    assert queue.clear() == [] and queue.unacked() == [taken]
    queue.nack(taken)
    assert queue.snapshot() == [taken] and _accounted(queue)


def test_blocked_consumer_wakes_on_nack():
    queue = InstructionQueue()
    queue.enqueue("2")
    entry = queue.get_unacked()
    got: list = []
    consumer = threading.Thread(target=lambda: got.append(queue.dequeue(timeout=10.0)))
    consumer.start()
    time.sleep(0.05)
    assert consumer.is_alive()
    queue.nack(entry)
    consumer.join(timeout=5.0)
    assert not consumer.is_alive() and got == [entry]


# --- concurrency ---
PRODUCERS, PER_PRODUCER = 4, 2500


def _run_producers_and_consumer(queue: InstructionQueue) -> list[QueuedInstruction]:
    """4 producers x 2,500 enqueues (retrying while full) while one consumer drains; returns what was consumed."""
    payloads = [Instruction.from_arms([arm]) for arm in (1, 2, 3)]
    start = threading.Barrier(PRODUCERS + 1)
    errors: list[BaseException] = []

    def produce(producer: int) -> None:
        try:
            start.wait()
            for index in range(PER_PRODUCER):
                while True:
                    try:
                        queue.enqueue(payloads[index % 3], source=f"p{producer}",
                                      metadata={"producer": producer, "index": index})
                        break
                    except QueueFullError:
                        time.sleep(0)  # back-pressure: let the consumer run
        except BaseException as error:  # noqa: BLE001 - pragma: no cover - reported below
            errors.append(error)

    threads = [threading.Thread(target=produce, args=(p,)) for p in range(PRODUCERS)]
    for thread in threads:
        thread.start()
    consumed: list[QueuedInstruction] = []
    start.wait()
    deadline = time.monotonic() + 15.0
    while (any(t.is_alive() for t in threads) or len(queue)) and time.monotonic() < deadline:
        entry = queue.dequeue(timeout=0.05)
        if entry is not None:
            consumed.append(entry)
    for thread in threads:
        thread.join(timeout=5.0)
    assert not errors, errors
    assert not any(t.is_alive() for t in threads), "producers did not finish"
    return consumed


def _assert_order(consumed: list[QueuedInstruction]) -> None:
    sequences = [entry.sequence for entry in consumed]
    assert sequences == sorted(sequences) and len(set(sequences)) == len(sequences)  # global FIFO, no duplicates
    times = [entry.arrival_time for entry in consumed]
    assert times == sorted(times)  # timestamps taken under the lock: arrival order == sequence order
    for producer in range(PRODUCERS):
        indices = [e.metadata["index"] for e in consumed if e.metadata["producer"] == producer]
        assert indices == sorted(indices), f"producer {producer} order broken"
        assert all(e.source == f"p{producer}" for e in consumed if e.metadata["producer"] == producer)


def test_concurrent_producers_nothing_lost_or_duplicated():
    queue = InstructionQueue(capacity=64, overflow="raise")
    consumed = _run_producers_and_consumer(queue)
    keys = [(e.metadata["producer"], e.metadata["index"]) for e in consumed]
    assert len(keys) == PRODUCERS * PER_PRODUCER
    assert set(keys) == set(itertools.product(range(PRODUCERS), range(PER_PRODUCER)))
    _assert_order(consumed)
    for producer in range(PRODUCERS):
        indices = [e.metadata["index"] for e in consumed if e.metadata["producer"] == producer]
        assert indices == list(range(PER_PRODUCER))
    assert (queue.enqueued, queue.dequeued, queue.dropped, len(queue)) == (10_000, 10_000, 0, 0)
    assert [e.sequence for e in consumed] == list(range(10_000))


def test_concurrent_producers_with_drop_oldest_account_for_everything():
    queue = InstructionQueue(capacity=8, overflow="drop_oldest")
    consumed = _run_producers_and_consumer(queue)
    _assert_order(consumed)
    assert len(consumed) + queue.dropped == PRODUCERS * PER_PRODUCER
    assert queue.enqueued == PRODUCERS * PER_PRODUCER and queue.dequeued == len(consumed)
    seen = {e.sequence for e in consumed} | {e.sequence for e in queue.dropped_items}
    assert len(seen) == len(consumed) + len(queue.dropped_items)  # an entry is consumed or dropped, never both


# --- arrival processes ---
def test_arrival_process_is_abstract():
    with pytest.raises(TypeError):
        ArrivalProcess()  # type: ignore[abstract]


def test_scheduled_arrivals_and_feed():
    inst = Instruction.from_arms([3, 2, 1])
    process = ScheduledArrivals({5: inst, 0: "1,2", 3: ["2", [3, 1]], 4: [2, 3], 6: []})
    assert process.steps == (0, 3, 4, 5, 6) and process.last_step == 6
    assert process.arrivals(0) == [Instruction.from_arms([1, 2])]
    assert process.arrivals(1) == []
    assert process.arrivals(3) == [Instruction.from_arms([2]), Instruction.from_arms([3, 1])]
    assert process.arrivals(4) == [Instruction.from_arms([2, 3])]  # a list of numbers is one instruction
    assert process.arrivals(6) == [Instruction()]
    assert process.num_instructions == 6
    queue = InstructionQueue()
    fed = [entry for step in range(10) for entry in process.feed(queue, step)]
    assert len(fed) == 6 and queue.snapshot() == fed
    assert [e.metadata["step"] for e in fed] == [0, 3, 3, 4, 5, 6]
    assert {e.source for e in fed} == {"schedule"}
    assert fed[4].payload is inst
    assert process.feed(InstructionQueue(), 0, source="script")[0].source == "script"
    process.arrivals(0).clear()  # a new list each time
    assert process.arrivals(0) == [Instruction.from_arms([1, 2])]


@pytest.mark.parametrize(
    "schedule, match",
    [({0: "1", 7: "1,4"}, "step 7"), ({2: ["1", "0"]}, "step 2, instruction 1"), ({-1: "1"}, "step -1"),
     ({"3": "1"}, "step '3'"), ({4: None}, "step 4")],
)
def test_scheduled_arrivals_validate_at_construction(schedule, match):
    with pytest.raises(ValueError, match=match):
        ScheduledArrivals(schedule, n_arms=3)
    with pytest.raises(ValueError, match="n_arms"):
        ScheduledArrivals({}, n_arms=0)


def test_scheduled_arrivals_feed_raises_when_full():
    process = ScheduledArrivals({0: ["1", "2", "3"]})
    queue = InstructionQueue(capacity=2)
    with pytest.raises(QueueFullError):
        process.feed(queue, 0)
    assert codes(queue) == ["1", "2"]


def _uniform_sampler(rng: np.random.Generator) -> Instruction:
    return Instruction.from_arms(rng.integers(1, 4, size=int(rng.integers(1, 6))).tolist())


def _trace(process: PoissonArrivals, steps: int = 300) -> list[tuple[int, ...]]:
    return [tuple(i.arms for i in process.arrivals(step)) for step in range(steps)]


def test_poisson_same_seed_same_arrivals():
    a = PoissonArrivals(rate=0.3, sampler=_uniform_sampler, burst_probability=0.05, seed=7)
    b = PoissonArrivals(rate=0.3, sampler=_uniform_sampler, burst_probability=0.05, seed=7)
    trace = _trace(a)
    assert sum(map(len, trace)) > 50
    assert trace == _trace(b)
    assert trace == _trace(a)  # replaying steps gives the same answer
    assert [a.arrivals(s) for s in (250, 3, 99)] == [b.arrivals(s) for s in (250, 3, 99)]  # order-independent
    assert a.seed == 7


def test_poisson_different_seeds_differ_and_reset_reseeds():
    process = PoissonArrivals(rate=0.3, sampler=_uniform_sampler, seed=1)
    first = _trace(process)
    process.reset(seed=2)
    second = _trace(process)
    assert first != second
    process.reset(seed=1)
    assert _trace(process) == first
    process.reset()  # fresh entropy
    assert _trace(process) != first
    assert PoissonArrivals(rate=0.3, sampler=_uniform_sampler).seed != PoissonArrivals(
        rate=0.3, sampler=_uniform_sampler).seed


def test_poisson_rate_matches():
    process = PoissonArrivals(rate=0.5, instructions=["1"], seed=3)
    counts = np.array([len(process.arrivals(step)) for step in range(4000)])
    assert 0.45 < counts.mean() < 0.55
    assert 0.43 < counts.var() < 0.57  # Poisson: variance == mean
    assert PoissonArrivals(rate=0.0, instructions=["1"], seed=3).arrivals(10) == []


def test_poisson_bursts():
    always = PoissonArrivals(rate=0.0, instructions=["1"], burst_probability=1.0, burst_size=(3, 3), seed=0)
    assert all(len(always.arrivals(step)) == 3 for step in range(50))
    sometimes = PoissonArrivals(rate=0.0, instructions=["1"], burst_probability=0.1, burst_size=(2, 4), seed=0)
    counts = np.array([len(sometimes.arrivals(step)) for step in range(3000)])
    assert set(np.unique(counts)) == {0, 2, 3, 4}
    assert 0.08 < (counts > 0).mean() < 0.12


def test_poisson_fixed_list_and_feed():
    pool = ["1,2", [3], Instruction.from_arms([2, 1, 3])]
    process = PoissonArrivals(rate=2.0, instructions=pool, seed=11)
    drawn = [inst for step in range(200) for inst in process.arrivals(step)]
    assert {inst.to_code() for inst in drawn} == {"1,2", "3", "2,1,3"}
    queue = InstructionQueue(capacity=1000)
    fed = process.feed(queue, 17)
    assert [e.instruction for e in fed] == process.arrivals(17)
    assert all(e.source == "poisson" and e.metadata == {"step": 17} for e in fed)


def test_poisson_sampler_receives_a_generator_and_bad_output_names_the_step():
    received = []

    def sampler(rng):
        received.append(rng)
        return "1,4"

    process = PoissonArrivals(rate=5.0, sampler=sampler, seed=0, n_arms=3)
    with pytest.raises(ValueError, match="step 12"):
        process.arrivals(12)
    assert isinstance(received[0], np.random.Generator)


@pytest.mark.parametrize(
    "kwargs",
    [dict(rate=-0.1, instructions=["1"]), dict(rate=float("nan"), instructions=["1"]),
     dict(rate=1.0), dict(rate=1.0, instructions=["1"], sampler=_uniform_sampler),
     dict(rate=1.0, instructions=[]), dict(rate=1.0, instructions=["1", "5"], n_arms=3),
     dict(rate=1.0, instructions="1,2"), dict(rate=1.0, instructions=["1"], n_arms=-2),
     dict(rate=1.0, instructions=["1"], burst_probability=1.5), dict(rate=1.0, instructions=["1"], burst_size=(0, 2)),
     dict(rate=1.0, instructions=["1"], burst_size=(4, 2)), dict(rate=1.0, instructions=["1"], burst_size=3),
     dict(rate=1.0, instructions=["1"], seed=-1), dict(rate=1.0, sampler="not callable")],
)
def test_poisson_validation(kwargs):
    with pytest.raises(ValueError):
        PoissonArrivals(**kwargs)


@pytest.mark.parametrize("step", [-1, 1.5, True])
def test_arrivals_reject_bad_steps(step):
    with pytest.raises(ValueError):
        PoissonArrivals(rate=1.0, instructions=["1"], seed=0).arrivals(step)
    with pytest.raises(ValueError):
        ScheduledArrivals({0: "1"}).arrivals(step)


def test_discard_removes_matching_entries_and_keeps_the_rest_untouched():
    queue = InstructionQueue()
    kept = queue.enqueue("1", source="user")
    queue.enqueue("2", source="process")
    later = queue.enqueue("3", source="user")
    removed = queue.discard(lambda entry: entry.source == "process")
    assert [e.payload.arms for e in removed] == [(2,)]
    assert queue.snapshot() == [kept, later]  # same entries: sequence numbers and timestamps unchanged
    assert queue.cleared == 1 and queue.enqueued == queue.dequeued + queue.dropped + queue.cleared + len(queue)
    assert queue.discard(lambda entry: False) == []


# --- the multimedia stream feeding the queue (a stub generator: no model needed) ---
class _CodeGenerator:
    """Transcribes ``code=`` only, like the real generator's code path, and fails on anything else."""

    def transcribe(self, audio=None, image=None, code=None, sample_rate=None):
        from types import SimpleNamespace

        if code is None:
            raise SystemExit("no code given")  # the worst a generator can do to a thread
        return SimpleNamespace(instruction=Instruction.coerce(code), confidence=1.0, confidences=(1.0,),
                               low_confidence=False, method="code", warnings=(), modalities=("code",))


def test_stream_stop_and_wait_return_at_once_when_never_started():
    from vafn_media.stream import MultimediaStream

    stream = MultimediaStream(InstructionQueue(), _CodeGenerator())
    assert stream.wait() is True  # nothing pending
    stream.submit(code="1")
    outcome: list = []
    waiter = threading.Thread(target=lambda: outcome.append((stream.wait(), stream.stop(), stream.stop(drain=False))))
    waiter.start()
    waiter.join(timeout=2.0)
    assert not waiter.is_alive(), "wait()/stop() hung on a stream that was never started"
    assert outcome == [(False, None, None)] and not stream.alive


@pytest.mark.parametrize("fatal", [SystemExit, KeyboardInterrupt, RuntimeError])
def test_stream_worker_survives_callbacks_and_generators_raising_anything(fatal):
    from vafn_media.stream import MultimediaStream

    def callback(event):
        if event.ticket == 0:
            raise fatal("callback failed")

    queue = InstructionQueue()
    stream = MultimediaStream(queue, _CodeGenerator(), on_event=callback).start()
    stream.submit(code="1")  # its callback raises
    stream.submit(audio=np.zeros(10))  # the generator raises SystemExit
    stream.submit(code="2,3")
    drained, alive = stream.wait(timeout=5.0), stream.alive
    stream.stop(drain=False, timeout=5.0)
    assert drained and alive and not stream.alive
    assert [event.status for event in stream.events] == ["enqueued", "error", "enqueued"]
    assert "SystemExit" in stream.events[1].message
    assert codes(queue) == ["1", "2,3"]
    assert len(stream.errors) == 1 and fatal.__name__ in stream.errors[0] and "ticket 0" in stream.errors[0]
