"""Loading and validating audio: any sample rate in range, mono float32, with clear errors for unusable input."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from vafn_media.constants import (
    CLIP_FRACTION,
    CLIP_LEVEL,
    MAX_AUDIO_SECONDS,
    MAX_SAMPLE_RATE,
    MIN_SAMPLE_RATE,
    SILENCE_DBFS,
)

AudioSource = str | os.PathLike | np.ndarray | tuple[np.ndarray, int]
_INT_SCALE = {np.dtype(np.int16): 32768.0, np.dtype(np.int32): 2147483648.0, np.dtype(np.uint8): 128.0}


@dataclass
class Audio:
    """A validated mono clip: float32 samples in [-1, 1], its sample rate and non-fatal quality warnings."""

    waveform: np.ndarray
    sample_rate: int
    warnings: list[str] = field(default_factory=list)

    @property
    def seconds(self) -> float:
        """Duration in seconds."""
        return len(self.waveform) / self.sample_rate


def read_audio_file(path: str | os.PathLike) -> tuple[np.ndarray, int]:
    """Read a WAV/FLAC/OGG file with soundfile; corrupt or truncated files raise ValueError naming the file.

    :param path: file to read.
    """
    import soundfile

    if not os.path.isfile(path):
        raise ValueError(f"audio file {os.fspath(path)!r} does not exist")
    try:
        data, rate = soundfile.read(os.fspath(path), dtype="float32", always_2d=True)
    except Exception as error:  # libsndfile raises its own error types
        raise ValueError(f"audio file {os.fspath(path)!r} is corrupt or not a supported format: {error}") from error
    return data, int(rate)


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

    Raises ValueError for empty, non-finite, silent, too long or wrongly sampled audio; clipping is a warning.

    :param source: file path, numpy waveform, or (waveform, sample_rate) tuple.
    :param sample_rate: sample rate of a bare waveform (Hz); ignored for files.
    """
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
    bad = int(np.count_nonzero(~np.isfinite(waveform)))
    if bad:
        raise ValueError(f"audio contains {bad} NaN or infinite samples")
    if waveform.size / rate > MAX_AUDIO_SECONDS:
        raise ValueError(f"audio lasts {waveform.size / rate:.1f} s; at most {MAX_AUDIO_SECONDS:.0f} s are accepted")
    magnitude = np.abs(waveform)
    peak = float(magnitude.max())
    rms = float(np.sqrt(np.mean(np.square(waveform, dtype=np.float64))))
    level_dbfs = 20 * np.log10(max(rms, 1e-12))
    if peak == 0.0 or level_dbfs < SILENCE_DBFS:
        raise ValueError(f"audio is silent (RMS {level_dbfs:.0f} dBFS < {SILENCE_DBFS:.0f} dBFS)")
    warnings = []
    clipped = float(np.mean(magnitude >= CLIP_LEVEL))
    if clipped > CLIP_FRACTION:
        warnings.append(f"audio is clipped ({100 * clipped:.1f}% of samples at full scale)")
    if peak > 1.0 + 1e-3:
        warnings.append(f"audio exceeds full scale (peak {peak:.2f}); it was not normalised")
    return Audio(np.ascontiguousarray(waveform), rate, warnings)
