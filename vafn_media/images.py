"""Loading, validating and canonicalising images (OpenCV).

Any size up to MAX_IMAGE_PIXELS (sides up to MAX_IMAGE_SIDE, at most MAX_ASPECT_RATIO times longer than high or
high than long), gray or BGR(A), either polarity -> a 32-px strip. A file's size is read from its header before
anything is decoded; images too small to hold a digit, and pixel noise, are errors.
"""

from __future__ import annotations

import os

import numpy as np

from vafn_media.constants import (
    BLANK_IMAGE_STD,
    CONTENT_MARGIN,
    CONTENT_THRESHOLD,
    IMAGE_HEIGHT,
    MAX_IMAGE_WIDTH,
    MIN_IMAGE_WIDTH,
)

ImageSource = str | os.PathLike | np.ndarray
#: Largest accepted image (pixels), checked from the file header before decoding (a phone photo is ~12-50 MP).
MAX_IMAGE_PIXELS: int = 64_000_000
#: Smallest accepted image side (pixels): a digit needs a few pixels to be a digit.
MIN_IMAGE_SIDE: int = 8
#: Largest accepted image side (pixels), and the most one side may exceed the other: a row of ten digits is about
#: 6 : 1. This bounds the work arrays (an 8 x 999,999 strip would be scaled to 32 x 4,000,000 floats).
MAX_IMAGE_SIDE: int = 32_768
MAX_ASPECT_RATIO: int = 32
#: Strokes are connected: an ink pixel's neighbour is ink far more often than a random pixel is. Below this ratio
#: (P(neighbour is ink | ink) / P(ink), worst direction) the image is pixel noise. Measured: 600 rendered and
#: handwritten strips >= 1.58 (5th percentile 7.1); uniform, Gaussian and salt-and-pepper noise 0.98-1.04.
MIN_INK_CLUSTERING: float = 1.3
#: Normalised ink level counted as ink by that test, and the contrast (gray levels) below which scattered "ink" is
#: the sensor noise of a blank card (read as the empty instruction), not a noise image.
_INK_LEVEL: float = 0.3
_NOISE_CONTRAST: float = 48.0
#: Gaussian blur kernel (pixels, at canonical scale) used only to locate the content box.
_BOX_BLUR = 5
#: Rows of the low-resolution copy on which the paper level is estimated.
_BACKGROUND_ROWS = 9
#: Side of the median window on that copy: about half its height, so light that changes across a short card (one
#: digit, a shadow) is followed; a window as tall as the copy took nearly the whole of a square photo and left the
#: shadow in as "ink".
_BACKGROUND_WINDOW = 5
#: Images taller than this are first downscaled to it (speed; the output has IMAGE_HEIGHT rows).
_WORK_HEIGHT = 4 * IMAGE_HEIGHT
#: A mask (a Cutout, a sticker): a solid rectangle of one exact grey level, the image's darkest or brightest, that
#: covers between these shares of the image, at least MASK_MIN_SIDE pixels each way, fills at least MASK_SOLIDITY of
#: its bounding box, and whose grey level is rare outside it (else it is saturated paper, not a mask).
MASK_AREA_RANGE: tuple[float, float] = (0.02, 0.5)
MASK_MIN_SIDE: int = 4
MASK_SOLIDITY: float = 0.9
MASK_OUTSIDE_SHARE: float = 0.2
#: A mask hides what is under it when it covers at least this share of the digits' height; a thinner bar through the
#: row is painted over and the digits around it are read.
MASK_HIDES_HEIGHT: float = 0.5


def _cv2():
    os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(MAX_IMAGE_PIXELS))  # OpenCV's own guard, as a backstop
    import cv2

    return cv2


def _check_pixels(height: int, width: int, what: str) -> None:
    """ValueError when an image is larger than MAX_IMAGE_PIXELS or MAX_IMAGE_SIDE, smaller than MIN_IMAGE_SIDE on a
    side, or more elongated than MAX_ASPECT_RATIO."""
    if height * width > MAX_IMAGE_PIXELS:
        raise ValueError(f"{what} has {width} x {height} = {width * height:,} pixels; at most "
                         f"{MAX_IMAGE_PIXELS:,} pixels are accepted")
    if max(height, width) > MAX_IMAGE_SIDE:
        raise ValueError(f"{what} is {width} x {height} pixels; a side has at most {MAX_IMAGE_SIDE:,} pixels")
    if 0 < min(height, width) < MIN_IMAGE_SIDE:
        raise ValueError(f"{what} is too small: {height} x {width} pixels (at least {MIN_IMAGE_SIDE} on each side)")
    if min(height, width) > 0 and max(height, width) > MAX_ASPECT_RATIO * min(height, width):
        raise ValueError(f"{what} is {width} x {height} pixels: one side is more than {MAX_ASPECT_RATIO} times the "
                         "other, not a photo or scan of a row of digits")


def _ink_clustering(mask: np.ndarray) -> float:
    """P(a neighbour of an ink pixel is ink) / P(ink), in the worse of the two directions (1 for random pixels)."""
    density = float(mask.mean())
    if density == 0.0 or mask.shape[0] < 2 or mask.shape[1] < 2:
        return float("inf")
    across = np.count_nonzero(mask[:, 1:] & mask[:, :-1]) / max(1, np.count_nonzero(mask[:, :-1]))
    down = np.count_nonzero(mask[1:] & mask[:-1]) / max(1, np.count_nonzero(mask[:-1]))
    return min(across, down) / density


def image_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(height, width) of an image file read from its header only (Pillow, lazily); None if Pillow cannot tell.

    :param path: image file.
    """
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        return None
    try:
        with Image.open(os.fspath(path)) as handle:  # parses the header; pixel data is not decoded
            width, height = handle.size
    except Image.DecompressionBombError as error:  # Pillow's own limit (~179 MP) is above ours: refuse as well
        raise ValueError(f"image file {os.fspath(path)!r} has too many pixels: {error}") from error
    except Exception:  # noqa: BLE001 - any format Pillow cannot parse is left to OpenCV's checks
        return None
    return int(height), int(width)


def read_image_file(path: str | os.PathLike) -> np.ndarray:
    """Read an image file unchanged; a missing, corrupt or truncated file raises ValueError naming it.

    :param path: file to read.
    """
    cv2 = _cv2()
    name = f"image file {os.fspath(path)!r}"
    if not os.path.isfile(path):
        raise ValueError(f"{name} does not exist")
    size = image_size(path)
    if size is None:  # nothing is decoded whose size the header does not give
        raise ValueError(f"{name} is corrupt, truncated or not an image (its header gives no size)")
    _check_pixels(*size, name)
    data = np.fromfile(os.fspath(path), dtype=np.uint8)
    try:
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    except cv2.error as error:  # OpenCV's own limits and decoder failures
        raise ValueError(f"{name} cannot be decoded: {' '.join(str(error).split())[-160:]}") from None
    if image is None:
        raise ValueError(f"{name} is corrupt, truncated or not an image")
    _check_pixels(image.shape[0], image.shape[1], name)  # the decoded size, should a header have lied
    return image


def to_gray(image: np.ndarray) -> np.ndarray:
    """Validate an image array and return it as float32 gray levels in [0, 255].

    :param image: H x W gray, H x W x 3 BGR or H x W x 4 BGRA array of dtype uint8, uint16 or float in [0, 1].
    """
    cv2 = _cv2()
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[:, :, 0]
    if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] not in (3, 4)):
        raise ValueError(f"image must be H x W, H x W x 3 (BGR) or H x W x 4 (BGRA), got shape {array.shape}")
    if array.size == 0 or min(array.shape[:2]) == 0:
        raise ValueError(f"image is empty (shape {array.shape})")
    _check_pixels(array.shape[0], array.shape[1], "image")
    if array.dtype == np.uint8:
        scaled = array.astype(np.float32)
    elif array.dtype == np.uint16:
        scaled = array.astype(np.float32) / 257.0
    elif array.dtype in (np.float32, np.float64):
        if not np.all(np.isfinite(array)):
            raise ValueError("image contains NaN or infinite pixels")
        if array.min() < 0.0 or array.max() > 1.0:
            raise ValueError(f"float images must lie in [0, 1], got range [{array.min():.3g}, {array.max():.3g}]")
        scaled = array.astype(np.float32) * 255.0
    else:
        raise ValueError(f"unsupported image dtype {array.dtype}; use uint8, uint16 or float in [0, 1]")
    if scaled.ndim == 3:
        code = cv2.COLOR_BGR2GRAY if scaled.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        scaled = cv2.cvtColor(scaled, code)
    return scaled


def paper_background(gray: np.ndarray) -> np.ndarray:
    """The paper (or board) behind the ink, as a smooth image of gray's size: a median over windows about half as tall
    as the image, taken at low resolution, so strokes are ignored but uneven light and shadows are kept.

    :param gray: float32 gray image.
    """
    cv2 = _cv2()
    height, width = gray.shape
    rows = min(_BACKGROUND_ROWS, height)
    cols = max(1, int(round(width * rows / height)))
    small = np.clip(cv2.resize(gray, (cols, rows), interpolation=cv2.INTER_AREA), 0, 255).astype(np.uint8)
    kernel = min(_BACKGROUND_WINDOW, 2 * (rows // 2) + 1)
    padded = cv2.copyMakeBorder(small, kernel, kernel, kernel, kernel, cv2.BORDER_REFLECT)
    smooth = cv2.medianBlur(padded, kernel)[kernel:-kernel, kernel:-kernel].astype(np.float32)
    return cv2.resize(smooth, (width, height), interpolation=cv2.INTER_LINEAR)


def _ink_map(gray: np.ndarray) -> np.ndarray:
    """Ink as positive values on a zero background: gray minus its local paper level, sign chosen by polarity.

    Polarity: ink is the minority, so the deviations from the paper have a long tail on the ink's side (skewness).
    """
    residual = gray - paper_background(gray)
    centred = (residual - float(residual.mean())).ravel()
    skew = float(np.dot(centred * centred, centred))  # third moment (sign only); ** 3 is 50x slower
    return residual if skew > 0 else -residual


def find_mask(gray: np.ndarray) -> tuple[int, int, int, int] | None:
    """The mask on an image, as (top, bottom, left, right) pixel bounds, or None: see :data:`MASK_AREA_RANGE`.

    :param gray: float32 gray image (exact grey levels, as :func:`to_gray` leaves them).
    """
    cv2 = _cv2()
    area = gray.shape[0] * gray.shape[1]
    best = None
    for level in {float(gray.min()), float(gray.max())}:
        same = (gray == level).astype(np.uint8)
        total = int(same.sum())
        count, _, stats, _ = cv2.connectedComponentsWithStats(same, connectivity=4)
        for left, top, width, height, pixels in stats[1:count]:
            box = width * height
            if (min(width, height) < MASK_MIN_SIDE or not MASK_AREA_RANGE[0] * area <= box <= MASK_AREA_RANGE[1] * area
                    or pixels < MASK_SOLIDITY * box
                    or total - pixels > MASK_OUTSIDE_SHARE * (area - box)):
                continue
            if best is None or box > (best[1] - best[0]) * (best[3] - best[2]):
                best = (int(top), int(top + height), int(left), int(left + width))
    return best


def canonical_strip(image: ImageSource) -> np.ndarray:
    """Turn an image of a digit row into the model's input: float32 (IMAGE_HEIGHT, W), ink bright on a zero background
    (:func:`read_strip` without the mask)."""
    return read_strip(image)[0]


def read_strip(image: ImageSource) -> tuple[np.ndarray, tuple[int, int] | None]:
    """The model's input for an image of a digit row, float32 (IMAGE_HEIGHT, W) with ink bright on a zero background,
    and the strip's columns [start, stop) under a mask that may hide a digit (:func:`find_mask`, covering at least
    :data:`MASK_HIDES_HEIGHT` of the digits' height beside or over them; None otherwise).

    Steps: gray conversion, a mask painted over with the paper's level, subtraction of the local paper level (uneven
    light, tinted paper), polarity from the side the ink stands out on, contrast normalisation, crop to the content
    box plus a margin (widened to a mask beside the digits, which may hide one), aspect-preserving resize to
    IMAGE_HEIGHT rows.

    :param image: path, or array accepted by :func:`to_gray`.
    """
    cv2 = _cv2()
    gray = to_gray(read_image_file(image) if isinstance(image, (str, os.PathLike)) else image)
    mask = find_mask(gray)
    if mask is not None:
        top, bottom, left, right = mask
        covered = np.zeros(gray.shape, bool)
        covered[top:bottom, left:right] = True
        gray = gray.copy()
        gray[covered] = float(np.median(gray[~covered]))
        mask_box = np.array([top, bottom, left, right], np.float64)
    if float(gray.std()) < BLANK_IMAGE_STD:
        shade = "all-black" if gray.mean() < 128 else "uniform"
        raise ValueError(f"image is {shade} (every pixel ~ {gray.mean():.0f}): there is nothing to read")
    if gray.shape[0] > _WORK_HEIGHT:  # work at a bounded resolution: the output is IMAGE_HEIGHT rows anyway
        width = max(1, int(round(gray.shape[1] * _WORK_HEIGHT / gray.shape[0])))
        if mask is not None:
            mask_box *= np.repeat([_WORK_HEIGHT / gray.shape[0], width / gray.shape[1]], 2)
        gray = cv2.resize(gray, (width, _WORK_HEIGHT), interpolation=cv2.INTER_AREA)
    ink = _ink_map(gray)
    scale = float(np.percentile(ink, 99.5))
    if scale <= BLANK_IMAGE_STD:
        raise ValueError("image has no visible ink: no pixel stands out from the background")
    ink = np.clip(ink / scale, 0.0, 1.0)
    clustering = _ink_clustering(ink > _INK_LEVEL)
    if clustering < MIN_INK_CLUSTERING and scale > _NOISE_CONTRAST:
        raise ValueError(f"image looks like pixel noise, not digits: its ink pixels are scattered, not strokes "
                         f"(clustering {clustering:.2f} < {MIN_INK_CLUSTERING})")
    # content box on a resized, blurred copy so pixel noise does not count as ink
    height, width = ink.shape
    factor = IMAGE_HEIGHT / height
    reach = int(round(1.0 / factor))  # thin strokes must survive the downscale: spread each over a small pixel
    spread = cv2.dilate(ink, np.ones((reach, reach), np.uint8)) if reach > 1 else ink
    small = cv2.resize(spread, (max(1, int(round(width * factor))), IMAGE_HEIGHT), interpolation=cv2.INTER_AREA)
    smooth = cv2.GaussianBlur(small, (_BOX_BLUR, _BOX_BLUR), 0)
    rows = np.flatnonzero(smooth.max(axis=1) > CONTENT_THRESHOLD)
    cols = np.flatnonzero(smooth.max(axis=0) > CONTENT_THRESHOLD)
    if rows.size and cols.size:
        grown = (reach - 1) / 2.0  # the dilation widened the ink by this much on each side: take it back
        top, bottom = rows[0] / factor + grown, (rows[-1] + 1) / factor - grown
        left, right = cols[0] / factor + grown, (cols[-1] + 1) / factor - grown
        margin = CONTENT_MARGIN * (bottom - top)
        if mask is not None:
            digit_height = bottom - top
            covered = min(bottom, mask_box[1]) - max(top, mask_box[0])
            beside = mask_box[2] < right + digit_height and mask_box[3] > left - digit_height
            if covered < MASK_HIDES_HEIGHT * digit_height or not beside:
                mask = None  # digits are visible around it, or it is off the row
            else:  # a digit may be under the mask: keep its columns in the strip
                left, right = min(left, mask_box[2]), max(right, mask_box[3])
        top, bottom = int(max(0, top - margin)), int(min(height, bottom + margin + 1))
        left, right = int(max(0, left - margin)), int(min(width, right + margin + 1))
        ink = ink[top:bottom, left:right]
        if mask is not None:
            mask_box[2:] -= left
    else:
        mask = None
    crop_h, crop_w = ink.shape
    new_w = int(np.clip(round(crop_w * IMAGE_HEIGHT / crop_h), MIN_IMAGE_WIDTH, MAX_IMAGE_WIDTH))
    strip = cv2.resize(ink, (new_w, IMAGE_HEIGHT), interpolation=cv2.INTER_AREA).astype(np.float32)
    if mask is None:
        return strip, None
    start, stop = np.clip(np.round(mask_box[2:] * new_w / crop_w), 0, new_w).astype(int)
    return strip, ((int(start), int(stop)) if stop > start else None)
