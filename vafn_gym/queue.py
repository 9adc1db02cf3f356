"""The Dynamic Instruction Queue: a bounded, thread-safe FIFO of timestamped instructions, and its arrival processes.

Producers (speech, images, code, other threads) call :meth:`InstructionQueue.enqueue`; the controller calls
:meth:`InstructionQueue.dequeue` and *holds* while the queue is empty. A consumer that may fail while handling an entry
takes it with acknowledgement instead (:meth:`InstructionQueue.take`, or :meth:`~InstructionQueue.get_unacked` then
:meth:`~InstructionQueue.ack` / :meth:`~InstructionQueue.nack`), so an entry is only gone once it was handled.
:class:`ArrivalProcess` subclasses turn a simulation step counter into arrivals so that a queue-driven episode is
reproducible.
"""

from __future__ import annotations

import math
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from numbers import Integral, Real
from typing import Any, Literal

import numpy as np

from vafn_gym.instructions import Instruction, brief_repr

__all__ = [
    "ArrivalProcess",
    "InstructionQueue",
    "OVERFLOW_POLICIES",
    "PoissonArrivals",
    "QueueFullError",
    "QueuedInstruction",
    "ScheduledArrivals",
]

#: The overflow policies :class:`InstructionQueue` accepts.
OVERFLOW_POLICIES: tuple[str, ...] = ("raise", "drop_oldest")
#: How many evicted items :attr:`InstructionQueue.dropped_items` keeps (the most recent ones); ``on_drop`` gets all.
DROPPED_HISTORY: int = 100

OverflowPolicy = Literal["raise", "drop_oldest"]


class QueueFullError(RuntimeError):
    """Raised by :meth:`InstructionQueue.enqueue` when the queue is full and its overflow policy is ``"raise"``."""


DropCallback = Callable[["QueuedInstruction"], None]


@dataclass(frozen=True)
class QueuedInstruction:
    """One queue entry: the producer's payload, when it arrived, its global arrival number and where it came from.

    :param payload: what the producer passed (an :class:`Instruction` when enqueued with ``validate=True``).
    :param arrival_time: the queue clock's reading at enqueue (``time.perf_counter`` by default).
    :param sequence: the queue's arrival counter; strictly increasing in arrival order, starting at 0.
    :param source: free-form producer name (``"user"``, ``"speech"``, ``"schedule"``, ...).
    :param metadata: free-form extras, e.g. latency or confidence from a media stream (a copy of the caller's dict).
    :param n_arms: the queue's arm count, checked by :attr:`instruction` (``None``: any arm id >= 1).
    """

    # payload and metadata may be unhashable (a raw list, a dict); sequence and arrival_time identify an entry.
    payload: Any = field(hash=False)
    arrival_time: float
    sequence: int
    source: str = "user"
    metadata: dict = field(default_factory=dict, hash=False)
    n_arms: int | None = field(default=None, compare=False)

    @property
    def instruction(self) -> Instruction:
        """The payload as an :class:`Instruction`; raises only ``ValueError`` for a malformed payload."""
        return Instruction.coerce(self.payload, n_arms=self.n_arms)


def _wait_seconds(timeout: Any) -> float | None:
    """A dequeue timeout as seconds to wait, ``None`` meaning forever (``None``, ``inf`` or beyond the lock's limit)."""
    if timeout is None:
        return None
    if isinstance(timeout, (bool, np.bool_)) or not isinstance(timeout, Real) or math.isnan(timeout) or timeout < 0:
        raise ValueError(f"timeout must be None or a number >= 0, got {brief_repr(timeout)}")
    # Condition.wait raises OverflowError beyond TIMEOUT_MAX (about 49 days); anything that long is "forever".
    return None if timeout >= threading.TIMEOUT_MAX else float(timeout)


class InstructionQueue:
    """Bounded, thread-safe FIFO of :class:`QueuedInstruction`, with an explicit overflow policy and hold state.

    One ``threading.Condition`` guards a ``collections.deque``; timestamps and sequence numbers are taken inside the
    lock, so arrival order, sequence order and timestamp order agree even with producers on many threads.

    Entries are *ready* (waiting in the queue) or *in flight* (taken with :meth:`take` / :meth:`get_unacked` and not
    yet acknowledged). ``len``, :meth:`peek`, :meth:`snapshot`, iteration, :attr:`holding`, :meth:`clear`,
    :meth:`discard` and the capacity all concern ready entries only, like ``queue.Queue``'s ``qsize`` and ``maxsize``;
    :attr:`in_flight` and :meth:`unacked` show the others. An entry put back with :meth:`nack` is ready again at the
    head of the queue, with its sequence number and timestamp, and is never evicted or refused on the way back: ``len``
    may then exceed the capacity until consumers catch up (``"raise"`` refuses new entries meanwhile, ``"drop_oldest"``
    evicts the oldest ready ones, the put-back entry first).

    :param capacity: the most ready entries the queue holds at once (>= 1).
    :param overflow: what :meth:`enqueue` does when the queue is full: ``"raise"`` (the default, backpressure): wait up
        to the enqueue's ``timeout`` for room, then raise :class:`QueueFullError` and change nothing; or
        ``"drop_oldest"``: evict the oldest ready entry, count it in :attr:`dropped`, keep it in :attr:`dropped_items`
        (the last ``DROPPED_HISTORY``) and hand it to ``on_drop``.
    :param clock: zero-argument function giving the arrival timestamp in seconds (monotonic clocks only).
    :param n_arms: the arm count of the layout the instructions are for: validated enqueues reject higher arm ids and
        :attr:`QueuedInstruction.instruction` checks them (``None``: any arm id >= 1).
    :param on_drop: called with *every* evicted entry, on the enqueuing thread, after the queue's lock is released (so
        it may use the queue). An exception it raises is kept in :attr:`drop_callback_errors`, never raised to the
        producer, whose entry is queued.
    """

    def __init__(
        self,
        capacity: int = 64,
        overflow: OverflowPolicy = "raise",
        clock: Callable[[], float] = time.perf_counter,
        *,
        n_arms: int | None = None,
        on_drop: DropCallback | None = None,
    ) -> None:
        if isinstance(capacity, bool) or not isinstance(capacity, Integral):
            raise ValueError(f"capacity must be an integer >= 1, got {brief_repr(capacity)}")
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if not isinstance(overflow, str) or overflow not in OVERFLOW_POLICIES:
            raise ValueError(f"overflow must be one of {list(OVERFLOW_POLICIES)}, got {brief_repr(overflow)}")
        if not callable(clock):
            raise ValueError(f"clock must be callable, got {brief_repr(clock)}")
        if on_drop is not None and not callable(on_drop):
            raise ValueError(f"on_drop must be callable or None, got {brief_repr(on_drop)}")
        if n_arms is not None:
            Instruction().check_arms(n_arms)  # validates n_arms itself
        self._capacity = int(capacity)
        self._overflow: OverflowPolicy = overflow
        self._clock = clock
        self._n_arms: int | None = None if n_arms is None else int(n_arms)
        self._items: deque[QueuedInstruction] = deque()
        self._in_flight: dict[int, QueuedInstruction] = {}
        self._dropped_items: deque[QueuedInstruction] = deque(maxlen=DROPPED_HISTORY)
        self._on_drop = on_drop
        self._drop_callback_errors: list[str] = []
        lock = threading.Lock()
        self._cond = threading.Condition(lock)  # "an entry is ready"
        self._not_full = threading.Condition(lock)  # "there is room", for producers that wait
        self._next_sequence = 0
        self._enqueued = 0
        self._dequeued = 0
        self._dropped = 0
        self._cleared = 0
        self._requeued = 0

    # --- configuration ---
    @property
    def capacity(self) -> int:
        """The most ready entries the queue holds at once (entries put back by :meth:`nack` may exceed it)."""
        return self._capacity

    @property
    def overflow(self) -> OverflowPolicy:
        """The overflow policy: ``"raise"`` or ``"drop_oldest"``."""
        return self._overflow

    @property
    def n_arms(self) -> int | None:
        """The arm count instructions are validated against, or ``None`` for any arm id >= 1."""
        return self._n_arms

    # --- counters ---
    @property
    def enqueued(self) -> int:
        """How many entries were accepted by :meth:`enqueue` (rejected ones are not counted)."""
        return self._enqueued

    @property
    def dequeued(self) -> int:
        """How many entries left for good: handed out by :meth:`dequeue` or acknowledged with :meth:`ack`."""
        return self._dequeued

    @property
    def dropped(self) -> int:
        """How many entries the ``"drop_oldest"`` policy evicted."""
        return self._dropped

    @property
    def cleared(self) -> int:
        """How many entries :meth:`clear` / :meth:`discard` removed.

        ``enqueued == dequeued + dropped + cleared + len(queue) + in_flight`` at any quiet moment.
        """
        return self._cleared

    @property
    def requeued(self) -> int:
        """How many times an in-flight entry was put back with :meth:`nack`."""
        return self._requeued

    @property
    def in_flight(self) -> int:
        """How many entries are taken but not yet acknowledged."""
        with self._cond:
            return len(self._in_flight)

    @property
    def dropped_items(self) -> list[QueuedInstruction]:
        """The most recently evicted entries (at most ``DROPPED_HISTORY``), oldest first, as a copy.

        Every eviction, without limit, goes to the ``on_drop`` callback.
        """
        with self._cond:
            return list(self._dropped_items)

    @property
    def drop_callback_errors(self) -> list[str]:
        """What the ``on_drop`` callback raised, one line per failed call, oldest first (a copy)."""
        with self._cond:
            return list(self._drop_callback_errors)

    # --- producer side ---
    def enqueue(
        self,
        item: Any,
        source: str = "user",
        validate: bool = True,
        metadata: Mapping | None = None,
        timeout: float | None = 0.0,
    ) -> QueuedInstruction:
        """Append an instruction, timestamped and numbered on arrival, and wake a waiting consumer.

        :param item: an :class:`Instruction`, machine code (``"2,3,1"``), a list of arm ids or instruction JSON.
        :param source: producer name stored on the entry.
        :param validate: parse ``item`` now, raising ``ValueError`` (and only that) and enqueueing nothing if it is
            malformed (the stored payload is then the :class:`Instruction`); with ``False`` the raw ``item`` is stored
            and the error surfaces on :attr:`QueuedInstruction.instruction`, so a stream can defer parsing to the
            consumer.
        :param metadata: free-form extras stored (copied) on the entry.
        :param timeout: with the ``"raise"`` policy, how long to wait for room in a full queue: ``0`` (default) raises
            at once, a positive number waits at most that long, ``None`` or ``math.inf`` waits forever. Ignored by
            ``"drop_oldest"``, which never waits.
        :return: the queued entry.
        :raises QueueFullError: when the queue is (still) full and the policy is ``"raise"``; the queue is unchanged.
        """
        if not isinstance(source, str):
            raise ValueError(f"source must be a string, got {brief_repr(source)}")
        if metadata is not None and not isinstance(metadata, Mapping):
            raise ValueError(f"metadata must be a mapping or None, got {brief_repr(metadata)}")
        seconds = _wait_seconds(timeout)
        # Parse outside the lock: it can be slow and never depends on the queue's state.
        payload = Instruction.coerce(item, n_arms=self._n_arms) if validate else item
        extras = dict(metadata) if metadata is not None else {}
        with self._cond:
            if self._overflow == "raise" and not self._wait_for_room(seconds):
                raise QueueFullError(
                    f"instruction queue is full ({self._capacity} entries); "
                    f"rejected {brief_repr(item)} from {brief_repr(source)}"
                )
            evicted = self._evict_for_room()
            entry = QueuedInstruction(
                payload=payload,
                arrival_time=float(self._clock()),
                sequence=self._next_sequence,
                source=source,
                metadata=extras,
                n_arms=self._n_arms,
            )
            self._next_sequence += 1
            self._items.append(entry)
            self._enqueued += 1
            self._cond.notify()
        self._report_drops(evicted)
        return entry

    def _wait_for_room(self, seconds: float | None) -> bool:
        """Under the lock: wait up to ``seconds`` (``None``: forever) until a ready slot is free; whether one is."""
        if len(self._items) >= self._capacity and seconds != 0:
            self._not_full.wait_for(lambda: len(self._items) < self._capacity, timeout=seconds)
        return len(self._items) < self._capacity

    def _evict_for_room(self) -> list[QueuedInstruction]:
        """Under the lock: evict the oldest ready entries until one slot is free; returns them, oldest first."""
        evicted = []
        while len(self._items) >= self._capacity:
            evicted.append(self._items.popleft())
        self._dropped_items.extend(evicted)
        self._dropped += len(evicted)
        return evicted

    def _report_drops(self, evicted: list[QueuedInstruction]) -> None:
        """Outside the lock: hand every evicted entry to ``on_drop``, keeping (not raising) what the callback raises."""
        if self._on_drop is None:
            return
        for entry in evicted:
            try:
                self._on_drop(entry)
            except Exception as error:  # noqa: BLE001 - the producer's entry is queued; the callback's fault is kept
                with self._cond:
                    self._drop_callback_errors.append(
                        f"on_drop raised {type(error).__name__}: {brief_repr(str(error))} for entry #{entry.sequence}"
                    )

    # --- consumer side ---
    def _pop_ready(self, timeout: Any) -> QueuedInstruction | None:
        """Under the lock: wait up to ``timeout`` for a ready entry and pop it (``None`` if there is none)."""
        seconds = _wait_seconds(timeout)
        if not self._items and seconds != 0:
            self._cond.wait_for(lambda: bool(self._items), timeout=seconds)
        if not self._items:
            return None
        self._not_full.notify()
        return self._items.popleft()

    def dequeue(self, timeout: float | None = 0.0) -> QueuedInstruction | None:
        """Remove and return the oldest entry, waiting up to ``timeout`` seconds for one; ``None`` if still empty.

        The entry is gone for good (counted in :attr:`dequeued`); use :meth:`take` when handling it may fail.

        :param timeout: ``0`` returns at once, a positive number waits at most that long, ``None`` or ``math.inf``
            waits forever; a negative or NaN timeout raises ``ValueError``.
        """
        with self._cond:
            entry = self._pop_ready(timeout)
            if entry is not None:
                self._dequeued += 1
            return entry

    def get_unacked(self, timeout: float | None = 0.0) -> QueuedInstruction | None:
        """Take the oldest entry *in flight*: it stays the queue's until :meth:`ack` (done) or :meth:`nack` (put back).

        Every entry returned must be settled with exactly one :meth:`ack` or :meth:`nack`; prefer :meth:`take`, which
        does that for you.

        :param timeout: as for :meth:`dequeue`.
        :return: the entry, or ``None`` when none became ready within ``timeout``.
        """
        with self._cond:
            entry = self._pop_ready(timeout)
            if entry is not None:
                self._in_flight[entry.sequence] = entry
            return entry

    def _settle(self, entry: QueuedInstruction) -> None:
        """Under the lock: remove ``entry`` from the in-flight set, or raise ``ValueError`` if it is not there."""
        if not isinstance(entry, QueuedInstruction) or self._in_flight.get(entry.sequence) is not entry:
            raise ValueError(
                f"{brief_repr(entry)} is not in flight on this queue (already acknowledged, put back, or never taken)"
            )
        del self._in_flight[entry.sequence]

    def ack(self, entry: QueuedInstruction) -> None:
        """Acknowledge an in-flight entry: it was handled and leaves the queue for good (counted in :attr:`dequeued`).

        :param entry: the entry returned by :meth:`get_unacked`; ``ValueError`` if it is not in flight.
        """
        with self._cond:
            self._settle(entry)
            self._dequeued += 1

    def nack(self, entry: QueuedInstruction) -> None:
        """Put an in-flight entry back at the head of the queue, keeping its sequence number and timestamp.

        Entries put back keep their arrival order among themselves, and a waiting consumer is woken. This never evicts
        and never raises :class:`QueueFullError`, even on a full queue.

        :param entry: the entry returned by :meth:`get_unacked`; ``ValueError`` if it is not in flight.
        """
        with self._cond:
            self._settle(entry)
            self._requeue(entry)

    def _requeue(self, entry: QueuedInstruction) -> None:
        """Under the lock: insert ``entry`` among the ready entries in sequence order (normally at the head)."""
        index = 0
        while index < len(self._items) and self._items[index].sequence < entry.sequence:
            index += 1
        self._items.insert(index, entry)
        self._requeued += 1
        self._cond.notify()

    @contextmanager
    def take(self, timeout: float | None = 0.0) -> Iterator[QueuedInstruction | None]:
        """Lend the oldest entry to a ``with`` block: acknowledged if the block completes, put back if it raises.

        A failing consumer thus loses nothing: on any exception (``KeyboardInterrupt`` included) the entry is back at
        the head of the queue (:meth:`nack`) before the exception propagates::

            with queue.take(timeout=1.0) as entry:
                if entry is not None:
                    handle(entry.instruction)

        The block may also settle the entry itself with :meth:`ack` or :meth:`nack`; the exit then does nothing.

        :param timeout: as for :meth:`dequeue`; the block receives ``None`` when no entry became ready in time.
        """
        entry = self.get_unacked(timeout)
        if entry is None:
            yield None
            return
        try:
            yield entry
        except BaseException:
            self._settle_if_in_flight(entry, requeue=True)
            raise
        self._settle_if_in_flight(entry, requeue=False)

    def _settle_if_in_flight(self, entry: QueuedInstruction, requeue: bool) -> None:
        with self._cond:
            if self._in_flight.get(entry.sequence) is not entry:
                return  # the block settled it already
            self._settle(entry)
            if requeue:
                self._requeue(entry)
            else:
                self._dequeued += 1

    def unacked(self) -> list[QueuedInstruction]:
        """A copy of the in-flight entries, oldest first."""
        with self._cond:
            return sorted(self._in_flight.values(), key=lambda entry: entry.sequence)

    def peek(self) -> QueuedInstruction | None:
        """The oldest ready entry without removing it, or ``None`` when none is ready."""
        with self._cond:
            return self._items[0] if self._items else None

    def snapshot(self) -> list[QueuedInstruction]:
        """A copy of the ready entries, oldest first; later queue changes do not affect it."""
        with self._cond:
            return list(self._items)

    def clear(self) -> list[QueuedInstruction]:
        """Remove every ready entry and return them, oldest first (counted in :attr:`cleared`); in-flight ones stay."""
        with self._cond:
            items = list(self._items)
            self._items.clear()
            self._cleared += len(items)
            self._not_full.notify_all()
            return items

    def discard(self, predicate: Callable[[QueuedInstruction], bool]) -> list[QueuedInstruction]:
        """Remove the ready entries for which ``predicate`` is true and return them, oldest first.

        The other entries keep their place and stamps. Removed entries are counted in :attr:`cleared`; in-flight
        entries are not considered.

        :param predicate: called on each entry, under the lock (keep it cheap and free of queue calls).
        """
        with self._cond:
            removed = [entry for entry in self._items if predicate(entry)]
            if removed:
                self._items = deque(entry for entry in self._items if not predicate(entry))
                self._cleared += len(removed)
                self._not_full.notify_all()
            return removed

    @property
    def holding(self) -> bool:
        """Whether the controller must hold: ``True`` exactly when no entry is ready (in-flight ones do not count)."""
        with self._cond:
            return not self._items

    def __len__(self) -> int:
        """The number of ready entries (so an empty queue is falsy: test ``is None``, not truthiness)."""
        with self._cond:
            return len(self._items)

    def __iter__(self) -> Iterator[QueuedInstruction]:
        """Iterate over a snapshot of the ready entries taken under the lock, oldest first."""
        return iter(self.snapshot())

    def __repr__(self) -> str:
        return (
            f"InstructionQueue(len={len(self)}, in_flight={self.in_flight}, capacity={self._capacity}, "
            f"overflow={self._overflow!r}, enqueued={self._enqueued}, dequeued={self._dequeued}, "
            f"dropped={self._dropped})"
        )


# --- arrival processes ---
def _check_step(step: Any) -> int:
    if isinstance(step, bool) or not isinstance(step, Integral) or step < 0:
        raise ValueError(f"step must be an integer >= 0, got {step!r}")
    return int(step)


class ArrivalProcess(ABC):
    """Turns a simulation step counter into instruction arrivals, so a queue-driven episode is reproducible."""

    #: Source name used by :meth:`feed` when none is given.
    default_source: str = "arrival"

    def reset(self, seed: int | None = None) -> None:  # noqa: B027 - optional hook; deterministic processes keep it
        """Start a new episode; seeded processes reseed (``None`` keeps a deterministic process as it is).

        :param seed: the new seed, or ``None``.
        """

    @abstractmethod
    def arrivals(self, step: int) -> list[Instruction]:
        """The instructions that arrive at env step ``step``, in arrival order (a new list).

        :param step: the env step counter (>= 0).
        """

    def check_arms(self, n_arms: int) -> None:
        """Raise ``ValueError`` naming the first arrival that names an arm above ``n_arms``, where that is knowable now.

        Called when the process is attached to an env. The base class knows nothing ahead of time (a sampler's output is
        only checked when it arrives); subclasses with fixed instructions check them all.

        :param n_arms: the env's arm count.
        """
        Instruction().check_arms(n_arms)  # validates n_arms itself

    def feed(
        self,
        queue: InstructionQueue,
        step: int,
        source: str | None = None,
        on_error: Callable[[str], None] | None = None,
    ) -> list[QueuedInstruction]:
        """Enqueue this step's arrivals into ``queue`` (metadata ``{"step": step}``) and return the new entries.

        Without ``on_error``, a malformed arrival (``ValueError``) or a full ``overflow="raise"`` queue
        (:class:`QueueFullError`) propagates; earlier arrivals stay queued. With ``on_error``, each failure is reported
        to it as one line naming the step and the arrival, that arrival is skipped and the others are still fed.

        :param queue: the queue to feed.
        :param step: the env step counter (>= 0).
        :param source: source name for the entries (default: the process's ``default_source``).
        :param on_error: receives a line per arrival that could not be queued (or per step whose arrivals could not be
            drawn); ``None`` raises instead.
        """
        name = self.default_source if source is None else source
        if on_error is None:
            return [queue.enqueue(item, source=name, metadata={"step": step}) for item in self.arrivals(step)]
        try:
            items = self.arrivals(step)
        except Exception as error:  # noqa: BLE001 - a faulty process (e.g. its sampler) must not stop the env's loop
            on_error(f"arrivals at step {step} skipped: {type(error).__name__}: {brief_repr(str(error))}")
            return []
        entries = []
        for index, item in enumerate(items):
            try:
                entries.append(queue.enqueue(item, source=name, metadata={"step": step}))
            except (ValueError, QueueFullError) as error:
                on_error(f"arrival {index} at step {step} ({brief_repr(item)}) skipped: {error}")
        return entries


def _is_single_instruction(value: Any) -> bool:
    """Whether a schedule value is one instruction rather than a list of them (a list of numbers is arm ids)."""
    if isinstance(value, (Instruction, str, bytes, dict)):
        return True
    if isinstance(value, (list, tuple)):
        return all(isinstance(element, (Real, np.number)) for element in value)
    return True


def _schedule_place(step: int, index: int, count: int) -> str:
    """Where a scheduled instruction is: ``"schedule step 5"``, or ``"schedule step 5, instruction 1"`` of several."""
    return f"schedule step {step}" + ("" if count == 1 else f", instruction {index}")


def _check_arms(item: Instruction, n_arms: int, where: str) -> None:
    """Check an instruction's arm ids against ``n_arms``; the ``ValueError`` starts with ``where``."""
    try:
        item.check_arms(n_arms)
    except ValueError as error:
        raise ValueError(f"{where}: {error}") from None


class ScheduledArrivals(ArrivalProcess):
    """A scripted schedule: at step ``k`` the instruction(s) ``schedule[k]`` arrive.

    A value is one instruction in any form :meth:`Instruction.coerce` accepts, or a list of them. A list of numbers
    (``[2, 3, 1]``, and also ``[]``) is read as one instruction's arm ids; write ``[[2, 3], [1]]`` or
    ``["2,3", "1"]`` for several. Everything is validated here: ``ValueError`` names the offending step.

    :param schedule: mapping from env step (>= 0) to instruction(s).
    :param n_arms: when given, instructions naming a higher arm id are rejected here.
    """

    default_source = "schedule"

    def __init__(self, schedule: Mapping[int, Any], *, n_arms: int | None = None) -> None:
        if not isinstance(schedule, Mapping):
            raise ValueError(f"schedule must be a mapping step -> instruction(s), got {type(schedule).__name__}")
        if n_arms is not None:
            Instruction().check_arms(n_arms)  # validates n_arms itself
        parsed: dict[int, tuple[Instruction, ...]] = {}
        for key, value in schedule.items():
            try:
                step = _check_step(key)
            except ValueError as error:
                raise ValueError(f"schedule step {key!r}: {error}") from None
            values = [value] if _is_single_instruction(value) else list(value)
            items = []
            for index, element in enumerate(values):
                try:
                    items.append(Instruction.coerce(element, n_arms=n_arms))
                except ValueError as error:
                    raise ValueError(f"{_schedule_place(step, index, len(values))}: {error}") from error
            parsed[step] = tuple(items)
        self._schedule = dict(sorted(parsed.items()))

    @property
    def steps(self) -> tuple[int, ...]:
        """The scheduled steps, ascending."""
        return tuple(self._schedule)

    def check_arms(self, n_arms: int) -> None:
        """Raise ``ValueError`` naming the first scheduled step (and instruction) with an arm above ``n_arms``.

        :param n_arms: the env's arm count.
        """
        super().check_arms(n_arms)
        for step, items in self._schedule.items():
            for index, item in enumerate(items):
                _check_arms(item, n_arms, _schedule_place(step, index, len(items)))

    @property
    def last_step(self) -> int:
        """The last scheduled step, or -1 for an empty schedule (nothing arrives after it)."""
        return max(self._schedule, default=-1)

    def arrivals(self, step: int) -> list[Instruction]:
        """The instructions scheduled at ``step`` (empty for an unscheduled step).

        :param step: the env step counter (>= 0).
        """
        return list(self._schedule.get(_check_step(step), ()))

    @property
    def num_instructions(self) -> int:
        """How many instructions the whole schedule delivers."""
        return sum(len(items) for items in self._schedule.values())


class PoissonArrivals(ArrivalProcess):
    """Seeded Poisson arrivals with optional bursts; same seed, same arrivals.

    At each step ``Poisson(rate)`` instructions arrive, plus, with probability ``burst_probability``, a burst of
    ``burst_size`` (an integer drawn uniformly from the inclusive range) more. Each step draws from its own
    ``np.random.Generator`` derived from ``(seed, step)``, so :meth:`arrivals` is a pure function of the step: calling
    it out of order, skipping steps or replaying a step gives the same answer.

    :param rate: mean number of (non-burst) arrivals per step (>= 0).
    :param sampler: ``sampler(rng) -> instruction``, drawing from the step's generator; give this or ``instructions``.
    :param instructions: a fixed list of instructions to draw from uniformly; give this or ``sampler``.
    :param burst_probability: per-step probability of a burst, in [0, 1].
    :param burst_size: inclusive ``(low, high)`` range of a burst's size, 1 <= low <= high.
    :param seed: the seed; ``None`` draws fresh entropy (still fixed until the next :meth:`reset`).
    :param n_arms: when given, instructions (from the list or the sampler) naming a higher arm id are rejected.
    """

    default_source = "poisson"

    def __init__(
        self,
        rate: float,
        sampler: Callable[[np.random.Generator], Any] | None = None,
        instructions: Sequence[Any] | None = None,
        burst_probability: float = 0.0,
        burst_size: tuple[int, int] = (2, 5),
        seed: int | None = None,
        *,
        n_arms: int | None = None,
    ) -> None:
        if isinstance(rate, bool) or not isinstance(rate, Real) or not math.isfinite(rate) or rate < 0:
            raise ValueError(f"rate must be a finite number >= 0, got {rate!r}")
        if (
            isinstance(burst_probability, bool)
            or not isinstance(burst_probability, Real)
            or not 0.0 <= burst_probability <= 1.0
        ):
            raise ValueError(f"burst_probability must be in [0, 1], got {burst_probability!r}")
        try:
            low, high = burst_size
        except (TypeError, ValueError):
            raise ValueError(f"burst_size must be a (low, high) pair, got {burst_size!r}") from None
        if any(isinstance(v, bool) or not isinstance(v, Integral) for v in (low, high)) or not 1 <= low <= high:
            raise ValueError(f"burst_size must be integers with 1 <= low <= high, got {burst_size!r}")
        if (sampler is None) == (instructions is None):
            raise ValueError("give exactly one of sampler (a callable) or instructions (a non-empty list)")
        if n_arms is not None:
            Instruction().check_arms(n_arms)  # validates n_arms itself
        if sampler is not None and not callable(sampler):
            raise ValueError(f"sampler must be callable, got {sampler!r}")
        pool: tuple[Instruction, ...] = ()
        if instructions is not None:
            if isinstance(instructions, (str, bytes, Instruction)):
                raise ValueError("instructions must be a list of instructions, not a single one")
            pool_list = []
            for index, element in enumerate(instructions):
                try:
                    pool_list.append(Instruction.coerce(element, n_arms=n_arms))
                except ValueError as error:
                    raise ValueError(f"instructions[{index}]: {error}") from error
            if not pool_list:
                raise ValueError("instructions must not be empty")
            pool = tuple(pool_list)
        self.rate = float(rate)
        self.burst_probability = float(burst_probability)
        self.burst_size = (int(low), int(high))
        self._sampler = sampler
        self._pool = pool
        self._n_arms = n_arms
        self._entropy = 0
        self.reset(seed)

    @property
    def seed(self) -> int:
        """The entropy every step's generator is derived from (the seed, or the drawn entropy for ``seed=None``)."""
        return self._entropy

    def check_arms(self, n_arms: int) -> None:
        """Raise ``ValueError`` naming the first listed instruction with an arm above ``n_arms`` (a sampler's output is
        checked when it arrives).

        :param n_arms: the env's arm count.
        """
        super().check_arms(n_arms)
        for index, item in enumerate(self._pool):
            _check_arms(item, n_arms, f"instructions[{index}]")

    def reset(self, seed: int | None = None) -> None:
        """Reseed; ``None`` draws fresh entropy.

        :param seed: the new seed (an integer >= 0) or ``None``.
        """
        if seed is None:
            self._entropy = int(np.random.SeedSequence().entropy)
        elif isinstance(seed, bool) or not isinstance(seed, Integral) or seed < 0:
            raise ValueError(f"seed must be None or an integer >= 0, got {seed!r}")
        else:
            self._entropy = int(seed)

    def arrivals(self, step: int) -> list[Instruction]:
        """The instructions that arrive at ``step``, drawn from a generator seeded by ``(seed, step)``.

        :param step: the env step counter (>= 0).
        """
        rng = np.random.default_rng(np.random.SeedSequence([self._entropy, _check_step(step)]))
        count = int(rng.poisson(self.rate))
        if self.burst_probability > 0.0 and rng.random() < self.burst_probability:
            count += int(rng.integers(self.burst_size[0], self.burst_size[1], endpoint=True))
        result = []
        for _ in range(count):
            if self._sampler is not None:
                drawn = self._sampler(rng)
                try:
                    result.append(Instruction.coerce(drawn, n_arms=self._n_arms))
                except ValueError as error:
                    raise ValueError(f"step {step}: the sampler returned a malformed instruction: {error}") from error
            else:
                result.append(self._pool[int(rng.integers(len(self._pool)))])
        return result
