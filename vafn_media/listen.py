"""Live commands: continuous audio (a microphone, a long recording, raw PCM on stdin) -> utterances -> the stream.

A *source* yields mono float32 chunks; :class:`VoiceActivitySegmenter` cuts them into utterances with Silero VAD (its
model ships in the ``silero-vad`` wheel and runs on torch); :class:`Listener` runs both on a background thread and
hands each utterance to a callback, and :func:`listen` submits each one to a :class:`~vafn_media.MultimediaStream`.

    from vafn_media.listen import listen, open_source
    listener = listen(stream, open_source("commands.wav"))   # None: the microphone; "-": 16-bit PCM on stdin
    listener.wait()

Each submission's metadata carries the utterance's stream times and ``speech_end_at``, the wall time the end of its
speech arrived, so :func:`end_of_speech_latency` of a queue entry is end-of-speech -> enqueued.
"""

from __future__ import annotations

import collections
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, BinaryIO

import numpy as np

#: Silero VAD's rate and window (32 ms); sources at other rates are resampled to it.
VAD_RATE: int = 16_000
VAD_WINDOW: int = 512
#: Length of the chunks the sources deliver (seconds).
CHUNK_S: float = 0.032
#: Speech starts at a window with probability >= threshold and goes on while windows stay >= threshold - HYSTERESIS.
HYSTERESIS: float = 0.15
#: The background level is this percentile of the window levels of the last FLOOR_HISTORY_S (never below
#: MIN_FLOOR_DB dBFS, so digital silence does not make every sound "loud").
FLOOR_PERCENTILE: float = 10.0
FLOOR_HISTORY_S: float = 10.0
MIN_FLOOR_DB: float = -90.0
SOUNDDEVICE_INSTALL = "pip install sounddevice; apt-get install libportaudio2"
SILERO_INSTALL = "pip install silero-vad (part of vafn[media])"


class LiveInputError(RuntimeError):
    """A live audio source that cannot be opened (missing package, no microphone, unreadable file)."""


# --- sources ---
class AudioStreamSource:
    """Continuous mono audio at :attr:`rate` Hz, delivered as float32 chunks by :meth:`chunks` until it ends."""

    rate: int = VAD_RATE

    def chunks(self) -> Iterator[np.ndarray]:
        """Yield float32 mono chunks until the audio ends or :meth:`close` is called."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop delivering chunks (called from another thread)."""
        self._closed = True

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return getattr(self, "_closed", False)


class RecordingSource(AudioStreamSource):
    """A recording read in chunks: a file of any length (read lazily) or a ``(waveform, rate)`` pair.

    :param recording: path to a WAV/FLAC/OGG file, or ``(waveform, rate)``.
    :param realtime: deliver each chunk when it would have been heard (a replayed recording); False: as fast as read.
    :param chunk_s: chunk length, seconds.
    """

    def __init__(self, recording: str | os.PathLike | tuple[np.ndarray, int], realtime: bool = False,
                 chunk_s: float = CHUNK_S) -> None:
        self.recording = recording
        self.realtime = bool(realtime)
        if isinstance(recording, tuple):
            waveform, rate = recording
            self.rate = int(rate)
            self._waveform = _mono(np.asarray(waveform))
        else:
            import soundfile

            try:
                self.rate = int(soundfile.info(str(recording)).samplerate)
            except Exception as error:  # noqa: BLE001 - soundfile raises its own types for unreadable files
                raise LiveInputError(f"cannot read the recording {recording}: {error}") from error
            self._waveform = None
        self.chunk = max(1, int(round(chunk_s * self.rate)))

    def _blocks(self) -> Iterator[np.ndarray]:
        if self._waveform is not None:
            for start in range(0, len(self._waveform), self.chunk):
                yield self._waveform[start:start + self.chunk]
            return
        import soundfile

        with soundfile.SoundFile(str(self.recording)) as handle:
            while True:
                block = handle.read(self.chunk, dtype="float32", always_2d=True)
                if not len(block):
                    return
                yield block.mean(axis=1)

    def chunks(self) -> Iterator[np.ndarray]:
        """Yield the recording's chunks, paced in real time when :attr:`realtime` (from :attr:`started_at`)."""
        started, delivered = time.perf_counter(), 0
        #: ``perf_counter`` time the first chunk was asked for: a paced sample at ``t`` s arrives at ``started_at + t``.
        self.started_at = started
        for block in self._blocks():
            if self.closed:
                return
            delivered += len(block)
            if self.realtime:
                time.sleep(max(0.0, started + delivered / self.rate - time.perf_counter()))
            yield block


class PcmSource(AudioStreamSource):
    """Raw signed 16-bit little-endian PCM from a binary stream (default: stdin), e.g. ``arecord -f S16_LE -r 16000``.

    :param stream: a binary file object.
    :param rate: its sample rate, Hz.
    :param channels: interleaved channels (mixed to mono).
    :param chunk_s: chunk length, seconds.
    """

    def __init__(self, stream: BinaryIO | None = None, rate: int = VAD_RATE, channels: int = 1,
                 chunk_s: float = CHUNK_S) -> None:
        if rate <= 0 or channels <= 0:
            raise LiveInputError(f"PCM needs a positive rate and channel count, got {rate} Hz, {channels} channels")
        self.stream = stream if stream is not None else sys.stdin.buffer
        self.rate, self.channels = int(rate), int(channels)
        self.frame_bytes = 2 * self.channels
        self.chunk_bytes = max(1, int(round(chunk_s * self.rate))) * self.frame_bytes

    def chunks(self) -> Iterator[np.ndarray]:
        """Yield chunks until end of file; a trailing partial frame is dropped."""
        pending = b""
        while not self.closed:
            data = self.stream.read(self.chunk_bytes - len(pending))
            if not data:
                break
            pending += data
            if len(pending) < self.chunk_bytes:  # a pipe may deliver less than asked: wait for the rest
                continue
            yield _pcm_to_float(pending, self.channels)
            pending = b""
        usable = len(pending) - len(pending) % self.frame_bytes
        if usable and not self.closed:
            yield _pcm_to_float(pending[:usable], self.channels)


def _pcm_to_float(data: bytes, channels: int) -> np.ndarray:
    samples = np.frombuffer(data, dtype="<i2").astype(np.float32) / 32768.0
    return samples.reshape(-1, channels).mean(axis=1) if channels > 1 else samples


def _sounddevice() -> Any:
    """The ``sounddevice`` module, or :class:`LiveInputError` saying what to install."""
    try:
        import sounddevice
    except (ImportError, OSError) as error:  # OSError: the package is there but PortAudio is not
        raise LiveInputError(f"microphone input needs the sounddevice package and PortAudio ({SOUNDDEVICE_INSTALL}): "
                             f"{error}") from error
    return sounddevice


class MicrophoneSource(AudioStreamSource):
    """A microphone through ``sounddevice`` (PortAudio), imported only when opened.

    :param device: sounddevice's input device (index or name; None: the default input).
    :param rate: capture rate, Hz.
    :param chunk_s: chunk length, seconds.
    """

    def __init__(self, device: int | str | None = None, rate: int = VAD_RATE, chunk_s: float = CHUNK_S) -> None:
        self.sd = _sounddevice()
        try:
            self.sd.query_devices(device, "input")
        except Exception as error:  # noqa: BLE001 - ValueError or PortAudioError, depending on the failure
            raise LiveInputError(f"no microphone found (sounddevice input device {device!r}): {error}") from error
        self.device, self.rate = device, int(rate)
        self.chunk = max(1, int(round(chunk_s * self.rate)))
        #: Chunks PortAudio reported as overflowed (audio lost because this process was too slow).
        self.overflows = 0

    def chunks(self) -> Iterator[np.ndarray]:
        """Yield captured chunks until :meth:`close` is called."""
        import queue

        captured: queue.Queue[np.ndarray] = queue.Queue()

        def callback(indata: np.ndarray, frames: int, time_info: Any, status: Any) -> None:
            if status:
                self.overflows += 1
            captured.put(indata[:, 0].copy())

        with self.sd.InputStream(samplerate=self.rate, channels=1, dtype="float32", blocksize=self.chunk,
                                 device=self.device, callback=callback):
            while not self.closed:
                try:
                    yield captured.get(timeout=0.1)
                except queue.Empty:
                    continue


def open_source(spec: str | None = None, realtime: bool = True, rate: int = VAD_RATE) -> AudioStreamSource:
    """A source from a command-line value: None or "mic" the microphone, "-" 16-bit PCM on stdin, else a recording.

    :param spec: None/"mic", "-" or a file path.
    :param realtime: replay a recording in real time (as if heard live).
    :param rate: the rate of PCM on stdin (and of microphone capture), Hz.
    """
    if spec is None or spec == "mic":
        return MicrophoneSource(rate=rate)
    if spec == "-":
        return PcmSource(rate=rate)
    if not os.path.isfile(spec):
        raise LiveInputError(f"--listen {spec}: no such file")
    return RecordingSource(spec, realtime=realtime)


def _mono(samples: np.ndarray) -> np.ndarray:
    """float32 mono samples of a chunk, or ValueError for what cannot be audio."""
    from vafn_media.audio import _to_mono_float

    waveform = _to_mono_float(samples)
    if waveform.size and not np.isfinite(waveform).all():
        raise ValueError(f"audio chunk holds {np.count_nonzero(~np.isfinite(waveform))} NaN or infinite samples")
    return waveform


# --- segmentation ---
@dataclass(frozen=True)
class Utterance:
    """One stretch of speech found in a stream.

    :param index: 0-based order in the stream.
    :param waveform: float32 samples at :data:`VAD_RATE`: the pre-roll, the speech and the silence heard after it.
    :param start_s: stream time (seconds from the first sample) the speech began, by the VAD.
    :param end_s: stream time the speech ended (end of its last speech window).
    :param detected_s: stream time the segmenter closed it (``end_s`` + the minimum silence, or at the maximum length).
    :param detected_at: ``time.perf_counter()`` when it was closed.
    :param truncated: closed at the maximum length rather than at a silence.
    """

    index: int
    waveform: np.ndarray
    start_s: float
    end_s: float
    detected_s: float
    detected_at: float
    truncated: bool = False

    @property
    def rate(self) -> int:
        """Sample rate of :attr:`waveform`."""
        return VAD_RATE

    @property
    def speech_end_at(self) -> float:
        """``perf_counter`` time the end of the speech arrived, for a source delivered in real time."""
        return self.detected_at - (self.detected_s - self.end_s)


def load_vad_model() -> Any:
    """A fresh Silero VAD (TorchScript, from the ``silero-vad`` wheel's data; no download, no torchaudio)."""
    import importlib.resources

    import torch

    try:
        path = importlib.resources.files("silero_vad.data").joinpath("silero_vad.jit")
    except ModuleNotFoundError as error:
        raise LiveInputError(f"voice-activity detection needs the silero-vad package ({SILERO_INSTALL})") from error
    with importlib.resources.as_file(path) as file:
        model = torch.jit.load(str(file), map_location="cpu")
    return model.eval()


class VoiceActivitySegmenter:
    """Cuts a continuous stream into utterances with Silero VAD (streaming, 32 ms windows at 16 kHz) and a level gate.

    A window is speech when Silero says so *and* it is at least ``level_gate_db`` above the background (the
    :data:`FLOOR_PERCENTILE` of the last :data:`FLOOR_HISTORY_S` of window levels) and within ``drop_db`` of the
    utterance's loudest window: quieter talk behind the speaker (babble) and the VAD's lingering after the last word
    do not count. An utterance closes after ``min_silence_s`` without speech (so it is handed on that long after its
    end), or at ``max_utterance_s``; stretches with less than ``min_speech_s`` of speech are dropped (clicks, coughs).

    :param threshold: speech probability that starts an utterance.
    :param min_silence_s: silence that ends one, and so the delay from the end of speech to the hand-on. Speakers
        pause up to ~0.35 s between the items of a command ("two, then one, then three"): 0.4 s keeps those
        commands whole; 0.2 s hands on within 300 ms but splits them (docs/multimedia.md, "Live commands").
    :param pre_roll_s: audio kept before the first speech window, so word onsets are not cut.
    :param min_speech_s: shortest speech kept.
    :param max_utterance_s: longest utterance (then it is closed and a new one starts).
    :param level_gate_db: how far above the background a speech window must be.
    :param drop_db: how far below the utterance's loudest window its speech may fall.
    :param model: a Silero VAD model (default: :func:`load_vad_model`).
    """

    def __init__(self, threshold: float = 0.5, min_silence_s: float = 0.4, pre_roll_s: float = 0.2,
                 min_speech_s: float = 0.15, max_utterance_s: float = 8.0, level_gate_db: float = 9.0,
                 drop_db: float = 35.0, model: Any = None) -> None:
        if not 0.0 < threshold < 1.0 or min_silence_s <= 0 or pre_roll_s < 0 or max_utterance_s <= min_speech_s:
            raise ValueError(f"need 0 < threshold < 1, min_silence_s > 0, pre_roll_s >= 0 and max_utterance_s > "
                             f"min_speech_s; got {threshold}, {min_silence_s}, {pre_roll_s}, {max_utterance_s}, "
                             f"{min_speech_s}")
        self.threshold, self.min_silence_s, self.min_speech_s = threshold, min_silence_s, min_speech_s
        self.max_utterance_s = max_utterance_s
        self.level_gate_db, self.drop_db = level_gate_db, drop_db
        self.model = load_vad_model() if model is None else model
        self._pre_windows = int(np.ceil(pre_roll_s * VAD_RATE / VAD_WINDOW))
        #: Speech stretches dropped as shorter than ``min_speech_s``.
        self.dropped = 0
        self.reset()

    def reset(self) -> None:
        """Forget the stream: times restart at 0, the VAD's state is cleared."""
        self.model.reset_states()
        self._rate, self._resampler = VAD_RATE, None
        self._buffer = np.zeros(0, np.float32)
        self._samples = 0
        self._pre: collections.deque[np.ndarray] = collections.deque(maxlen=self._pre_windows + 1)
        self._parts: list[np.ndarray] | None = None
        self._start_s = self._last_speech_s = 0.0
        self._peak_db = -np.inf
        self._levels: collections.deque[float] = collections.deque(maxlen=int(FLOOR_HISTORY_S * VAD_RATE / VAD_WINDOW))
        self._count = 0

    @property
    def floor_db(self) -> float:
        """The background level (dBFS): a low percentile of the recent window levels (-90 until 1 s is heard)."""
        if len(self._levels) < VAD_RATE // VAD_WINDOW:
            return MIN_FLOOR_DB
        return max(MIN_FLOOR_DB, float(np.percentile(self._levels, FLOOR_PERCENTILE)))

    @property
    def time_s(self) -> float:
        """Stream time of the audio analysed so far, seconds."""
        return self._samples / VAD_RATE

    def feed(self, chunk: np.ndarray, rate: int = VAD_RATE) -> list[Utterance]:
        """Analyse a chunk of the stream; returns the utterances it closed (usually none). ValueError on bad audio.

        :param chunk: mono (or multi-channel) samples, float or integer PCM.
        :param rate: their sample rate, Hz (the same for the whole stream, or the resampler restarts).
        """
        waveform = _mono(np.asarray(chunk))
        if rate != self._rate or (rate != VAD_RATE and self._resampler is None):
            if not 8_000 <= rate <= 192_000:
                raise ValueError(f"sample rate {rate} Hz is outside 8000..192000 Hz")
            import soxr

            self._rate = int(rate)
            self._resampler = None if rate == VAD_RATE else soxr.ResampleStream(rate, VAD_RATE, 1, dtype="float32")
        if self._resampler is not None:
            waveform = self._resampler.resample_chunk(waveform)
        self._buffer = np.concatenate([self._buffer, waveform])
        found = []
        while len(self._buffer) >= VAD_WINDOW:
            window, self._buffer = self._buffer[:VAD_WINDOW], self._buffer[VAD_WINDOW:]
            utterance = self._step(window)
            if utterance is not None:
                found.append(utterance)
        return found

    def flush(self) -> list[Utterance]:
        """Close the utterance in progress at the end of the stream (if it holds enough speech)."""
        if self._parts is None:
            return []
        utterance = self._close(truncated=False)
        return [] if utterance is None else [utterance]

    def _step(self, window: np.ndarray) -> Utterance | None:
        import torch

        with torch.inference_mode():
            probability = float(self.model(torch.from_numpy(np.ascontiguousarray(window)), VAD_RATE))
        level = 10.0 * float(np.log10(np.mean(np.square(window, dtype=np.float64)) + 1e-12))
        self._levels.append(level)
        loud = level >= max(self.floor_db + self.level_gate_db, self._peak_db - self.drop_db)
        start_s = self.time_s
        self._samples += VAD_WINDOW
        if self._parts is None:
            self._pre.append(window)
            if probability < self.threshold or not loud:
                return None
            self._parts, self._start_s, self._last_speech_s = list(self._pre), start_s, self.time_s
            self._peak_db = level
            self._pre.clear()
            return None
        self._parts.append(window)
        if probability >= self.threshold - HYSTERESIS and loud:
            self._last_speech_s = self.time_s
            self._peak_db = max(self._peak_db, level)
        if self.time_s - self._last_speech_s >= self.min_silence_s:
            return self._close(truncated=False)
        if self.time_s - self._start_s >= self.max_utterance_s:
            return self._close(truncated=True)
        return None

    def _close(self, truncated: bool) -> Utterance | None:
        parts, self._parts, self._peak_db = self._parts, None, -np.inf
        if self._last_speech_s - self._start_s < self.min_speech_s:
            self.dropped += 1
            return None
        utterance = Utterance(self._count, np.concatenate(parts), self._start_s, self._last_speech_s, self.time_s,
                              time.perf_counter(), truncated)
        self._count += 1
        return utterance


# --- running it ---
class Listener:
    """Reads a source on a background thread (or in :meth:`run`), segments it and hands each utterance on.

    Bad chunks, a failing callback and a source that breaks off are recorded in :attr:`errors`; none stops the loop
    (a broken source ends it, like the end of a recording).

    :param source: an :class:`AudioStreamSource`.
    :param on_utterance: called with each :class:`Utterance` (on the listener's thread); its return value is kept in
        :attr:`results` under the utterance's index.
    :param segmenter: a :class:`VoiceActivitySegmenter` (default: one with its defaults).
    """

    def __init__(self, source: AudioStreamSource, on_utterance: Callable[[Utterance], Any] | None = None,
                 segmenter: VoiceActivitySegmenter | None = None) -> None:
        self.source = source
        self.on_utterance = on_utterance
        self.segmenter = segmenter if segmenter is not None else VoiceActivitySegmenter()
        self.utterances: list[Utterance] = []
        self.results: dict[int, Any] = {}
        self.errors: list[str] = []
        self._thread: threading.Thread | None = None
        self._done = threading.Event()

    def run(self) -> list[Utterance]:
        """Listen in this thread until the source ends or :meth:`stop`; returns the utterances found."""
        from vafn_media.stream import _describe

        try:
            for chunk in self.source.chunks():
                try:
                    found = self.segmenter.feed(chunk, self.source.rate)
                except Exception as error:  # noqa: BLE001 - a bad chunk is skipped, never the end of listening
                    self.errors.append(f"chunk at {self.segmenter.time_s:.2f} s skipped: {_describe(error)}")
                    continue
                for utterance in found:
                    self._emit(utterance)
                if self.source.closed:
                    break
            for utterance in self.segmenter.flush():
                self._emit(utterance)
        except Exception as error:  # noqa: BLE001 - the source broke off: record why, end like a finished recording
            self.errors.append(f"audio source stopped: {_describe(error)}")
        finally:
            self._done.set()
        return self.utterances

    def _emit(self, utterance: Utterance) -> None:
        from vafn_media.stream import _describe

        self.utterances.append(utterance)
        if self.on_utterance is None:
            return
        try:
            self.results[utterance.index] = self.on_utterance(utterance)
        except Exception as error:  # noqa: BLE001 - e.g. a full stream backlog: report, keep listening
            self.errors.append(f"utterance {utterance.index} at {utterance.start_s:.2f} s not handed on: "
                               f"{_describe(error)}")

    def start(self) -> Listener:
        """Listen on a background thread."""
        if self._thread is None:
            self._thread = threading.Thread(target=self.run, name="vafn-listener", daemon=True)
            self._thread.start()
        return self

    @property
    def finished(self) -> bool:
        """Whether the source ended (or was stopped) and every utterance was handed on."""
        return self._done.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until :attr:`finished` (or ``timeout`` seconds); True when finished."""
        return self._done.wait(timeout)

    def stop(self, timeout: float | None = 2.0) -> None:
        """Close the source and wait for the thread to end."""
        self.source.close()
        if self._thread is not None:
            self._thread.join(timeout)


def submit_to(stream: Any) -> Callable[[Utterance], int]:
    """A callback that submits an utterance to a ``MultimediaStream``, with its times in the entry's metadata."""

    def submit(utterance: Utterance) -> int:
        return stream.submit(audio=(utterance.waveform, utterance.rate), metadata={
            "utterance": utterance.index, "speech_start_s": utterance.start_s, "speech_end_s": utterance.end_s,
            "detected_s": utterance.detected_s, "speech_end_at": utterance.speech_end_at,
        })

    return submit


def listen(stream: Any, source: AudioStreamSource, segmenter: VoiceActivitySegmenter | None = None,
           background: bool = True) -> Listener:
    """Read ``source`` into ``stream``: every utterance is submitted as audio (the stream reads and enqueues it).

    :param stream: a started :class:`~vafn_media.MultimediaStream`.
    :param source: continuous audio (:func:`open_source`).
    :param segmenter: the voice-activity segmenter (default settings when None).
    :param background: listen on a thread and return at once; False: return when the source has ended.
    """
    listener = Listener(source, submit_to(stream), segmenter)
    if background:
        return listener.start()
    listener.run()
    return listener


def end_of_speech_latency(metadata: dict) -> float:
    """End of speech -> enqueued (seconds) of a queue entry submitted by :func:`listen` (NaN for other entries)."""
    if "speech_end_at" not in metadata or "latency_s" not in metadata:
        return float("nan")
    return metadata["submitted_at"] + metadata["latency_s"] - metadata["speech_end_at"]
