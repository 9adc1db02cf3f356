"""The online adaptive controller (the paper's Algorithm 1) over the queue-driven ``VAFN/ThreeArmStream-v1``.

Loop, one control step at a time:

1. no instruction running: ask the stream for the next one (``start_next``; malformed entries are recorded in the
   stream's ``errors`` and skipped). Queue empty: **hold** (zero velocity for every arm) and step;
2. an instruction was dequeued: **adapt** the model to it. The support set is collected on a private *twin*
   :class:`~vafn_gym.envs.MultiArmEnv` (the stream's own world, task and reward settings) after
   ``set_task(instruction)``, so the real arms never execute exploratory support actions and adaptation finishes
   before the first real action. The twin is a simulator of the same world: this assumes the task (including hidden
   targets) can be simulated, as in meta-training;
3. **execute** the adapted policy (deterministic) until the stream reports the instruction completed or timed out;
4. **reset to θ**: drop the adapted parameters (``adapt`` never modifies the model) and continue.

When the robot changes mid-stream (another robot, a payload, a re-mounted base),
:meth:`OnlineController.announce_dynamics` tells the controller: its twin takes the new dynamics and a running
instruction is adapted again at once (a row in :attr:`OnlineController.dynamics_events` times it). A model that
identifies the change from the arm's own motion (:class:`vafn_sb3.inference.DynamicsCompensation` with
``online=True``) needs no announcement.

Instructions may be enqueued from any thread (the queue is thread-safe). Every instruction gets an
:class:`InstructionLog` row (arrival, wait, adaptation and first-action times, completion step, success, collisions);
one that could not be started is in :attr:`OnlineController.rejected`, one the queue evicted (``drop_oldest``) in
:attr:`OnlineController.dropped`.
"""

from __future__ import annotations

import csv
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from vafn_gym.dynamics import Dynamics
from vafn_gym.envs import MultiArmEnv, MultiArmStreamEnv
from vafn_gym.queue import QueuedInstruction

__all__ = ["InstructionLog", "OnlineController"]


@dataclass
class InstructionLog:
    """What happened to one dequeued instruction. Times are ``time.perf_counter`` seconds (the queue's clock).

    :param sequence: the queue's arrival number of the instruction.
    :param instruction: its machine code.
    :param arrival_time: when it was enqueued.
    :param dequeue_time: when the controller took it from the queue.
    :param adaptation_time_s: wall time of ``model.adapt`` (support rollout on the twin + K inner rounds);
        0 without adaptation.
    :param first_action_time: when the first adapted action was ready to be sent.
    :param latency_s: ``first_action_time - arrival_time`` (includes waiting behind earlier instructions).
    :param service_latency_s: ``first_action_time - dequeue_time`` (the controller's own reaction time).
    :param service_cpu_s: CPU time of the controller thread from dequeue to the first action (``time.thread_time``):
        the reaction time on one dedicated thread, free of other processes' contention.
    :param start_step: stream step at which execution started.
    :param completion_step: stream step at which it completed or timed out (-1 while running).
    :param outcome: "completed", "timeout" or "running".
    :param success: completed without any arm-arm contact.
    :param collisions: number of steps with an arm-arm contact during execution.
    :param waypoints_reached: waypoints reached before it ended.
    :param error: adaptation error (the unadapted policy was used instead), empty if none.
    """

    sequence: int
    instruction: str
    arrival_time: float
    dequeue_time: float
    adaptation_time_s: float = 0.0
    first_action_time: float = float("nan")
    latency_s: float = float("nan")
    service_latency_s: float = float("nan")
    service_cpu_s: float = float("nan")
    start_step: int = -1
    completion_step: int = -1
    outcome: str = "running"
    success: bool = False
    collisions: int = 0
    waypoints_reached: int = 0
    error: str = ""


class OnlineController:
    """Algorithm 1: hold on an empty queue, dequeue, adapt, execute until done or timeout, reset to θ, repeat.

    :param model: an :class:`~vafn_sb3.common.adaptation.Adaptable` (e.g. :class:`~vafn_sb3.MAMLSAC`); with ``k=0`` or
        a model without ``adapt`` (any ``predict``-able policy) the unadapted policy executes every instruction.
    :param env: a ``VAFN/ThreeArmStream-v1`` env (possibly wrapped) created with ``auto_dequeue=False``.
    :param k: adaptation rounds per instruction (default: the model's ``inner_steps``, 0 for models without ``adapt``).
    :param n_support: support transitions per instruction, collected on the twin env. The support rollout dominates the
        reaction time (about 1.1 ms per transition on one unloaded thread): 25 keeps dequeue -> first action under
        100 ms with K <= 5; larger supports give better-informed adaptation at a proportional latency cost.
    :param seed: base seed of the support rollouts (instruction ``i`` uses ``seed + sequence``).
    :param deterministic: execute the adapted policy's deterministic action.
    """

    def __init__(
        self, model: Any, env: gym.Env, k: int | None = None, n_support: int = 25, seed: int = 0,
        deterministic: bool = True,
    ) -> None:
        stream = env.unwrapped
        if not isinstance(stream, MultiArmStreamEnv):
            raise TypeError(f"env must be a MultiArmStreamEnv (VAFN/ThreeArmStream-v1), got {type(stream).__name__}")
        if stream.auto_dequeue:
            raise ValueError("create the stream env with auto_dequeue=False: the controller dequeues itself")
        can_adapt = callable(getattr(model, "adapt", None))
        k = (getattr(model, "inner_steps", 0) if can_adapt else 0) if k is None else int(k)
        if k < 0 or n_support < 1:
            raise ValueError(f"need k >= 0 and n_support >= 1, got k={k}, n_support={n_support}")
        if k > 0 and not can_adapt:
            raise TypeError(f"{type(model).__name__} has no adapt(); use k=0")
        self.model = model
        self.env = env
        self.stream = stream
        self.k = k
        self.n_support = int(n_support)
        self.seed = int(seed)
        self.deterministic = deterministic
        self.twin = MultiArmEnv(**stream.world_kwargs) if k > 0 else None
        self.hold_action = np.zeros(stream.action_space.shape, dtype=np.float32)
        self.log: list[InstructionLog] = []
        #: Every line the stream reported: rejected instructions and arrivals that could not be queued.
        self.errors: list[str] = []
        #: Every queued instruction the stream could not start: ``sequence``, ``source``, ``reason``, ``step``.
        self.rejected: list[dict[str, Any]] = []
        self._collected = (0, 0)  # how many of the stream's errors and rejections of this episode were copied
        #: Per-step trace for plots: stream step, distances of the arms to their current targets, running sequence.
        self.trace: dict[str, list] = {"step": [], "distances": [], "sequence": []}
        self._obs: np.ndarray | None = None
        self._policy: Any = None
        self._current: InstructionLog | None = None
        self._dequeue_cpu = 0.0
        #: One row per :meth:`announce_dynamics`: stream step, the dynamics, the instruction re-adapted (or -1),
        #: adaptation wall time and announcement -> first action sent after it (``first_action_s``; NaN until then).
        self.dynamics_events: list[dict[str, Any]] = []

    @property
    def dropped(self) -> list[QueuedInstruction]:
        """Every entry the stream's queue evicted (``overflow="drop_oldest"``), oldest first, as a copy."""
        return list(self.stream.dropped)

    def _collect(self) -> None:
        """Copy the stream's new errors and rejections (the stream keeps them per episode only)."""
        n_errors, n_rejected = self._collected
        self.errors.extend(self.stream.errors[n_errors:])
        self.rejected.extend(self.stream.rejected[n_rejected:])
        self._collected = (len(self.stream.errors), len(self.stream.rejected))

    # --- Algorithm 1 ---
    def announce_dynamics(self, dynamics: Any) -> None:
        """The robot now follows ``dynamics`` (a :class:`vafn_gym.Dynamics`, a dict of its fields, or ``None`` for
        the nominal robot): the twin takes them, and a running instruction is adapted again before the next action.

        Raises ``ValueError``/``TypeError`` naming a bad field before anything changes.
        """
        dynamics = Dynamics.coerce(dynamics)
        if self.twin is not None:
            self.twin.set_dynamics(dynamics)
        event = {"step": self.stream.total_steps, "dynamics": dynamics.label, "sequence": -1,
                 "adaptation_time_s": 0.0, "announced": time.perf_counter(), "first_action_s": float("nan")}
        if self._current is not None and self.k > 0:
            event["sequence"] = self._current.sequence
            self._policy, event["adaptation_time_s"] = self._adapt(self._current, self._current.sequence)
        self.dynamics_events.append(event)

    def _adapt(self, entry: InstructionLog, sequence: int) -> tuple[Any, float]:
        """The model adapted to the running instruction on the twin (the unadapted model if adaptation fails, the
        error recorded), and the wall time it took."""
        start = time.perf_counter()
        try:
            policy = self.model.adapt(self.twin, task=self.stream.instruction, n_support=self.n_support, k=self.k,
                                      seed=self.seed + sequence)
        except Exception as error:  # noqa: BLE001 - a failed adaptation must not stop the arms' loop
            policy = self.model
            entry.error = f"{type(error).__name__}: {error}"
            self.errors.append(f"instruction #{sequence}: adaptation failed, unadapted policy used: {entry.error}")
        return policy, time.perf_counter() - start

    def _begin(self, item: QueuedInstruction) -> None:
        """Adapt to a freshly dequeued instruction and open its log row."""
        entry = InstructionLog(
            sequence=item.sequence, instruction=self.stream.instruction.to_code(), arrival_time=item.arrival_time,
            dequeue_time=time.perf_counter(), start_step=self.stream.total_steps,
        )
        self._dequeue_cpu = time.thread_time()
        self._policy = self.model
        reset = getattr(self.model, "reset", None)
        if callable(reset):  # a policy with per-instruction state (e.g. TargetInferencePolicy) starts afresh
            reset()
        if self.k > 0:
            self._policy, entry.adaptation_time_s = self._adapt(entry, item.sequence)
        self._current = entry
        self.log.append(entry)

    def _finish(self, record: dict[str, Any]) -> None:
        """Close the log row of a completed or timed-out instruction and reset to θ."""
        entry = self._current
        if entry is None or record["sequence"] != entry.sequence:
            raise RuntimeError(f"stream finished instruction #{record['sequence']}, controller was running {entry}")
        entry.completion_step = record["end_step"]
        entry.outcome = record["outcome"]
        entry.success = bool(record["success"])
        entry.waypoints_reached = int(record["waypoints_reached"])
        self._current = None
        self._policy = None  # reset to θ: the adapted parameters are dropped, the model was never modified

    def step(self) -> dict[str, Any]:
        """One control step of Algorithm 1; returns the stream's info dict."""
        if self._obs is None:
            self._obs, _ = self.env.reset(seed=self.seed)
            self._collected = (0, 0)
        if self.stream.current is None:
            item = self.stream.start_next()
            self._collect()
            if item is not None:
                self._begin(item)
                # The instruction changed the phase flags and targets: observe again before acting (the stream has no
                # public "observe" yet, so its observation builder is called directly).
                self._obs = self.stream.observe()
        if self._current is None:
            action = self.hold_action
        else:
            action, _ = self._policy.predict(self._obs, deterministic=self.deterministic)
            if self.dynamics_events and np.isnan(self.dynamics_events[-1]["first_action_s"]):
                event = self.dynamics_events[-1]
                event["first_action_s"] = time.perf_counter() - event["announced"]
            if np.isnan(self._current.first_action_time):
                now = time.perf_counter()
                self._current.first_action_time = now
                self._current.latency_s = now - self._current.arrival_time
                self._current.service_latency_s = now - self._current.dequeue_time
                self._current.service_cpu_s = time.thread_time() - self._dequeue_cpu
        self._obs, _, terminated, truncated, info = self.env.step(action)
        self._collect()
        if self._current is not None:
            self._current.collisions += int(info["collision"])
        for record in info["finished"]:
            self._finish(record)
        self.trace["step"].append(info["total_steps"])
        self.trace["distances"].append(np.asarray(info["distances"], dtype=np.float32))
        self.trace["sequence"].append(info["instruction_sequence"])
        if terminated or truncated:
            self._obs = None
            if self._current is not None:
                self._current.outcome = "cut by episode end"
                self._current = None
                self._policy = None
        return info

    def run(self, n_steps: int) -> list[InstructionLog]:
        """Run ``n_steps`` control steps (resetting the stream at its horizon); returns the per-instruction log."""
        if n_steps < 0:
            raise ValueError(f"n_steps must be >= 0, got {n_steps}")
        for _ in range(n_steps):
            self.step()
        return self.log

    def close(self) -> None:
        """Close the twin env (the stream env belongs to the caller)."""
        if self.twin is not None:
            self.twin.close()

    # --- outputs ---
    def write_csv(self, path: str | Path) -> Path:
        """Write the per-instruction log as CSV (one row per instruction, columns = :class:`InstructionLog` fields)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=[f.name for f in fields(InstructionLog)])
            writer.writeheader()
            for entry in self.log:
                writer.writerow(asdict(entry))
        return path
