"""The asynchronous multimedia stream: a background thread transcribes submitted media into the instruction queue."""

from __future__ import annotations

import itertools
import queue as _queue
import threading
import time
from dataclasses import dataclass, field
from collections.abc import Callable
from typing import Any

from vafn_media.constants import LOW_CONFIDENCE

#: How long the worker waits for a request before re-checking for shutdown (seconds).
_POLL_SECONDS = 0.05


def _describe(error: BaseException) -> str:
    """``"Type: message"`` of an exception, cut to a readable length."""
    try:
        message = str(error)
    except Exception:  # noqa: BLE001 - an exception with a broken __str__ must not take the worker down with it
        message = "<unprintable message>"
    if len(message) > 200:
        message = message[:197] + "..."
    return f"{type(error).__name__}: {message}"


@dataclass(frozen=True)
class StreamEvent:
    """What happened to one submitted request.

    :param ticket: the id returned by :meth:`MultimediaStream.submit`.
    :param status: "enqueued", "rejected" (low confidence), "error" (bad input, full queue, …) or "cancelled"
        (the stream stopped before handling it).
    :param message: the reason for a rejection, an error or a cancellation ("" when enqueued).
    :param transcription: the generator's result, when there was one.
    :param latency_s: submit -> enqueue (or -> failure) wall time, seconds.
    """

    ticket: int
    status: str
    message: str = ""
    transcription: Any = None
    latency_s: float = 0.0


@dataclass
class _Request:
    ticket: int
    submitted_at: float
    kwargs: dict
    metadata: dict = field(default_factory=dict)


class MultimediaStream:
    """Runs an :class:`InstructionGenerator` on a background thread and enqueues results into an ``InstructionQueue``.

    Each entry's ``source`` is the modalities that produced it (``"audio"``, ``"image"``, ``"audio+image"``,
    ``"code"``) and its ``metadata`` holds ``latency_s`` (submit -> enqueue), ``transcribe_s``, ``confidence``,
    ``confidences``, ``method``, ``warnings`` and ``ticket``. Results below ``min_confidence`` are not enqueued but
    reported as "rejected"; bad input and a full queue are reported as "error". The thread never dies: not on bad
    input, and not on a generator or ``on_event`` callback that raises (even ``SystemExit`` or ``KeyboardInterrupt``);
    such failures are kept in :attr:`errors`. Every submitted request gets exactly one event: a request the stream
    stops before handling, or one submitted after :meth:`stop`, is reported as "cancelled".

    :param instruction_queue: the destination ``vafn_gym.queue.InstructionQueue``.
    :param generator: the generator (default: the packaged checkpoint).
    :param min_confidence: results with a lower sequence confidence are rejected (0 disables; default: the
        generator's own ``low_confidence`` threshold, so a generator loaded with a looser one is not overruled).
    :param reject_flagged: also reject results the generator flagged ``low_confidence`` (warnings, disagreement);
        with False they are enqueued and the flag stays in the metadata.
    :param on_event: optional callback called with every :class:`StreamEvent`, on the worker thread (a cancellation
        outside the worker: on the thread calling :meth:`stop` or :meth:`submit`). It may call :meth:`stop`.
    :param max_pending: bound of the request backlog; ``submit`` raises ``queue.Full`` beyond it.
    """

    def __init__(
        self,
        instruction_queue: Any,
        generator: Any = None,
        min_confidence: float | None = None,
        reject_flagged: bool = True,
        on_event: Callable[[StreamEvent], None] | None = None,
        max_pending: int = 256,
    ) -> None:
        if generator is None:
            from vafn_media.generator import InstructionGenerator

            generator = InstructionGenerator.load()
        self.queue = instruction_queue
        self.generator = generator
        if min_confidence is None:
            min_confidence = getattr(generator, "low_confidence", LOW_CONFIDENCE)
        self.min_confidence = float(min_confidence)
        self.reject_flagged = bool(reject_flagged)
        self.on_event = on_event
        self.events: list[StreamEvent] = []
        #: Failures of the worker's own machinery (a raising ``on_event`` callback, ...), oldest first.
        self.errors: list[str] = []
        self._requests: _queue.Queue[_Request] = _queue.Queue(max_pending)
        self._tickets = itertools.count()
        self._stop = threading.Event()  # cancel what is pending and exit (after the request in hand)
        self._closed = False  # stop() was called: no new request is accepted, the worker exits once the backlog is gone
        self._submit_lock = threading.Lock()  # orders submit() against stop(), so no request slips past the worker
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    # --- lifecycle ---
    def start(self) -> MultimediaStream:
        """Start the worker thread (idempotent); after :meth:`stop` it starts a new one and accepts requests again."""
        if self.alive and not self._closed:
            return self
        if self._on_worker():
            raise RuntimeError("MultimediaStream.start() cannot restart the stream from its own worker (on_event)")
        if self._thread is not None:
            self._thread.join()  # a stopping worker: let it settle its backlog first
        with self._submit_lock:
            self._closed = False
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="vafn-multimedia-stream", daemon=True)
            self._thread.start()
        return self

    def stop(self, drain: bool = True, timeout: float | None = None) -> None:
        """Stop accepting requests and stop the worker; safe from any thread, ``on_event`` callbacks included.

        Every pending request still gets an event: with ``drain`` the worker handles the backlog first, otherwise (or
        once ``timeout`` has passed) the pending requests are reported "cancelled"; a request being transcribed
        finishes. Called from the worker itself (an ``on_event`` callback) it returns at once and the worker winds down
        after the callback. A stream that was never started cancels its pending requests here.

        :param drain: handle the backlog before stopping.
        :param timeout: seconds to wait for draining and the worker's exit, ``None`` for no limit.
        """
        with self._submit_lock:
            self._closed = True
        if not drain:
            self._stop.set()
        if self._on_worker():
            return
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():  # the drain ran out of time: cancel the rest, finish the request in hand
                self._stop.set()
        if not self.alive:
            self._cancel_pending()

    def _on_worker(self) -> bool:
        """Whether the caller runs on the worker thread (e.g. inside ``on_event``)."""
        return self._thread is not None and threading.current_thread() is self._thread

    def __enter__(self) -> MultimediaStream:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    @property
    def alive(self) -> bool:
        """Whether the worker thread is running."""
        return self._thread is not None and self._thread.is_alive()

    # --- producer side ---
    def submit(self, audio: Any = None, image: Any = None, code: Any = None, sample_rate: int | None = None,
               metadata: dict | None = None) -> int:
        """Queue media for transcription; returns a ticket. Arrival time is taken now.

        :param audio: audio path / waveform / (waveform, rate).
        :param image: image path / array.
        :param code: machine code.
        :param sample_rate: rate of a bare waveform.
        :param metadata: extras copied into the queue entry's metadata.
        """
        ticket = next(self._tickets)
        kwargs = {"audio": audio, "image": image, "code": code, "sample_rate": sample_rate}
        request = _Request(ticket, time.perf_counter(), kwargs, dict(metadata or {}))
        with self._submit_lock:
            if not self._closed:
                self._requests.put_nowait(request)
                return ticket
        self._record(self._cancelled(request))  # on the caller's thread: the worker is stopping or gone
        return ticket

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every submitted request was handled (or ``timeout`` seconds passed); True when drained.

        Returns at once when the worker is not running (never started, or stopped), or when called from the worker
        itself (an ``on_event`` callback): True only if nothing is pending.

        :param timeout: seconds, None for no limit.
        """
        deadline = None if timeout is None else time.perf_counter() + timeout
        while self._requests.unfinished_tasks:
            if not self.alive or self._on_worker() or (deadline is not None and time.perf_counter() > deadline):
                return False
            time.sleep(0.005)
        return True

    # --- worker ---
    def _record(self, event: StreamEvent) -> None:
        with self._lock:
            self.events.append(event)
        if self.on_event is not None:
            try:
                self.on_event(event)
            except BaseException as error:  # noqa: BLE001 - a faulty callback (even SystemExit) must not kill the stream
                self._error(f"on_event callback raised {_describe(error)} for ticket {event.ticket}")

    def _error(self, message: str) -> None:
        with self._lock:
            self.errors.append(message)

    def _handle(self, request: _Request) -> StreamEvent:
        started = time.perf_counter()
        try:
            result = self.generator.transcribe(**request.kwargs)
        except BaseException as error:  # noqa: BLE001 - bad input of any kind becomes an event, never a dead thread
            return StreamEvent(request.ticket, "error", _describe(error),
                               latency_s=time.perf_counter() - request.submitted_at)
        transcribe_s = time.perf_counter() - started
        if result.confidence < self.min_confidence or (self.reject_flagged and result.low_confidence):
            reasons = "; ".join(result.warnings) or f"below {self.min_confidence:.2f}"
            return StreamEvent(request.ticket, "rejected", f"low confidence {result.confidence:.2f}: {reasons}",
                               result, time.perf_counter() - request.submitted_at)
        metadata = {**request.metadata, "ticket": request.ticket, "transcribe_s": transcribe_s,
                    "confidence": result.confidence, "confidences": list(result.confidences),
                    "low_confidence": result.low_confidence, "method": result.method,
                    "warnings": list(result.warnings), "submitted_at": request.submitted_at}
        try:
            latency = time.perf_counter() - request.submitted_at
            metadata["latency_s"] = latency
            self.queue.enqueue(result.instruction, source="+".join(result.modalities), metadata=metadata)
        except Exception as error:  # noqa: BLE001 - QueueFullError, or anything the queue rejects
            return StreamEvent(request.ticket, "error", f"{type(error).__name__}: {error}", result,
                               time.perf_counter() - request.submitted_at)
        return StreamEvent(request.ticket, "enqueued", "", result, latency)

    def _cancelled(self, request: _Request) -> StreamEvent:
        """The event of a request the stream will not handle because it was stopped."""
        return StreamEvent(request.ticket, "cancelled", "the stream was stopped before handling it",
                           latency_s=time.perf_counter() - request.submitted_at)

    def _cancel_pending(self) -> None:
        """Report every request still waiting as "cancelled" and take it off the backlog."""
        while True:
            try:
                request = self._requests.get_nowait()
            except _queue.Empty:
                return
            try:
                self._record(self._cancelled(request))
            finally:
                self._requests.task_done()

    def _finished(self) -> bool:
        """Whether the worker may exit: told to stop, or closed with an empty backlog (nothing can be added then)."""
        return self._stop.is_set() or (self._closed and self._requests.empty())

    def _run(self) -> None:
        while not self._finished():
            try:
                request = self._requests.get(timeout=_POLL_SECONDS)
            except _queue.Empty:
                continue
            try:
                self._record(self._cancelled(request) if self._stop.is_set() else self._handle(request))
            except BaseException as error:  # noqa: BLE001 - last line of defence: the worker must outlive anything
                self._error(f"ticket {request.ticket}: {_describe(error)}")
                self._record(StreamEvent(request.ticket, "error", _describe(error)))
            finally:
                self._requests.task_done()
        self._cancel_pending()
