"""MultiArmStreamEnv: the long-horizon, queue-driven variant; instructions come via the Dynamic Instruction Queue."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from vafn_gym.checks import check_bool, check_int, check_number
from vafn_gym.envs.multi_arm import MultiArmEnv
from vafn_gym.instructions import Instruction, brief_repr
from vafn_gym.queue import (
    ArrivalProcess,
    DropCallback,
    InstructionQueue,
    PoissonArrivals,
    QueuedInstruction,
    ScheduledArrivals,
)

#: Source name of the items the env's own arrival process enqueues (dropped on reset; user items are kept).
ARRIVAL_SOURCE = "arrival-process"
DEFAULT_HORIZON = 2000


class MultiArmStreamEnv(MultiArmEnv):
    """Instructions arrive asynchronously; the arms hold when the queue is empty, and finishing one starts the next.

    Episodes never terminate on success: they are truncated at ``horizon`` steps (2,000, the paper's long-horizon test).
    Per-instruction outcomes are appended to :attr:`records`; malformed queued items to :attr:`rejected` and
    :attr:`errors`, arrivals that could not be queued to :attr:`errors` (the loop goes on). Every queued entry ends in
    exactly one of: :attr:`records` (completed or timed out), :attr:`rejected`, :attr:`dropped` (evicted by
    ``overflow="drop_oldest"``), or still in the queue (ready or running).

    :param arrivals: ``"poisson"`` (seeded, instructions from the task sampler), ``None`` (only user code enqueues,
        e.g. ``env.unwrapped.queue.enqueue("2,3,1")`` from another thread), a schedule ``{step: instruction(s)}`` or
        any :class:`ArrivalProcess`.
    :param arrival_rate: mean arrivals per step of the Poisson process.
    :param horizon: steps per episode.
    :param queue_capacity: bound of the queue.
    :param overflow: the queue's overflow policy: "raise" (default: backpressure, a producer gets ``QueueFullError`` or
        waits with ``enqueue(..., timeout=s)``) or "drop_oldest" (every eviction is kept in :attr:`dropped`).
    :param on_drop: also called with every entry "drop_oldest" evicts (on the producer's thread).
    :param auto_dequeue: start the next queued instruction automatically; set False when a controller (e.g.
        :class:`vafn_sb3.OnlineController`) dequeues itself through :meth:`start_next`.
    :param instruction_timeout: steps allowed per instruction (default ``50 + 80 * len``); a timed-out one is recorded
        and skipped.
    :param kwargs: everything :class:`MultiArmEnv` accepts (arms, robot, targets, reward, rendering, ...).
    """

    def __init__(
        self,
        arrivals: str | Mapping[int, Any] | ArrivalProcess | None = "poisson",
        arrival_rate: float = 0.005,
        horizon: int = DEFAULT_HORIZON,
        queue_capacity: int = 64,
        overflow: str = "raise",
        auto_dequeue: bool = True,
        instruction_timeout: int | None = None,
        on_drop: DropCallback | None = None,
        **kwargs: Any,
    ) -> None:
        if "instruction" in kwargs or "max_steps" in kwargs:
            raise ValueError("MultiArmStreamEnv takes instructions from its queue; use arrivals= and horizon=")
        self.horizon = check_int("horizon", horizon, 1)
        self.auto_dequeue = check_bool("auto_dequeue", auto_dequeue)
        self.instruction_timeout = (
            None if instruction_timeout is None else check_int("instruction_timeout", instruction_timeout, 1)
        )
        arrival_rate = check_number("arrival_rate", arrival_rate, 0.0, 1.0)
        if on_drop is not None and not callable(on_drop):
            raise ValueError(f"on_drop must be callable or None, got {brief_repr(on_drop)}")
        super().__init__(max_steps=self.horizon, **kwargs)
        self._user_on_drop = on_drop
        #: Every entry the queue evicted (``overflow="drop_oldest"``) since the env was made, oldest first; never
        #: cleared by a reset (the queue and its users' entries outlive episodes).
        self.dropped: list[QueuedInstruction] = []
        self.queue = InstructionQueue(
            capacity=check_int("queue_capacity", queue_capacity, 1), overflow=overflow, n_arms=self.n_arms,
            on_drop=self._record_drop,
        )
        self._arrival_process: ArrivalProcess | None = None
        self.arrival_process = self._make_arrivals(arrivals, arrival_rate)
        self.total_steps = 0
        self.current: QueuedInstruction | None = None
        self.started_at = 0
        self.records: list[dict[str, Any]] = []
        #: This episode's queued entries that could not be started: ``sequence``, ``source``, ``reason``, ``step``.
        self.rejected: list[dict[str, Any]] = []
        self.errors: list[str] = []

    @property
    def arrival_process(self) -> ArrivalProcess | None:
        """The env's own arrival process (``None``: only user code enqueues)."""
        return self._arrival_process

    @arrival_process.setter
    def arrival_process(self, process: ArrivalProcess | None) -> None:
        """Attach a process, checked against the arm count first (``ValueError`` names the bad arrival)."""
        if process is not None and not isinstance(process, ArrivalProcess):
            raise ValueError(f"arrival_process must be an ArrivalProcess or None, got {brief_repr(process)}")
        if process is not None:
            process.check_arms(self.n_arms)
        self._arrival_process = process

    def _record_drop(self, entry: QueuedInstruction) -> None:
        """The queue's ``on_drop``: keep the evicted entry, then call the user's callback."""
        self.dropped.append(entry)
        if self._user_on_drop is not None:
            self._user_on_drop(entry)

    def _make_arrivals(self, arrivals: Any, rate: float) -> ArrivalProcess | None:
        if arrivals is None or isinstance(arrivals, ArrivalProcess):
            return arrivals
        if isinstance(arrivals, str) and arrivals == "poisson":
            return PoissonArrivals(rate, sampler=self.sampler.sample, seed=0)
        if isinstance(arrivals, Mapping):
            return ScheduledArrivals(arrivals, n_arms=self.n_arms)
        raise ValueError(f"arrivals must be 'poisson', None, a schedule or an ArrivalProcess, got {arrivals!r:.60}")

    @property
    def holding(self) -> bool:
        """True while no instruction is being executed (the queue was empty)."""
        return self.current is None

    def _begin_episode(self, instruction: Instruction | None) -> None:
        """Drop the previous episode's own arrivals (user-enqueued items are kept) and start holding."""
        if instruction is not None:
            raise ValueError("MultiArmStreamEnv takes instructions from its queue, not from reset options")
        if self.arrival_process is not None:
            # From the env's generator even on an unseeded reset, so reset(seed=s) then reset() is reproducible
            # (Gymnasium's contract; fresh OS entropy here made step-0 arrivals differ).
            self.arrival_process.reset(int(self.np_random.integers(2**63)))
        if self.current is not None:  # abandoned mid-way: a user's instruction goes back to the head of the queue
            settle = self.queue.ack if self.current.source == ARRIVAL_SOURCE else self.queue.nack
            settle(self.current)
            self.current = None
        self.queue.discard(lambda item: item.source == ARRIVAL_SOURCE)
        self.total_steps = 0
        self.records, self.rejected, self.errors = [], [], []
        self._hold()
        self._pump()

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Home the arms and start holding; the info carries the stream's state.

        ``options`` are checked before anything changes: an ``"instruction"`` option raises ``ValueError`` (the stream
        takes its instructions from the queue) and leaves the arms, the running instruction and the counters as they
        were.
        """
        if isinstance(options, Mapping) and "instruction" in options:
            raise ValueError(
                "MultiArmStreamEnv takes instructions from its queue, not from reset options: "
                "enqueue it instead (env.unwrapped.queue.enqueue(...))"
            )
        obs, info = super().reset(seed=seed, options=options)
        return obs, {**info, **self._stream_fields([])}

    def _hold(self) -> None:
        self.current = None
        self.start_instruction(Instruction())

    def start_next(self) -> QueuedInstruction | None:
        """Take the next valid instruction and start it (malformed ones are recorded in :attr:`errors` and skipped).

        The item stays unacknowledged in the queue (``queue.in_flight``) until it completes or times out, so an
        instruction abandoned by a reset is put back rather than lost.
        """
        while True:
            item = self.queue.get_unacked()
            if item is None:
                self._hold()
                return None
            try:
                instruction = self._coerce(item.instruction)
                self.start_instruction(instruction)
            except ValueError as error:
                self.queue.ack(item)  # handled: recorded as rejected, never retried
                self._reject(item, str(error))
                continue
            self.current = item
            self.started_at = self.total_steps
            return item

    def _reject(self, item: QueuedInstruction, reason: str) -> None:
        """Record a queued entry that could not be started, in :attr:`rejected` and :attr:`errors`."""
        self.rejected.append(
            {"sequence": item.sequence, "source": item.source, "reason": reason, "step": self.total_steps}
        )
        self.errors.append(f"instruction #{item.sequence} from {item.source!r:.60} rejected: {reason}")

    def _pump(self) -> None:
        """Feed this step's arrivals (a bad or refused one is recorded in :attr:`errors` and skipped) and, when idle and
        auto_dequeue is on, start the next instruction."""
        if self.arrival_process is not None:
            self.arrival_process.feed(self.queue, self.total_steps, source=ARRIVAL_SOURCE, on_error=self.errors.append)
        if self.current is None and self.auto_dequeue:
            self.start_next()

    def _finish(self, outcome: str) -> dict[str, Any]:
        assert self.current is not None
        record = {
            "sequence": self.current.sequence,
            "source": self.current.source,
            "instruction": self.instruction.to_code(),
            "arrival_time": self.current.arrival_time,
            "start_step": self.started_at,
            "end_step": self.total_steps,
            "waypoints_reached": self.task.waypoint_index,
            "collided": self.task.collided,
            "outcome": outcome,
            "success": outcome == "completed" and not self.task.collided,
        }
        self.records.append(record)
        self.queue.ack(self.current)
        self._hold()
        return record

    def instruction_budget(self) -> int:
        """Steps allowed for the current instruction."""
        if self.instruction_timeout is not None:
            return self.instruction_timeout
        return self.default_instruction_budget()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One control step; finished or timed-out instructions are recorded and the next one starts."""
        positions, reward, contact = self._advance(action)
        self.total_steps += 1
        events = []
        if self.current is not None and self.task.complete:
            events.append(self._finish("completed"))
        elif self.current is not None and self.task.steps >= self.instruction_budget():
            events.append(self._finish("timeout"))
        self._pump()
        terminated = bool(contact and self.terminate_on_collision)
        truncated = not terminated and self.total_steps >= self.horizon
        distances = self.task.distances(positions)
        info = {**self._info(distances, contact), **self._stream_fields(events)}
        return self._observation(positions, distances), reward, terminated, truncated, info

    def _stream_fields(self, events: list[dict]) -> dict[str, Any]:
        """The stream's part of ``info`` (``is_success`` covers every finished instruction of the episode)."""
        return {
            "is_success": all(r["success"] for r in self.records),
            "holding": self.holding,
            "queue_length": len(self.queue),
            "instruction_sequence": None if self.current is None else self.current.sequence,
            "finished": events,
            "total_steps": self.total_steps,
        }
