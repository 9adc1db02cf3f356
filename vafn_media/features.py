"""Log-mel features computed with torch (one code path for training batches and single-clip inference).

The STFT window and hop are fixed in *seconds*, so any sample rate gives the same frame rate and mel bands without
resampling; the mel filterbank for each rate is built once with librosa and cached.
"""

from __future__ import annotations

from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from vafn_media.constants import (
    F_MAX,
    F_MIN,
    HOP_SECONDS,
    LOG_EPS,
    LOW_CUT_HZ,
    N_MELS,
    NOISE_FLOOR_QUANTILE,
    NOISE_OVER_SUBTRACTION,
    NOISE_SPECTRAL_FLOOR,
    READ_PEAK,
    SAMPLE_RATE,
    WIN_SECONDS,
)

if TYPE_CHECKING:  # pragma: no cover
    import torch


def frame_params(sample_rate: int) -> tuple[int, int, int]:
    """(n_fft, win_length, hop_length) in samples for ``sample_rate``.

    :param sample_rate: audio sample rate in Hz.
    """
    win = int(round(WIN_SECONDS * sample_rate))
    hop = int(round(HOP_SECONDS * sample_rate))
    return 1 << (win - 1).bit_length(), win, hop


@lru_cache(maxsize=8)
def _low_cut_filter(sample_rate: int, cutoff_hz: float) -> np.ndarray:
    from scipy.signal import butter

    return butter(4, cutoff_hz, btype="highpass", fs=sample_rate, output="sos")


def low_cut(waveform: np.ndarray, sample_rate: int, cutoff_hz: float = LOW_CUT_HZ) -> np.ndarray:
    """The waveform high-passed at ``cutoff_hz`` (4th-order Butterworth; what the reader hears, see
    :data:`vafn_media.constants.LOW_CUT_HZ`).

    :param waveform: float32 samples.
    :param sample_rate: their rate in Hz.
    :param cutoff_hz: cut-off frequency (0: unchanged).
    """
    from scipy.signal import sosfilt

    if cutoff_hz <= 0:
        return np.asarray(waveform, np.float32)
    return sosfilt(_low_cut_filter(sample_rate, cutoff_hz), waveform).astype(np.float32)


def at_peak(waveform: np.ndarray, peak: float = READ_PEAK) -> np.ndarray:
    """The waveform scaled so that its largest magnitude is ``peak`` (unchanged when it is all zeros; see
    :data:`vafn_media.constants.READ_PEAK`), with samples more than 240 dB below ``peak`` set to zero.

    Those are the low cut's ringing over digital silence, decaying towards float32's subnormal numbers, on which the
    STFT, the power and the mel product ran about a hundred times slower per value (0.3 ms of a 5 s clip); a frame of
    them has a mel power ten orders of magnitude under LOG_EPS, so the features are the same bit for bit.

    :param waveform: float32 samples.
    :param peak: the peak to scale to.
    """
    largest = max(float(waveform.max()), -float(waveform.min())) if waveform.size else 0.0
    if largest == 0.0:
        return np.asarray(waveform, np.float32)
    scaled = (waveform * (peak / largest)).astype(np.float32, copy=False)
    scaled[np.abs(scaled) < peak * 2.0**-40] = 0.0
    return scaled


@lru_cache(maxsize=8)
def mel_filterbank(sample_rate: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(N_MELS, n_fft // 2 + 1) mel filterbank and Hann window for ``sample_rate`` (built once, cached).

    :param sample_rate: audio sample rate in Hz.
    """
    import warnings

    import librosa
    import torch

    n_fft, win, _ = frame_params(sample_rate)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # empty top bands are expected below 2 * F_MAX
        mel = librosa.filters.mel(sr=sample_rate, n_fft=n_fft, n_mels=N_MELS, fmin=F_MIN, fmax=F_MAX)
    return torch.from_numpy(mel.astype(np.float32)), torch.hann_window(win)


def num_frames(num_samples: int, sample_rate: int) -> int:
    """Number of feature frames of a clip with ``num_samples`` samples.

    :param num_samples: clip length in samples.
    :param sample_rate: sample rate in Hz.
    """
    _, _, hop = frame_params(sample_rate)
    return num_samples // hop + 1


def subtract_noise_floor(power: torch.Tensor) -> torch.Tensor:
    """Mel power (B, N_MELS, T) less each band's stationary noise floor (see
    :data:`vafn_media.constants.NOISE_FLOOR_QUANTILE`): ``max(power - a * floor, b * power)``.

    :param power: mel power of whole clips (every frame valid).
    """
    import torch

    values = power.numpy()
    rank = max(1, int(NOISE_FLOOR_QUANTILE * values.shape[-1]))
    floor = np.partition(values, rank - 1, axis=-1)[..., rank - 1:rank]  # numpy: a third of torch.kthvalue's time
    return torch.from_numpy(np.maximum(values - NOISE_OVER_SUBTRACTION * floor, NOISE_SPECTRAL_FLOOR * values))


def _log_mel_power(waveforms: torch.Tensor, sample_rate: int, denoise: bool = False) -> torch.Tensor:
    """Log mel power (B, N_MELS, T) of a (B, N) batch, centred frames, before normalisation (``denoise``: with
    :func:`subtract_noise_floor`)."""
    import torch

    n_fft, win, hop = frame_params(sample_rate)
    mel, window = mel_filterbank(sample_rate)
    spec = torch.stft(waveforms, n_fft=n_fft, hop_length=hop, win_length=win, window=window, center=True,
                      pad_mode="constant", return_complex=True)
    # numpy squares the interleaved real and imaginary parts in about half torch's time (the same float32 numbers)
    parts = torch.view_as_real(spec).numpy()
    power = torch.from_numpy(np.square(parts[..., 0]) + np.square(parts[..., 1]))
    mel_power = torch.matmul(mel, power)
    if denoise:
        mel_power = subtract_noise_floor(mel_power)
    return mel_power.add_(LOG_EPS).log_()


def log_mel_batch(
    waveforms: torch.Tensor, lengths: torch.Tensor, sample_rate: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-utterance mean/variance-normalised log-mel features of a zero-padded batch.

    :param waveforms: (B, N) float tensor.
    :param lengths: (B,) number of valid samples of each clip.
    :param sample_rate: sample rate of every clip in Hz.
    :return: features (B, N_MELS, T) and valid frame counts (B,).
    """
    import torch

    features = _log_mel_power(waveforms, sample_rate)
    _, _, hop = frame_params(sample_rate)
    frames = torch.clamp(lengths // hop + 1, max=features.shape[-1])
    mask = (torch.arange(features.shape[-1])[None, :] < frames[:, None]).to(features.dtype)[:, None, :]
    count = frames.to(features.dtype)[:, None, None]
    mean = (features * mask).sum(-1, keepdim=True) / count
    var = (((features - mean) * mask) ** 2).sum(-1, keepdim=True) / count
    normalised = (features - mean) / torch.sqrt(var + 1e-5) * mask
    return normalised, frames


def log_mel(waveform: np.ndarray, sample_rate: int, denoise: bool = False) -> torch.Tensor:
    """Normalised log-mel features (1, N_MELS, T) of one mono clip.

    Without ``denoise``, the same numbers as :func:`log_mel_batch` on a batch of this one clip (bit for bit: a clip
    alone has no padded frames, so the batch's frame mask is all ones and is skipped here, as are its allocations).

    :param waveform: float32 samples.
    :param sample_rate: sample rate in Hz.
    :param denoise: take each band's noise floor away first (:func:`subtract_noise_floor`).
    """
    import torch

    tensor = torch.from_numpy(np.ascontiguousarray(waveform, dtype=np.float32))[None]
    features = _log_mel_power(tensor, sample_rate, denoise)
    count = torch.full((1, 1, 1), features.shape[-1], dtype=features.dtype)  # centred frames: every one is valid
    mean = features.sum(-1, keepdim=True) / count
    centered = features - mean
    var = (centered ** 2).sum(-1, keepdim=True) / count
    return centered.div_(torch.sqrt(var + 1e-5))


def audio_features(waveform: np.ndarray) -> torch.Tensor:
    """What the reader reads of a clip at SAMPLE_RATE: :func:`low_cut`, scaled by :func:`at_peak`, then
    :func:`log_mel` with :func:`subtract_noise_floor` (1, N_MELS, T).

    Training features skip all three (:mod:`vafn_media.dataset`): they correct, at test time, a reader trained without
    them; an audio path fine-tuned on cut features read a person's voice and SVOX Pico worse (docs/multimedia.md).

    :param waveform: float32 samples at SAMPLE_RATE.
    """
    return log_mel(at_peak(low_cut(waveform, SAMPLE_RATE)), SAMPLE_RATE, denoise=True)
