"""Turning cached items into padded model batches, with the training-time augmentations."""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np
import torch

from vafn_media.constants import (F_MAX, F_MIN, IMAGE_HEIGHT, MAX_IMAGE_WIDTH, MIN_IMAGE_WIDTH, N_MELS,
                                  VTLP_PROBABILITY, VTLP_RANGE)
from vafn_media.dataset import INK_LEVELS, TrainingData

#: Augmentation settings (training only): probability of a degraded cached copy instead of the clean utterance.
NOISE_PROBABILITY: float = 0.75
SPEC_MASK_PROBABILITY: float = 0.5
MAX_FREQ_MASK: int = 6
MAX_TIME_MASK: int = 8
CUTOUT_PROBABILITY: float = 0.3
#: Probability of a camera photo of the card (when the batch is given camera strips) instead of the rendered strip.
CAMERA_PROBABILITY: float = 0.5
STRETCH_RANGE: tuple[float, float] = (0.8, 1.25)
INK_GAIN_RANGE: tuple[float, float] = (0.6, 1.0)
INK_NOISE_SIGMA: float = 0.05


def pad_images(strips: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """Right-pad canonical strips (float, ink bright on 0) into (B, 1, IMAGE_HEIGHT, W_max) plus widths.

    :param strips: (IMAGE_HEIGHT, W_i) float arrays.
    """
    widths = [s.shape[1] for s in strips]
    batch = np.zeros((len(strips), 1, IMAGE_HEIGHT, max(widths)), np.float32)
    for i, strip in enumerate(strips):
        batch[i, 0, :, : strip.shape[1]] = strip
    return torch.from_numpy(batch), torch.tensor(widths)


def _stretch(strip: np.ndarray, factor: float) -> np.ndarray:
    import cv2

    width = int(np.clip(round(strip.shape[1] * factor), MIN_IMAGE_WIDTH, MAX_IMAGE_WIDTH))
    return cv2.resize(strip, (width, strip.shape[0]), interpolation=cv2.INTER_AREA)


@lru_cache(maxsize=1)
def _mel_centres() -> np.ndarray:
    import librosa

    return librosa.mel_frequencies(N_MELS + 2, fmin=F_MIN, fmax=F_MAX)[1:-1]


def warp_vocal_tract(features: np.ndarray, factor: float) -> np.ndarray:
    """Vocal-tract-length perturbation of (N_MELS, T) log-mel features: band k takes the value at ``f_k / factor``.

    :param features: log-mel features, bands on axis 0.
    :param factor: formant scale (> 1: higher formants, like a shorter vocal tract).
    """
    centres = _mel_centres()
    source = np.interp(centres / factor, centres, np.arange(N_MELS))  # fractional band index, edges clamped
    low = np.minimum(source.astype(np.int64), N_MELS - 2)
    weight = (source - low)[:, None].astype(features.dtype)
    return features[low] * (1 - weight) + features[low + 1] * weight


def pad_features(features: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """Right-pad (N_MELS, T_i) feature arrays into (B, N_MELS, T_max) plus frame counts.

    :param features: per-utterance log-mel arrays.
    """
    frames = [f.shape[1] for f in features]
    batch = np.zeros((len(features), features[0].shape[0], max(frames)), np.float32)
    for i, f in enumerate(features):
        batch[i, :, : f.shape[1]] = f
    return torch.from_numpy(batch), torch.tensor(frames)


def bucketed_batches(data: TrainingData, batch_size: int, rng: np.random.Generator, pool: int = 8) -> list[np.ndarray]:
    """Random batches of similar-length items (less padding): draw ``pool`` batches' worth, sort by length, split.

    :param data: cached items.
    :param batch_size: items per batch.
    :param rng: random generator.
    :param pool: batches drawn per call.
    """
    indices = rng.integers(0, len(data), batch_size * pool)
    indices = indices[np.argsort([data.clean_audio[i].shape[1] for i in indices], kind="stable")]
    batches = np.split(indices, pool)
    return [batches[i] for i in rng.permutation(pool)]


def make_batch(data: TrainingData, indices: np.ndarray, rng: np.random.Generator | None,
               corrupted: bool = False, camera: Sequence[Sequence[np.ndarray]] | None = None,
               camera_probability: float = CAMERA_PROBABILITY,
               vtlp_probability: float = VTLP_PROBABILITY) -> dict[str, torch.Tensor]:
    """Build a training (``rng`` given: augmented) or evaluation (``rng`` None: clean, or ``corrupted``) batch.

    :param data: cached items.
    :param indices: which items.
    :param rng: augmentation randomness; None disables augmentation.
    :param corrupted: without ``rng``, use every item's noisy audio and Cutout strip instead of the clean ones.
    :param camera: training only: per copy, a camera-photo strip of every item (``camera[k][i]``); with probability
        ``camera_probability`` an item's image is one of them instead of its rendered (or Cutout) strip.
    :param camera_probability: see ``camera``.
    :param vtlp_probability: training only: probability of a vocal-tract-length perturbation of the audio features.
    """
    audio, strips = [], []
    for i in indices:
        noisy = rng.random() < NOISE_PROBABILITY if rng is not None else corrupted
        if noisy:
            copy = int(rng.integers(len(data.augmented_audio))) if rng is not None else 0
            features = data.augmented_audio[copy][i].astype(np.float32)
        else:
            features = data.clean_audio[i].astype(np.float32)
        use_mask = rng.random() < CUTOUT_PROBABILITY if rng is not None else corrupted
        strip = (data.masked[i] if use_mask else data.clean[i]).astype(np.float32) / INK_LEVELS
        if rng is not None and camera is not None and rng.random() < camera_probability:
            strip = camera[int(rng.integers(len(camera)))][i].astype(np.float32) / INK_LEVELS
        if rng is not None:
            if rng.random() < vtlp_probability:
                features = warp_vocal_tract(features, rng.uniform(*VTLP_RANGE))
            if rng.random() < SPEC_MASK_PROBABILITY:  # in place: ``features`` is this batch's own float32 copy
                f0 = int(rng.integers(0, features.shape[0] - MAX_FREQ_MASK))
                features[f0:f0 + int(rng.integers(1, MAX_FREQ_MASK + 1))] = 0.0
                t0 = int(rng.integers(0, max(1, features.shape[1] - MAX_TIME_MASK)))
                features[:, t0:t0 + int(rng.integers(1, MAX_TIME_MASK + 1))] = 0.0
            strip = _stretch(strip, rng.uniform(*STRETCH_RANGE)) * rng.uniform(*INK_GAIN_RANGE)
            strip = np.clip(strip + rng.normal(0.0, INK_NOISE_SIGMA, strip.shape), 0.0, 1.0).astype(np.float32)
        audio.append(features)
        strips.append(strip)
    features, frames = pad_features(audio)
    images, widths = pad_images(strips)
    lengths = torch.from_numpy(data.lengths[indices].astype(np.int64))
    targets = torch.from_numpy(data.arms[indices].astype(np.int64))
    return {"audio": features, "audio_lengths": frames, "image": images, "image_lengths": widths,
            "targets": targets, "target_lengths": lengths}
