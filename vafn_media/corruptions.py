"""The corruptions of Table 1: white Gaussian noise at a given SNR on audio, Cutout on images."""

from __future__ import annotations

import math

import numpy as np

from vafn_media.constants import CUTOUT_FRACTION


def add_awgn(waveform: np.ndarray, snr_db: float, rng: np.random.Generator) -> np.ndarray:
    """Add white Gaussian noise so that 10·log10(P_signal / P_noise) = ``snr_db`` over the whole clip.

    :param waveform: mono float samples.
    :param snr_db: signal-to-noise ratio in dB.
    :param rng: random generator for the noise.
    """
    signal_power = float(np.mean(np.asarray(waveform, dtype=np.float64) ** 2)) if len(waveform) else 0.0
    sigma = math.sqrt(signal_power / 10 ** (snr_db / 10))
    return (waveform + rng.normal(0.0, sigma, np.shape(waveform))).astype(np.float32)


def cutout(image: np.ndarray, rng: np.random.Generator, fraction: tuple[float, float] = CUTOUT_FRACTION,
           fill: int = 0) -> np.ndarray:
    """Mask one axis-aligned rectangle covering a uniform ``fraction`` of the image area (kept fully inside).

    :param image: H x W (x C) image.
    :param rng: random generator.
    :param fraction: (low, high) range of the masked area fraction.
    :param fill: value written into the rectangle.
    """
    height, width = image.shape[:2]
    target = rng.uniform(*fraction) * height * width
    rect_h = int(rng.integers(max(1, math.ceil(target / width)), height + 1))
    rect_w = min(max(round(target / rect_h), math.ceil(fraction[0] * height * width / rect_h)),
                 math.floor(fraction[1] * height * width / rect_h), width)
    y0 = int(rng.integers(0, height - rect_h + 1))
    x0 = int(rng.integers(0, width - rect_w + 1))
    out = image.copy()
    out[y0:y0 + rect_h, x0:x0 + rect_w] = fill
    return out
