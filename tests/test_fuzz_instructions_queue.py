"""Property-based and stress tests of the instruction parser and the instruction queue (issue 13: reliability).

Sized to run in well under a minute on two cores; no example database is written (``database=None``).
"""

from __future__ import annotations

import itertools
import json
import random
import threading
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from vafn_gym.constants import MAX_INSTRUCTION_LENGTH
from vafn_gym.instructions import Instruction, Waypoint
from vafn_gym.queue import InstructionQueue, QueuedInstruction, QueueFullError

FUZZ = settings(max_examples=150, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
#: Longest error message any malformed input may produce.
MESSAGE_LIMIT = 300

# --- strategies ---
arm_ids = st.integers(min_value=1, max_value=9)
coordinates = st.tuples(
    st.floats(-0.75, 0.75), st.floats(-0.75, 0.75), st.floats(0.06, 1.0)  # 0.05 is float32 in the workspace box
)
waypoints = st.builds(Waypoint, arm_ids, st.none() | coordinates)
instructions = st.lists(waypoints, max_size=MAX_INSTRUCTION_LENGTH).map(Instruction)
huge_numbers = st.sampled_from([10**310, -(10**310), 1e308, float("inf"), float("nan")]) | st.integers(4400, 6000).map(
    lambda digits: 10**digits  # beyond the int -> str limit: even repr() fails on it
)
json_scalars = st.none() | st.booleans() | st.integers() | huge_numbers | st.floats() | st.text(max_size=8)
json_like = st.recursive(
    json_scalars,
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.sampled_from(["arm", "target", "waypoints", "targt"]) | st.text(max_size=4), children,
                      max_size=3),
    max_leaves=16,
)
near_waypoints = st.fixed_dictionaries(
    {"arm": json_scalars | arm_ids}, optional={"target": st.lists(json_scalars | st.floats(0.06, 0.7), max_size=4)}
)
nested = st.integers(1, 3000).map(lambda depth: "[" * depth + "1" + "]" * depth)
texts = st.text(max_size=60) | st.text(alphabet="0123456789,; []<>{}-+.\n", max_size=40) | nested
unordered = st.sets(arm_ids, min_size=2) | st.frozensets(arm_ids, min_size=2) | st.dictionaries(arm_ids, arm_ids)


def _attempt(build, value) -> Instruction | None:
    """Run ``build(value)``: it must return an Instruction or raise a short ``ValueError`` (never anything else)."""
    try:
        result = build(value)
    except ValueError as error:
        assert type(error) is ValueError, f"{type(error).__name__}: {error}"  # not a decoder's subclass either
        assert len(str(error)) < MESSAGE_LIMIT, str(error)[:500]
        return None
    assert isinstance(result, Instruction)
    return result


# --- parser properties ---
@FUZZ
@given(instructions)
def test_round_trips(instruction):
    assert Instruction.from_json(instruction.to_json()) == instruction
    assert Instruction.from_json(json.loads(instruction.to_json())) == instruction
    assert Instruction.coerce(instruction.to_json().encode()) == instruction
    for code in (instruction.to_code(), str(instruction), instruction.to_code().replace(",", " "),
                 "<" + instruction.to_code().replace(",", ";") + ">"):
        assert Instruction.parse(code).arms == instruction.arms
    assert Instruction.parse(instruction.to_code()).has_default_targets
    assert hash(Instruction.from_json(instruction.to_json())) == hash(instruction)
    assert eval(repr(instruction).replace("Instruction(", "Instruction.coerce(")) == instruction


@FUZZ
@given(st.lists(arm_ids, max_size=MAX_INSTRUCTION_LENGTH), st.integers(1, 9))
def test_n_arms_accepts_exactly_the_arms_in_range(arms, n_arms):
    accepted = all(arm <= n_arms for arm in arms)
    code = ",".join(map(str, arms))
    for build in (lambda: Instruction.parse(code, n_arms=n_arms), lambda: Instruction.from_arms(arms, n_arms=n_arms),
                  lambda: Instruction.from_json(json.dumps(arms), n_arms=n_arms),
                  lambda: Instruction.coerce(Instruction.from_arms(arms), n_arms=n_arms)):
        assert (_attempt(lambda _, build=build: build(), None) is not None) == accepted
    if not accepted:
        with pytest.raises(ValueError, match=f"allowed range 1..{n_arms}"):
            Instruction.from_arms(arms).check_arms(n_arms)


@FUZZ
@given(st.lists(arm_ids, min_size=1, max_size=5), st.data())
def test_empty_tokens_are_rejected(arms, data):
    tokens = [str(arm) for arm in arms]
    tokens.insert(data.draw(st.integers(0, len(tokens))), data.draw(st.sampled_from(["", " ", "  "])))
    separator = data.draw(st.sampled_from([",", ";", ", "]))
    with pytest.raises(ValueError, match="empty"):
        Instruction.parse(separator.join(tokens))


@FUZZ
@given(texts)
def test_any_text_parses_or_raises_a_short_value_error(text):
    result = _attempt(Instruction.parse, text)
    if result is not None:
        assert text.isascii() and len(result) <= MAX_INSTRUCTION_LENGTH
    _attempt(Instruction.coerce, text.encode("utf-8", "surrogatepass"))


@FUZZ
@given(st.binary(max_size=80))
def test_any_bytes_coerce_or_raise_a_short_value_error(blob):
    _attempt(Instruction.coerce, blob)


@FUZZ
@given(json_like | st.lists(near_waypoints, max_size=4) | unordered)
def test_any_document_builds_or_raises_a_short_value_error(document):
    for build in (Instruction.coerce, Instruction.from_json, Instruction.from_arms):
        _attempt(build, document)
    try:
        text = json.dumps(document)
    except (TypeError, ValueError):  # a set, or an int json cannot print
        return
    _attempt(Instruction.parse, text)
    _attempt(Instruction.from_json, text)


@FUZZ
@given(unordered)
def test_unordered_containers_are_refused(container):
    with pytest.raises(ValueError):
        Instruction.coerce(container)


@FUZZ
@given(st.lists(near_waypoints, min_size=1, max_size=4), st.booleans())
def test_deferred_parsing_in_the_queue_raises_only_value_errors(document, as_text):
    queue = InstructionQueue()
    try:
        payload = json.dumps(document) if as_text else document
    except ValueError:  # an int json cannot print
        payload = document
    entry = queue.enqueue(payload, validate=False)
    _attempt(lambda _: entry.instruction, None)
    try:
        queue.enqueue(document)
    except ValueError as error:
        assert len(str(error)) < MESSAGE_LIMIT
    assert queue.enqueued in (1, 2)


# --- queue: a model-based state machine, one thread ---
class QueueMachine(RuleBasedStateMachine):
    """Drives a queue with every operation and checks it against a plain-list model."""

    @initialize(capacity=st.integers(1, 4), overflow=st.sampled_from(["raise", "drop_oldest"]))
    def start(self, capacity, overflow):
        self.told: list[int] = []  # what on_drop received
        self.queue = InstructionQueue(
            capacity=capacity, overflow=overflow, n_arms=3, on_drop=lambda entry: self.told.append(entry.sequence)
        )
        self.ready: list[int] = []
        self.held: list[QueuedInstruction] = []
        self.gone: list[int] = []
        self.evicted: list[int] = []
        self.next_sequence = 0

    @rule(code=st.sampled_from(["1", "2,3", "3,1,2"]))
    def enqueue(self, code):
        full = len(self.ready) >= self.queue.capacity
        if full and self.queue.overflow == "raise":
            with pytest.raises(QueueFullError):
                self.queue.enqueue(code)
            return
        while len(self.ready) >= self.queue.capacity:
            self.evicted.append(self.ready.pop(0))
            self.gone.append(self.evicted[-1])
        assert self.queue.enqueue(code).sequence == self.next_sequence
        self.ready.append(self.next_sequence)
        self.next_sequence += 1

    @rule(bad=st.sampled_from(["4", "0", "1,,2", "[1", None, [9], "2,x"]))
    def enqueue_malformed(self, bad):
        before = (self.queue.snapshot(), self.queue.enqueued, self.queue.dropped)
        with pytest.raises(ValueError):
            self.queue.enqueue(bad)  # checked before the queue is full or anything is evicted
        assert (self.queue.snapshot(), self.queue.enqueued, self.queue.dropped) == before

    @rule()
    def dequeue(self):
        entry = self.queue.dequeue()
        assert (entry is None) == (not self.ready)
        if entry is not None:
            assert entry.sequence == self.ready.pop(0)
            self.gone.append(entry.sequence)

    @rule()
    def get_unacked(self):
        entry = self.queue.get_unacked()
        if entry is not None:
            assert entry.sequence == self.ready.pop(0)
            self.held.append(entry)

    @precondition(lambda self: self.held)
    @rule(data=st.data(), requeue=st.booleans())
    def settle(self, data, requeue):
        entry = self.held.pop(data.draw(st.integers(0, len(self.held) - 1)))
        if requeue:
            self.queue.nack(entry)
            self.ready = sorted(self.ready + [entry.sequence])
        else:
            self.queue.ack(entry)
            self.gone.append(entry.sequence)
        with pytest.raises(ValueError):
            self.queue.ack(entry)

    @rule(fails=st.booleans())
    def take(self, fails):
        try:
            with self.queue.take() as entry:
                assert (entry is None) == (not self.ready)
                if fails:
                    raise KeyError("consumer failed")
        except KeyError:
            return
        if entry is not None:
            self.gone.append(self.ready.pop(0))

    @rule()
    def clear(self):
        assert [entry.sequence for entry in self.queue.clear()] == self.ready
        self.gone.extend(self.ready)
        self.ready = []

    @invariant()
    def matches_the_model(self):
        if not hasattr(self, "queue"):
            return
        queue = self.queue
        assert [entry.sequence for entry in queue.snapshot()] == self.ready == [e.sequence for e in queue]
        assert len(queue) == len(self.ready) and queue.holding == (not self.ready)
        assert (queue.peek().sequence if self.ready else None) == (self.ready[0] if self.ready else None)
        assert queue.unacked() == sorted(self.held, key=lambda entry: entry.sequence)
        assert queue.in_flight == len(self.held)
        assert queue.enqueued == queue.dequeued + queue.dropped + queue.cleared + len(queue) + queue.in_flight
        everything = self.ready + [entry.sequence for entry in self.held] + self.gone
        assert sorted(everything) == list(range(self.next_sequence))  # nothing lost, nothing twice
        assert self.told == self.evicted and queue.dropped == len(self.told)  # every eviction reported, uncapped


QueueMachine.TestCase.settings = settings(max_examples=60, stateful_step_count=40, deadline=None, database=None)
test_queue_state_machine = QueueMachine.TestCase


# --- queue: concurrent producers and consumers ---
def _run(queue: InstructionQueue, producers: int, per_producer: int, consumers: int, fail_rate: float,
         seed: int) -> tuple[list[tuple[int, int]], int]:
    """Producers enqueue (retrying while full); consumers ``take``, consumer 0 sometimes raising.

    Returns the keys handled (acknowledged) and the number of failures.
    """
    handled: list[tuple[int, int]] = []
    failures = [0]
    done = threading.Event()
    lock = threading.Lock()
    errors: list[BaseException] = []

    def produce(producer: int) -> None:
        try:
            for index in range(per_producer):
                while True:
                    try:
                        queue.enqueue(PAYLOAD, source="p", metadata={"key": (producer, index)})
                        break
                    except QueueFullError:
                        if errors:
                            return  # a consumer died: nobody will make room
                        time.sleep(0.0002)
        except BaseException as error:  # noqa: BLE001 - pragma: no cover - reported below
            errors.append(error)

    def consume(consumer: int) -> None:
        rng = random.Random(seed + consumer)
        flaky = consumer == 0 and fail_rate > 0
        while not (done.is_set() and queue.holding) and not errors:
            try:
                with queue.take(timeout=0.005) as entry:
                    if entry is None:
                        continue
                    if flaky and rng.random() < fail_rate:
                        raise KeyError("consumer failed while handling an entry")
                    with lock:
                        handled.append(entry.metadata["key"])
            except KeyError:
                with lock:
                    failures[0] += 1
            except BaseException as error:  # noqa: BLE001 - pragma: no cover - reported below
                errors.append(error)

    threads = [threading.Thread(target=produce, args=(p,)) for p in range(producers)]
    workers = [threading.Thread(target=consume, args=(c,)) for c in range(consumers)]
    for thread in threads + workers:
        thread.start()
    for thread in threads:
        thread.join(timeout=60.0)
    done.set()
    for thread in workers:
        thread.join(timeout=30.0)
    assert not errors, errors
    assert not any(thread.is_alive() for thread in threads + workers), "a producer or consumer hung"
    return handled, failures[0]


PAYLOAD = Instruction.from_arms([2, 1])


def test_8_producers_2_consumers_one_failing_lose_and_duplicate_nothing():
    producers, per_producer = 8, 5_000
    queue = InstructionQueue(capacity=64, overflow="raise")
    handled, failures = _run(queue, producers, per_producer, consumers=2, fail_rate=0.02, seed=13)
    expected = set(itertools.product(range(producers), range(per_producer)))
    duplicated = len(handled) - len(set(handled))
    lost = len(expected - set(handled))
    assert (lost, duplicated) == (0, 0)
    assert failures > 100  # the failing consumer really failed, and every failed entry came back
    assert queue.requeued == failures
    assert (queue.enqueued, queue.dequeued, queue.dropped, len(queue), queue.in_flight) == (40_000, 40_000, 0, 0, 0)


@settings(max_examples=12, deadline=None, database=None)
@given(
    producers=st.integers(1, 4),
    per_producer=st.integers(1, 300),
    consumers=st.integers(1, 3),
    capacity=st.integers(1, 8),
    overflow=st.sampled_from(["raise", "drop_oldest"]),
    fail_rate=st.sampled_from([0.0, 0.1]),
    seed=st.integers(0, 1000),
)
def test_concurrent_queue_accounts_for_every_entry(producers, per_producer, consumers, capacity, overflow, fail_rate,
                                                   seed):
    queue = InstructionQueue(capacity=capacity, overflow=overflow)
    handled, failures = _run(queue, producers, per_producer, consumers, fail_rate, seed)
    total = producers * per_producer
    assert len(handled) == len(set(handled))  # never handled twice
    dropped = {entry.metadata["key"] for entry in queue.dropped_items}
    assert not dropped & set(handled)  # an entry is handled or dropped, never both
    assert len(handled) + queue.dropped == total and queue.requeued == failures
    assert queue.enqueued == total and queue.dequeued == len(handled) and queue.in_flight == 0 and len(queue) == 0
    if overflow == "raise":
        assert set(handled) == set(itertools.product(range(producers), range(per_producer)))


# --- the stream env: arrivals with arbitrary arm ids never raise out of step() and are never lost silently ---
@settings(max_examples=25, deadline=None, database=None)
@given(
    schedule=st.dictionaries(st.integers(0, 6), st.lists(st.integers(1, 5), min_size=1, max_size=3), max_size=4),
    capacity=st.integers(1, 4),
)
def test_stream_env_arrivals_are_checked_on_attach_or_queued(schedule, capacity):
    import gymnasium as gym

    import vafn_gym  # noqa: F401  (registers the env IDs)
    from vafn_gym.queue import ScheduledArrivals

    env = gym.make("VAFN/ThreeArmStream-v1", arrivals=None, auto_dequeue=False, queue_capacity=capacity)
    stream = env.unwrapped
    process = ScheduledArrivals(schedule)  # built without n_arms: arm 4 or 5 is only known at attach
    bad_steps = sorted(step for step, arms in schedule.items() if max(arms) > 3)
    try:
        stream.arrival_process = process
    except ValueError as error:
        assert bad_steps and f"schedule step {bad_steps[0]}" in str(error) and len(str(error)) < MESSAGE_LIMIT
        assert stream.arrival_process is None
        env.close()
        return
    assert not bad_steps
    env.reset(seed=0)
    for _ in range(8):
        env.step(env.action_space.sample())
    refused = [line for line in stream.errors if "full" in line]
    assert stream.queue.enqueued + len(refused) == process.num_instructions  # queued, or refused with a record
    env.close()
