"""Instruction cards as a phone camera sees them: fonts, tinted paper, coloured ink, perspective, light, blur, JPEG.

A card is rendered in two steps. :func:`render_card_ink` draws the digit row as an ink map (float in [0, 1]) from
one glyph source: TrueType fonts bundled with matplotlib (:data:`TRAIN_TTF_FONTS` / :data:`HELDOUT_TTF_FONTS`),
OpenCV Hershey fonts (the split of :mod:`vafn_media.strips`, including the script fonts) or scikit-learn's 8x8
handwritten digits (first 70 % of each digit's samples for training, last 30 % held out). :func:`colour_card` puts
the ink on paper (uint8 BGR). Then the corruptions, one job each and all numpy/OpenCV, degrade the photo:
:func:`perspective_warp`, :func:`uneven_light`, :func:`gaussian_blur`, :func:`motion_blur`, :func:`jpeg` and
:func:`sensor_noise`. :func:`camera_augment` is the random training chain; :data:`CAMERA_CONDITIONS` and
:func:`apply_camera_condition` are the fixed evaluation conditions of the benchmark.

This module is deliberately not part of :func:`vafn_media.dataset.cache_key`: camera strips are cached separately
(:func:`build_image_cache`), so the speech cache stays valid.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np

from vafn_media.constants import MAX_INSTRUCTION_LENGTH

#: TrueType fonts (files in matplotlib's bundled ``mpl-data/fonts/ttf``) used to render training cards.
TRAIN_TTF_FONTS: tuple[str, ...] = (
    "DejaVuSans.ttf", "DejaVuSans-Bold.ttf", "DejaVuSans-Oblique.ttf", "DejaVuSerif.ttf", "DejaVuSerif-Bold.ttf",
    "DejaVuSerif-Italic.ttf", "DejaVuSansMono.ttf", "cmr10.ttf", "cmss10.ttf", "STIXGeneral.ttf",
    "STIXGeneralBol.ttf",
)
#: TrueType fonts never used for training (evaluation only): an italic book face, a typewriter face, a bold italic
#: and a bold-oblique monospace.
HELDOUT_TTF_FONTS: tuple[str, ...] = (
    "cmti10.ttf", "cmtt10.ttf", "STIXGeneralBolIta.ttf", "DejaVuSansMono-BoldOblique.ttf",
)
#: Glyph sources of a card: TrueType fonts, Hershey fonts (incl. script ones), scikit-learn handwriting.
SOURCES: tuple[str, ...] = ("font", "hershey", "handwritten")
#: A training-only source: MNIST handwriting (:func:`vafn_media.strips.mnist_pool`), other writers than scikit-learn's.
MNIST_SOURCE: str = "mnist"
#: Default chance that a training card of scikit-learn handwriting is written with MNIST's glyphs instead.
MNIST_PROBABILITY: float = 0.0
#: Probability of each source in the training chain (TrueType is the printed card a user is most likely to show).
TRAIN_SOURCE_PROBABILITIES: tuple[float, ...] = (0.5, 0.25, 0.25)
#: Cell size (pixels) of one digit on a card, and blank margins around the row (fraction of a cell).
CARD_CELL_RANGE: tuple[int, int] = (40, 80)
CARD_MARGIN_RANGE: tuple[float, float] = (0.3, 1.2)
#: Paper (BGR, light) and ink (BGR, dark) colour ranges of the training chain.
PAPER_LEVEL_RANGE: tuple[float, float] = (185.0, 255.0)
PAPER_TINT: float = 40.0
INK_LEVEL_RANGE: tuple[float, float] = (0.0, 90.0)
INK_TINT: float = 110.0
#: Brightest ink (luminance, gray levels): at least 45 levels below the darkest paper (145).
MAX_INK_LUMINANCE: float = 100.0
#: Training-chain ranges and probabilities of each corruption.
WARP_RANGE: tuple[float, float] = (0.0, 0.15)
LIGHT_DEPTH_RANGE: tuple[float, float] = (0.0, 0.7)
BLUR_SIGMA_RANGE: tuple[float, float] = (0.3, 2.5)
MOTION_LENGTH_RANGE: tuple[int, int] = (3, 11)
JPEG_QUALITY_RANGE: tuple[int, int] = (10, 90)
NOISE_SIGMA_RANGE: tuple[float, float] = (0.0, 8.0)
P_WARP, P_LIGHT, P_BLUR, P_MOTION, P_JPEG = 0.7, 0.7, 0.6, 0.35, 0.6
#: Default chance that a training photo gets every corruption of the chain at once (still at random severities): with
#: independent draws only 6 % of photos (P_WARP * P_LIGHT * P_BLUR * P_MOTION * P_JPEG) are that compound.
COMPOUND_PROBABILITY: float = 0.0
#: Evaluation conditions (fixed settings; "all" is the whole phone chain at those settings).
CAMERA_CONDITIONS: tuple[str, ...] = ("flat", "perspective", "uneven light", "tinted paper + coloured ink", "blur",
                                      "JPEG", "all")
EVAL_WARP: float = 0.12
EVAL_LIGHT_DEPTH: float = 0.6
EVAL_BLUR_SIGMA: float = 1.8
EVAL_MOTION_LENGTH: int = 7
EVAL_JPEG_QUALITY: int = 20
#: Evaluation palettes: tinted papers (yellowish, pink, blue-grey, green) and inks (blue, red, green, pencil grey).
EVAL_PAPERS: tuple[tuple[int, int, int], ...] = ((180, 230, 245), (215, 200, 250), (225, 210, 190), (200, 235, 215))
EVAL_INKS: tuple[tuple[int, int, int], ...] = ((150, 40, 20), (40, 40, 180), (40, 120, 30), (90, 90, 90))
#: Camera copies cached per training item.
CAMERA_COPIES: int = 2


def _cv2():
    import cv2

    return cv2


def font_path(name: str) -> Path:
    """Path of a TrueType font bundled with matplotlib (no system fonts: the same files on every machine).

    :param name: file name, e.g. "DejaVuSans.ttf".
    """
    import matplotlib

    path = Path(matplotlib.get_data_path()) / "fonts" / "ttf" / name
    if not path.is_file():
        raise FileNotFoundError(f"font {name!r} is not bundled with this matplotlib ({path})")
    return path


@lru_cache(maxsize=64)
def _font(name: str, size: int):
    from PIL import ImageFont

    return ImageFont.truetype(str(font_path(name)), size)


def ttf_glyph(arm: int, font: str, cell: int, rng: np.random.Generator) -> np.ndarray:
    """One digit of a TrueType font as an ink map (float32 in [0, 1], cell x cell), size and pose jittered.

    :param arm: the digit.
    :param font: font file name.
    :param cell: output size (pixels).
    :param rng: random generator (fill and affine jitter).
    """
    from PIL import Image, ImageDraw

    from vafn_media.strips import GLYPH_FILL_RANGE, SUPERSAMPLE, _jitter

    big = cell * SUPERSAMPLE
    face = _font(font, big)
    left, top, right, bottom = face.getbbox(str(arm))
    canvas = Image.new("L", (right - left + 8, bottom - top + 8), 0)
    ImageDraw.Draw(canvas).text((4 - left, 4 - top), str(arm), fill=255, font=face)
    glyph = np.asarray(canvas, np.float32) / 255.0
    fill = rng.uniform(*GLYPH_FILL_RANGE)
    scale = fill * big / max(glyph.shape)
    height, width = max(1, int(round(glyph.shape[0] * scale))), max(1, int(round(glyph.shape[1] * scale)))
    glyph = _cv2().resize(glyph, (width, height), interpolation=_cv2().INTER_AREA)
    out = np.zeros((big, big), np.float32)
    y0, x0 = (big - height) // 2, (big - width) // 2
    out[y0:y0 + height, x0:x0 + width] = glyph
    return _jitter(out, rng, cell)


def draw_card_cell(rng: np.random.Generator) -> int:
    """A random side of one digit's cell on a card (pixels, uniform in :data:`CARD_CELL_RANGE`)."""
    return int(rng.integers(CARD_CELL_RANGE[0], CARD_CELL_RANGE[1] + 1))


def render_card_ink(arms: Sequence[int], rng: np.random.Generator, source: str, heldout: bool,
                    font: str | None = None, cell: int | None = None) -> np.ndarray:
    """The ink map of a card (float32 in [0, 1]; 1 = full ink): one row of digits with blank margins.

    :param arms: arm ids (0..MAX_INSTRUCTION_LENGTH).
    :param rng: random generator (the card is a pure function of its state).
    :param source: "font" (TrueType), "hershey", "handwritten" (scikit-learn digits) or, for training only, "mnist".
    :param heldout: draw from the held-out fonts / glyphs instead of the training ones.
    :param font: for "font", this TrueType file instead of a random one from the split's list.
    :param cell: side of one digit's cell (pixels); None draws it with :func:`draw_card_cell` (the first draw from
        ``rng``).
    """
    from vafn_media.strips import _handwritten_glyph, _printed_glyph

    if source not in (*SOURCES, MNIST_SOURCE):
        raise ValueError(f"unknown glyph source {source!r}; choose from {(*SOURCES, MNIST_SOURCE)}")
    if len(arms) > MAX_INSTRUCTION_LENGTH:
        raise ValueError(f"at most {MAX_INSTRUCTION_LENGTH} digits fit a card, got {len(arms)}")
    if cell is None:
        cell = draw_card_cell(rng)
    fonts = HELDOUT_TTF_FONTS if heldout else TRAIN_TTF_FONTS
    chosen = font if font is not None else fonts[int(rng.integers(len(fonts)))]
    margins = (rng.uniform(*CARD_MARGIN_RANGE, size=4) * cell).astype(int)  # top, bottom, left, right
    spacing = rng.uniform(0.8, 1.05)  # digits may be set tighter than a cell
    step = max(1, int(round(cell * spacing)))
    width = margins[2] + margins[3] + step * max(len(arms) - 1, 0) + cell
    ink = np.zeros((cell + margins[0] + margins[1], width), np.float32)
    for position, arm in enumerate(arms):
        if source == "font":
            glyph = ttf_glyph(int(arm), chosen, cell, rng)
        elif source == "hershey":
            glyph = _printed_glyph(int(arm), rng, cell, heldout)
        else:
            glyph = _handwritten_glyph(int(arm), rng, cell, heldout, mnist=source == MNIST_SOURCE)
        x0 = margins[2] + position * step
        rows, cols = slice(margins[0], margins[0] + cell), slice(x0, x0 + cell)
        ink[rows, cols] = np.maximum(ink[rows, cols], glyph)
    return np.clip(ink, 0.0, 1.0)


def colour_card(ink: np.ndarray, paper: Sequence[float], ink_colour: Sequence[float]) -> np.ndarray:
    """Paint an ink map onto paper: uint8 BGR image, ``paper`` where ink is 0 and ``ink_colour`` where it is 1.

    :param ink: float ink map in [0, 1].
    :param paper: BGR colour of the paper (0-255).
    :param ink_colour: BGR colour of the ink (0-255).
    """
    alpha = np.clip(ink, 0.0, 1.0)[:, :, None]
    paper_bgr = np.asarray(paper, np.float32)[None, None, :]
    ink_bgr = np.asarray(ink_colour, np.float32)[None, None, :]
    return np.clip(np.rint(paper_bgr * (1.0 - alpha) + ink_bgr * alpha), 0, 255).astype(np.uint8)


def _luminance(bgr: Sequence[float]) -> float:
    """Gray level of a BGR colour (ITU-R BT.601 weights, as OpenCV's gray conversion)."""
    return 0.114 * bgr[0] + 0.587 * bgr[1] + 0.299 * bgr[2]


def random_paper(rng: np.random.Generator) -> tuple[float, float, float]:
    """A light paper colour: a gray level in PAPER_LEVEL_RANGE, each channel tinted down by up to PAPER_TINT.

    :param rng: random generator.
    """
    level = rng.uniform(*PAPER_LEVEL_RANGE)
    return tuple(float(np.clip(level - rng.uniform(0.0, PAPER_TINT), 0, 255)) for _ in range(3))


def random_ink(rng: np.random.Generator) -> tuple[float, float, float]:
    """A dark ink colour: a gray level in INK_LEVEL_RANGE, each channel raised by up to INK_TINT (blue, red, ...),
    then darkened if needed so that its luminance stays at most MAX_INK_LUMINANCE (ink must contrast with paper).

    :param rng: random generator.
    """
    level = rng.uniform(*INK_LEVEL_RANGE)
    colour = np.array([level + rng.uniform(0.0, INK_TINT) for _ in range(3)])
    colour *= min(1.0, MAX_INK_LUMINANCE / max(_luminance(colour), 1e-6))
    return tuple(float(c) for c in np.clip(colour, 0, 255))


def perspective_warp(image: np.ndarray, rng: np.random.Generator, strength: float) -> np.ndarray:
    """Photograph the card at an angle: move each corner by up to ``strength`` x the side, keep the size.

    The photo is framed inside the card: areas that the warp uncovers are filled with the nearest card pixels.

    :param image: H x W (x C) uint8 image.
    :param rng: random generator (corner offsets).
    :param strength: largest corner offset as a fraction of the image width / height.
    """
    cv2 = _cv2()
    height, width = image.shape[:2]
    corners = np.float32([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]])
    offsets = rng.uniform(-strength, strength, (4, 2)) * np.float32([width, height])
    matrix = cv2.getPerspectiveTransform(corners, (corners + offsets).astype(np.float32))
    return cv2.warpPerspective(image, matrix, (width, height), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REPLICATE)


def uneven_light(image: np.ndarray, rng: np.random.Generator, depth: float) -> np.ndarray:
    """Light falling off across the card: multiply by a field from 1 down to 1 - ``depth`` (a linear gradient in a
    random direction, plus a soft spot of shadow).

    :param image: H x W (x C) uint8 image.
    :param rng: random generator (direction, spot position).
    :param depth: darkest point of the field, as a fraction of the light lost (0: no change).
    """
    height, width = image.shape[:2]
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    angle = rng.uniform(0.0, 2.0 * np.pi)
    ramp = (xx / max(width - 1, 1) - 0.5) * np.cos(angle) + (yy / max(height - 1, 1) - 0.5) * np.sin(angle)
    cy, cx = rng.uniform(0, height), rng.uniform(0, width)
    radius = rng.uniform(0.3, 0.8) * max(height, width)
    spot = np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2.0 * radius**2))
    darkness = 0.6 * (ramp - ramp.min()) / max(float(np.ptp(ramp)), 1e-6) + 0.4 * spot
    darkness = (darkness - darkness.min()) / max(float(np.ptp(darkness)), 1e-6)
    field = 1.0 - depth * darkness
    if image.ndim == 3:
        field = field[:, :, None]
    return np.clip(np.rint(image.astype(np.float32) * field), 0, 255).astype(np.uint8)


def gaussian_blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """Out-of-focus blur: a Gaussian of standard deviation ``sigma`` pixels.

    :param image: H x W (x C) uint8 image.
    :param sigma: blur in pixels (0: no change).
    """
    if sigma <= 0:
        return image.copy()
    return _cv2().GaussianBlur(image, (0, 0), sigma)


def motion_blur(image: np.ndarray, length: int, angle_degrees: float) -> np.ndarray:
    """Camera shake: average along a line of ``length`` pixels at ``angle_degrees``.

    :param image: H x W (x C) uint8 image.
    :param length: blur length in pixels (1: no change).
    :param angle_degrees: direction of the motion.
    """
    cv2 = _cv2()
    length = max(1, int(length))
    kernel = np.zeros((length, length), np.float32)
    kernel[length // 2, :] = 1.0
    rotation = cv2.getRotationMatrix2D(((length - 1) / 2.0, (length - 1) / 2.0), angle_degrees, 1.0)
    kernel = cv2.warpAffine(kernel, rotation, (length, length))
    kernel /= max(float(kernel.sum()), 1e-6)
    return cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REPLICATE)


def jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """JPEG re-encoding at ``quality`` (1-100): block artefacts and, for colour images, chroma subsampling.

    :param image: H x W (x C) uint8 image.
    :param quality: JPEG quality.
    """
    cv2 = _cv2()
    ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 images
        raise ValueError("JPEG encoding failed")
    flag = cv2.IMREAD_COLOR if image.ndim == 3 else cv2.IMREAD_GRAYSCALE
    return cv2.imdecode(encoded, flag)


def sensor_noise(image: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    """Additive Gaussian sensor noise of ``sigma`` gray levels.

    :param image: H x W (x C) uint8 image.
    :param rng: random generator.
    :param sigma: noise standard deviation.
    """
    noisy = image.astype(np.float32) + rng.normal(0.0, sigma, image.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def camera_augment(ink: np.ndarray, rng: np.random.Generator,
                   compound_probability: float = COMPOUND_PROBABILITY) -> np.ndarray:
    """The random training chain: tinted paper and coloured ink, then perspective, light, blur, noise and JPEG.

    :param ink: ink map from :func:`render_card_ink`.
    :param rng: random generator (one per item and copy).
    :param compound_probability: chance that every corruption is applied (each still drawn at a random severity);
        otherwise each is applied with its own probability (``P_WARP`` ...).
    """
    image = colour_card(ink, random_paper(rng), random_ink(rng))
    # Every coin is drawn whatever the compound draw says, so the same rng makes the same photo but for the coins.
    compound = rng.random() < compound_probability
    if (rng.random() < P_WARP) or compound:
        image = perspective_warp(image, rng, rng.uniform(*WARP_RANGE))
    if (rng.random() < P_LIGHT) or compound:
        image = uneven_light(image, rng, rng.uniform(*LIGHT_DEPTH_RANGE))
    if (rng.random() < P_BLUR) or compound:
        image = gaussian_blur(image, rng.uniform(*BLUR_SIGMA_RANGE))
    if (rng.random() < P_MOTION) or compound:
        image = motion_blur(image, int(rng.integers(*MOTION_LENGTH_RANGE)), rng.uniform(0.0, 180.0))
    image = sensor_noise(image, rng, rng.uniform(*NOISE_SIGMA_RANGE))
    if (rng.random() < P_JPEG) or compound:
        image = jpeg(image, int(rng.integers(*JPEG_QUALITY_RANGE)))
    return image


def apply_camera_condition(ink: np.ndarray, condition: str, rng: np.random.Generator) -> np.ndarray:
    """A card photographed under one evaluation condition (uint8 BGR).

    "flat": black ink on white paper, only sensor noise; each other condition adds one degradation at its fixed
    setting; "tinted paper + coloured ink" draws paper and ink from :data:`EVAL_PAPERS` / :data:`EVAL_INKS`; "blur" is
    a Gaussian of EVAL_BLUR_SIGMA then motion blur of EVAL_MOTION_LENGTH px; "all" chains every one of them.

    :param ink: ink map from :func:`render_card_ink`.
    :param condition: one of :data:`CAMERA_CONDITIONS`.
    :param rng: random generator (palette, warp, light direction, noise).
    """
    if condition not in CAMERA_CONDITIONS:
        raise ValueError(f"unknown camera condition {condition!r}; choose from {CAMERA_CONDITIONS}")
    everything = condition == "all"
    if everything or condition == "tinted paper + coloured ink":
        paper, colour = EVAL_PAPERS[int(rng.integers(len(EVAL_PAPERS)))], EVAL_INKS[int(rng.integers(len(EVAL_INKS)))]
    else:
        paper, colour = (245, 245, 245), (20, 20, 20)
    image = colour_card(ink, paper, colour)
    if everything or condition == "perspective":
        image = perspective_warp(image, rng, EVAL_WARP)
    if everything or condition == "uneven light":
        image = uneven_light(image, rng, EVAL_LIGHT_DEPTH)
    if everything or condition == "blur":
        image = motion_blur(gaussian_blur(image, EVAL_BLUR_SIGMA), EVAL_MOTION_LENGTH, rng.uniform(0.0, 180.0))
    image = sensor_noise(image, rng, 3.0)
    if everything or condition == "JPEG":
        image = jpeg(image, EVAL_JPEG_QUALITY)
    return image


def camera_cache_key(seed: int, split: str, count: int, compound_probability: float = COMPOUND_PROBABILITY,
                     mnist_probability: float = MNIST_PROBABILITY) -> str:
    """Name of a cached set of image strips, with a hash of the code that renders and canonicalises them.

    :param seed: dataset seed.
    :param split: split name.
    :param count: number of items.
    :param compound_probability: see :func:`camera_augment`.
    :param mnist_probability: see :func:`build_image_cache`.
    """
    from vafn_media.dataset import source_digest

    digest = source_digest("camera.py", "strips.py", "images.py", "corruptions.py", "constants.py")
    options = "".join(f"-{name}{share:g}" for name, share in (("compound", compound_probability),
                                                                 ("mnist", mnist_probability)) if share > 0)
    return f"camera-{split}-seed{seed}-n{count}-copies{CAMERA_COPIES}{options}-{digest}"


def build_image_cache(arms: np.ndarray, lengths: np.ndarray, seed: int, split: str, cache_dir: Path,
                      progress: bool = True, compound_probability: float = COMPOUND_PROBABILITY,
                      mnist_probability: float = MNIST_PROBABILITY) -> dict[str, list]:
    """Image strips of every item, rendered and canonicalised by the current code, cached in one file.

    Returns ``{"clean": [...], "masked": [...], "camera": [[...] per copy]}`` of uint8 canonical strips: a fresh strip
    of the item's label (:func:`~vafn_media.strips.render_strip`, the split's glyphs), a Cutout copy of it, and
    CAMERA_COPIES camera photos (:func:`camera_augment` of training fonts and glyphs only, whatever the split). Item
    ``i`` draws from ``default_rng([seed, split_code, i, 2])``: the strips depend only on the labels, not on the
    speech data, so a speech cache made by older image code can be trained with current strips.

    :param arms: (N, MAX_INSTRUCTION_LENGTH) padded arm ids.
    :param lengths: (N,) instruction lengths.
    :param seed: dataset seed.
    :param split: split name ("train", "test", "heldout").
    :param cache_dir: where the file is stored.
    :param progress: show a tqdm progress bar.
    :param compound_probability: see :func:`camera_augment`.
    :param mnist_probability: chance that a camera photo drawn as scikit-learn handwriting is written with MNIST's
        glyphs instead (its own coin, ``default_rng([seed, split_code, i, 4])``, so the other photos do not change).
    """
    from tqdm import tqdm

    from vafn_media.corruptions import cutout
    from vafn_media.dataset import SPLIT_CODES, stored_strip
    from vafn_media.strips import render_strip

    path = Path(cache_dir) / (camera_cache_key(seed, split, len(lengths), compound_probability, mnist_probability)
                              + ".npz")
    names = ["clean", "masked"] + [f"camera{k}" for k in range(CAMERA_COPIES)]
    if not path.exists():
        store: dict[str, list[np.ndarray]] = {name: [] for name in names}
        for i in tqdm(range(len(lengths)), desc=f"{split} strips and camera cards", unit="item",
                      disable=not progress):
            labels = [int(a) for a in arms[i, : int(lengths[i])]]
            rng = np.random.default_rng([seed, SPLIT_CODES[split], i, 2])
            mnist_coins = np.random.default_rng([seed, SPLIT_CODES[split], i, 4]).random(CAMERA_COPIES)
            strip = render_strip(labels, rng, heldout=split == "heldout")
            store["clean"].append(stored_strip(strip, labels, None))
            store["masked"].append(stored_strip(cutout(strip, rng), labels, strip))
            for k in range(CAMERA_COPIES):
                source = SOURCES[int(rng.choice(len(SOURCES), p=TRAIN_SOURCE_PROBABILITIES))]
                if source == "handwritten" and mnist_coins[k] < mnist_probability:
                    source = MNIST_SOURCE
                ink = render_card_ink(labels, rng, source, heldout=False)
                store[f"camera{k}"].append(stored_strip(camera_augment(ink, rng, compound_probability), labels,
                                                        colour_card(ink, (245, 245, 245), (20, 20, 20))))
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {}
        for name in names:
            arrays[name] = np.concatenate(store[name], axis=1)
            arrays[f"{name}_widths"] = np.array([s.shape[1] for s in store[name]], np.int64)
        tmp = str(path) + ".tmp.npz"
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
    with np.load(path) as data:
        strips = {name: np.split(data[name], np.cumsum(data[f"{name}_widths"])[:-1], axis=1) for name in names}
    return {"clean": strips["clean"], "masked": strips["masked"],
            "camera": [strips[f"camera{k}"] for k in range(CAMERA_COPIES)]}
