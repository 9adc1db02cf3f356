"""Loading and validating audio: any sample rate in range, mono float32, with clear errors for unusable input.

File lengths are checked from the header before anything is decoded; a WAV whose header promises more data than the
file holds (a truncated download or copy) is an error. Decoded clips are resampled to SAMPLE_RATE and checked for
what cannot be a complete spoken command: too short, silent, noise without speech, sound cut off at either end.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from vafn_media.constants import (
    CLIP_FRACTION,
    CLIP_LEVEL,
    MAX_AUDIO_SECONDS,
    MAX_SAMPLE_RATE,
    MIN_SAMPLE_RATE,
    SAMPLE_RATE,
    SILENCE_DBFS,
)

#: Shortest accepted clip (seconds): one short word ("two", "stop") lasts about 0.25 s.
MIN_AUDIO_SECONDS: float = 0.1
#: Frame length (seconds) of the level and flatness analysis, and the band (Hz) of the flatness (telephone band).
_FRAME_SECONDS: float = 0.02
_FLATNESS_BAND: tuple[float, float] = (100.0, 3400.0)
#: A clip whose most tonal frames (10th percentile) are this flat and whose level varies less than
#: NOISE_MAX_RANGE_DB is noise, not speech (Gaussian white noise: ~0.56; speech frames: < 0.2 even at 5 dB SNR).
NOISE_MIN_FLATNESS: float = 0.4
NOISE_MAX_RANGE_DB: float = 6.0
#: A clip is reported as cut when the sound in its last EDGE_SECONDS stands more than EDGE_FRACTION of the clip's
#: dynamic range (95th minus 10th percentile of frame levels) above its quietest frames. Only the end is checked:
#: speech synthesisers and trimmed clips often start abruptly, while a command that stops mid-sound is the signature
#: of a cut recording (measured with flite clips: 0/30 clean or noisy clips flagged, 22/30 halves and 17/30
#: three-quarter cuts flagged; a cut that falls in a pause between words cannot be told from a shorter command).
EDGE_SECONDS: float = 0.03
EDGE_FRACTION: float = 0.55
MIN_DYNAMIC_RANGE_DB: float = 10.0
#: Silence the reader adds where a clip starts or ends in a sound by the same test (trimmed at its words, as a
#: voice-activity detector leaves a clip): without it the reader lost the first or last word (docs/multimedia.md).
EDGE_PAD_SECONDS: float = 0.25

AudioSource = str | os.PathLike | np.ndarray | tuple[np.ndarray, int]
_INT_SCALE = {np.dtype(np.int16): 32768.0, np.dtype(np.int32): 2147483648.0, np.dtype(np.uint8): 128.0}


@dataclass
class Audio:
    """A validated mono clip at SAMPLE_RATE: float32 samples, their rate, non-fatal quality warnings, the input rate."""

    waveform: np.ndarray
    sample_rate: int
    warnings: list[str] = field(default_factory=list)
    source_rate: int = SAMPLE_RATE
    #: Whether the clip starts / ends in the middle of a sound (see :data:`EDGE_FRACTION`).
    sounding_edges: tuple[bool, bool] = (False, False)

    @property
    def seconds(self) -> float:
        """Duration in seconds."""
        return len(self.waveform) / self.sample_rate


def _wav_truncation(path: str) -> str | None:
    """For a RIFF/WAVE file, a description of how much its header's data chunk exceeds the file; None if intact."""
    import struct

    size = os.path.getsize(path)
    with open(path, "rb") as handle:
        head = handle.read(12)
        if len(head) < 12 or head[:4] != b"RIFF" or head[8:12] != b"WAVE":
            return None
        position = 12
        while position + 8 <= size:
            handle.seek(position)
            chunk_id, chunk_size = struct.unpack("<4sI", handle.read(8))
            if chunk_id == b"data":
                available = size - position - 8
                if chunk_size not in (0, 0xFFFFFFFF) and chunk_size > available:
                    return (f"its header declares {chunk_size} bytes of audio but only {available} are present "
                            f"({100 * available / chunk_size:.0f}%)")
                return None
            position += 8 + chunk_size + (chunk_size & 1)
    return "it has no data chunk"


def read_audio_file(path: str | os.PathLike) -> tuple[np.ndarray, int]:
    """Read a WAV/FLAC/OGG file with soundfile; corrupt, truncated or over-long files raise ValueError naming the file.

    The duration is checked from the header before decoding.

    :param path: file to read.
    """
    import soundfile

    name = os.fspath(path)
    if not os.path.isfile(name):
        raise ValueError(f"audio file {name!r} does not exist")
    truncated = _wav_truncation(name)
    if truncated:
        raise ValueError(f"audio file {name!r} is truncated: {truncated}")
    try:
        info = soundfile.info(name)
    except Exception as error:  # noqa: BLE001 - libsndfile raises its own error types
        raise ValueError(f"audio file {name!r} is corrupt or not a supported format: {error}") from error
    if info.samplerate > 0 and info.frames / info.samplerate > MAX_AUDIO_SECONDS:
        raise ValueError(f"audio file {name!r} lasts {info.frames / info.samplerate:.1f} s (from its header); "
                         f"at most {MAX_AUDIO_SECONDS:.0f} s are accepted")
    if not MIN_SAMPLE_RATE <= info.samplerate <= MAX_SAMPLE_RATE:
        raise ValueError(f"audio file {name!r} is sampled at {info.samplerate} Hz, outside the supported range "
                         f"{MIN_SAMPLE_RATE}..{MAX_SAMPLE_RATE} Hz")
    try:
        data, rate = soundfile.read(name, dtype="float32", always_2d=True)
    except Exception as error:  # noqa: BLE001 - libsndfile raises its own error types
        raise ValueError(f"audio file {name!r} is corrupt or not a supported format: {error}") from error
    if 0 < len(data) < info.frames:
        raise ValueError(f"audio file {name!r} is truncated: its header declares {info.frames} samples, "
                         f"only {len(data)} could be decoded")
    return data, int(rate)


@lru_cache(maxsize=4)
def _frame_analysis(size: int) -> tuple[np.ndarray, slice]:
    """Hann window and the rfft bins of the flatness band for ``size``-sample frames (built once, cached)."""
    hz = np.fft.rfftfreq(size, 1.0 / SAMPLE_RATE)
    band = np.flatnonzero((hz >= _FLATNESS_BAND[0]) & (hz <= _FLATNESS_BAND[1]))  # contiguous bins
    window = np.hanning(size)
    window.setflags(write=False)
    return window, slice(int(band[0]), int(band[-1]) + 1)


def _frames(waveform: np.ndarray) -> np.ndarray:
    """A clip at SAMPLE_RATE as rows of 20 ms frames (one shorter row when the whole clip is shorter)."""
    size = int(_FRAME_SECONDS * SAMPLE_RATE)
    count = max(1, len(waveform) // size)
    return waveform[: count * size].reshape(count, size) if len(waveform) >= size else waveform[None]


def _frame_levels(frames: np.ndarray) -> np.ndarray:
    """Level (dB) of each frame of :func:`_frames`."""
    return 10 * np.log10(np.mean(np.square(frames, dtype=np.float64), axis=1) + 1e-20)


def _frame_flatness(frames: np.ndarray) -> np.ndarray:
    """100-3400 Hz spectral flatness of each frame of :func:`_frames`."""
    window, band = _frame_analysis(frames.shape[1])
    # Only the band every input rate has. Column-major like the boolean-mask selection this replaces, so that the
    # means below sum in the same order and give the same numbers bit for bit.
    spectrum = np.abs(np.asfortranarray(np.fft.rfft(frames * window, axis=1)[:, band])) ** 2 + 1e-20
    return np.exp(np.mean(np.log(spectrum), axis=1)) / np.mean(spectrum, axis=1)


def _percentiles(values: np.ndarray, percents: tuple[float, ...]) -> list[float]:
    """``np.percentile(values, percents)`` of a 1-D array: the same numbers (its linear interpolation, done from the
    nearer neighbour as numpy does) without its overhead, which was most of the cost on a clip's few hundred frames."""
    ordered = np.sort(values).tolist()
    last = len(ordered) - 1
    result = []
    for percent in percents:
        position = last * (percent / 100)
        below = min(int(position), last)
        low, high = ordered[below], ordered[min(below + 1, last)]
        fraction = position - below
        result.append(high - (high - low) * (1 - fraction) if fraction >= 0.5 else low + (high - low) * fraction)
    return result


def speech_problems(waveform: np.ndarray) -> list[str]:
    """Why a clip at SAMPLE_RATE may not be a complete spoken command (warnings); ValueError when it is noise.

    :param waveform: float32 samples at SAMPLE_RATE.
    """
    return inspect_speech(waveform)[0]


def inspect_speech(waveform: np.ndarray) -> tuple[list[str], tuple[bool, bool]]:
    """:func:`speech_problems` and whether the clip starts / ends in the middle of a sound; ValueError when it is noise.

    :param waveform: float32 samples at SAMPLE_RATE.
    """
    frames = _frames(waveform)
    levels = _frame_levels(frames)
    floor, loud = _percentiles(levels, (10, 95))
    dynamic = loud - floor
    if dynamic < NOISE_MAX_RANGE_DB:  # the flatness (an FFT of every frame) decides only then
        (tonal,) = _percentiles(_frame_flatness(frames), (10,))
        if tonal > NOISE_MIN_FLATNESS:
            raise ValueError(f"audio is noise, not speech: its level varies by only {dynamic:.1f} dB and even its "
                             f"most tonal frames are flat (spectral flatness {tonal:.2f})")
    if dynamic < MIN_DYNAMIC_RANGE_DB:
        return [], (False, False)
    edge = max(1, int(round(EDGE_SECONDS / _FRAME_SECONDS)))
    start, end = (float(10 * np.log10(np.mean(10 ** (part / 10)))) - floor for part in (levels[:edge], levels[-edge:]))
    sounding = (start > EDGE_FRACTION * dynamic, end > EDGE_FRACTION * dynamic)
    problems = [f"audio ends in the middle of a sound ({end:.0f} dB above its quietest part): it may be cut off "
                "mid-word"] if sounding[1] else []
    return problems, sounding


def with_quiet_edges(clip: Audio) -> np.ndarray:
    """The clip's samples with :data:`EDGE_PAD_SECONDS` of silence added at an end where it is in a sound.

    :param clip: a validated clip (from :func:`load_audio`).
    """
    if not any(clip.sounding_edges):
        return clip.waveform
    pad = int(round(EDGE_PAD_SECONDS * clip.sample_rate))
    return np.pad(clip.waveform, tuple(pad if sounding else 0 for sounding in clip.sounding_edges))


def _to_mono_float(samples: np.ndarray) -> np.ndarray:
    array = np.asarray(samples)
    if array.dtype.kind not in "fiu" or array.dtype == np.bool_:
        raise ValueError(f"audio samples must be real numbers, got dtype {array.dtype}")
    if array.ndim == 2:
        channel_axis = 1 if array.shape[1] <= array.shape[0] else 0
        array = array.mean(axis=channel_axis)
    elif array.ndim != 1:
        raise ValueError(f"audio must be 1-D (mono) or 2-D (multi-channel), got shape {array.shape}")
    if array.dtype.kind in "iu":
        scale = _INT_SCALE.get(array.dtype)
        if scale is None:
            raise ValueError(f"unsupported integer audio dtype {array.dtype}; use int16, int32 or float")
        offset = 128.0 if array.dtype == np.uint8 else 0.0
        return ((array.astype(np.float32) - offset) / scale).astype(np.float32)
    return array.astype(np.float32, copy=False)


def load_audio(source: AudioSource, sample_rate: int | None = None) -> Audio:
    """Load and validate audio from a path, a ``(waveform, sample_rate)`` pair, or a waveform plus ``sample_rate``.

    Any rate from MIN_SAMPLE_RATE to MAX_SAMPLE_RATE is resampled to SAMPLE_RATE. Raises ValueError for empty,
    too short, non-finite, silent, noise-only, too long or wrongly sampled audio; clipping and sound cut off at either
    end are warnings.

    :param source: file path, numpy waveform, or (waveform, sample_rate) tuple.
    :param sample_rate: sample rate of a bare waveform (Hz); ignored for files.
    """
    from vafn_media.augment import resample

    if isinstance(source, (str, os.PathLike)):
        samples, rate = read_audio_file(source)
    elif isinstance(source, tuple):
        if len(source) != 2:
            raise ValueError("audio tuple must be (waveform, sample_rate)")
        samples, rate = source
    else:
        samples, rate = source, sample_rate
    if rate is None:
        raise ValueError("a waveform needs its sample_rate")
    if isinstance(rate, bool) or not isinstance(rate, (int, np.integer, float)) or float(rate) != int(rate):
        raise ValueError(f"sample rate must be an integer number of Hz, got {rate!r}")
    rate = int(rate)
    if not MIN_SAMPLE_RATE <= rate <= MAX_SAMPLE_RATE:
        raise ValueError(
            f"sample rate {rate} Hz is outside the supported range {MIN_SAMPLE_RATE}..{MAX_SAMPLE_RATE} Hz"
        )
    waveform = _to_mono_float(samples)
    if waveform.size == 0:
        raise ValueError("audio is empty (0 samples)")
    if waveform.size / rate > MAX_AUDIO_SECONDS:
        raise ValueError(f"audio lasts {waveform.size / rate:.1f} s; at most {MAX_AUDIO_SECONDS:.0f} s are accepted")
    low, high = float(waveform.min()), float(waveform.max())
    if not (np.isfinite(low) and np.isfinite(high)):  # both are NaN when any sample is
        raise ValueError(f"audio contains {np.count_nonzero(~np.isfinite(waveform))} NaN or infinite samples")
    if waveform.size / rate < MIN_AUDIO_SECONDS:
        raise ValueError(f"audio is too short to hold a command: {waveform.size} samples = "
                         f"{1000 * waveform.size / rate:.1f} ms (at least {1000 * MIN_AUDIO_SECONDS:.0f} ms)")
    peak = max(high, -low)
    # The float32 mean square is within 25 % of the exact one at any accepted length (n * 2**-24 < 0.25), so it
    # decides unless it is within a factor of two of the threshold; there the float64 one does, as always.
    mean_square = float(np.dot(waveform, waveform)) / waveform.size
    if mean_square < 2 * 10 ** (SILENCE_DBFS / 10):
        mean_square = float(np.mean(np.square(waveform, dtype=np.float64)))
    level_dbfs = 20 * np.log10(max(np.sqrt(mean_square), 1e-12))
    if peak == 0.0 or level_dbfs < SILENCE_DBFS:
        raise ValueError(f"audio is silent (RMS {level_dbfs:.0f} dBFS < {SILENCE_DBFS:.0f} dBFS)")
    warnings = []
    # A float waveform beyond full scale is intact (the features are level-normalised); clipping is flat tops at its
    # own peak, wherever that is.
    top = CLIP_LEVEL * max(peak, 1.0)
    clipped = float(np.mean(np.abs(waveform) >= top)) if peak >= top else 0.0
    if clipped > CLIP_FRACTION:
        warnings.append(f"audio is clipped ({100 * clipped:.1f}% of samples at full scale)")
    waveform = resample(waveform, rate, SAMPLE_RATE)
    problems, edges = inspect_speech(waveform)
    return Audio(np.ascontiguousarray(waveform), SAMPLE_RATE, warnings + problems, rate, edges)
