"""Evaluation helpers shared by the Table-1 benchmark and the tests: corrupted inputs, exact-match accuracy, timing."""

from __future__ import annotations

import time
from dataclasses import dataclass
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vafn_media.constants import NOISE_SNR_DB
from vafn_media.corruptions import add_awgn, cutout
from vafn_media.dataset import RawItems

if TYPE_CHECKING:
    from vafn_media.generator import InstructionGenerator

#: Table-1 rows: name -> (use audio, audio noisy, use image, image Cutout, use code).
ROWS: dict[str, tuple[bool, bool, bool, bool, bool]] = {
    "Audio": (True, False, False, False, False),
    "Audio (noise)": (True, True, False, False, False),
    "Audio-Visual": (True, False, True, False, False),
    "Audio-Visual (noise)": (True, True, True, True, False),
    "Visual": (False, False, True, False, False),
    "Visual (Cutout)": (False, False, True, True, False),
    "Machine code": (False, False, False, False, True),
}
#: The paper's Table 1 (accuracy %, Easy / Medium / Hard) for the rows it reports.
PAPER_ACCURACY: dict[str, tuple[float, float, float]] = {
    "Audio": (93.8, 87.8, 83.0),
    "Audio (noise)": (87.4, 77.2, 67.0),
    "Audio-Visual": (94.6, 91.2, 90.6),
    "Audio-Visual (noise)": (92.8, 88.0, 83.2),
}
#: The paper's per-instruction latency range (seconds) for audio and audio-visual input.
PAPER_LATENCY_S: dict[str, str] = {"Audio": "0.008-0.025", "Audio-Visual": "0.389-0.571"}

#: Seed of the items that choose between audio checkpoints (`benchmarks/speech_checkpoints.py`) and check the
#: reader's test-time corrections (`benchmarks/speech_corrections.py`); the robustness table uses its own.
SELECTION_SEED: int = 12345
#: Seed of the cards that choose between image checkpoints (`benchmarks/camera_checkpoints.py`); the camera table of
#: `benchmarks/instruction_table.py` uses its own.
CAMERA_SELECTION_SEED: int = 777


@dataclass
class CellResult:
    """Per-item outcomes of one (row, split) cell: correctness, wall and thread-CPU latency, confidence."""

    correct: np.ndarray
    seconds: np.ndarray
    cpu_seconds: np.ndarray
    confidence: np.ndarray
    #: Per item: digit errors (edit distance, capped at the reference length) and reference digits.
    digit_errors: np.ndarray | None = None
    digits: np.ndarray | None = None
    #: Per item: the result was flagged ``low_confidence`` (a rejected input counts as flagged: nothing is acted on).
    flagged: np.ndarray | None = None

    @property
    def acted_right(self) -> float:
        """Share (%) of items read right and not flagged: what a robot acts on correctly."""
        return 100.0 * float(np.mean(self.correct & ~self.flagged)) if self.flagged is not None else float("nan")

    @property
    def acted_wrong(self) -> float:
        """Share (%) of items read wrong and not flagged: what a robot acts on wrongly."""
        return 100.0 * float(np.mean(~self.correct & ~self.flagged)) if self.flagged is not None else float("nan")

    @property
    def digit_accuracy(self) -> float:
        """1 - digit errors / reference digits, in % (100 for a cell of empty instructions)."""
        if self.digits is None or self.digits.sum() == 0:
            return 100.0
        return 100.0 * (1.0 - self.digit_errors.sum() / self.digits.sum())


def corrupted_inputs(items: RawItems, eval_seed: int, index: int, row: str) -> dict:
    """The ``transcribe`` keyword arguments of item ``index`` for a Table-1 row (noise seeded per item).

    :param items: rendered items.
    :param eval_seed: seed of the corruption noise.
    :param index: item index within ``items``.
    :param row: a key of :data:`ROWS`.
    """
    use_audio, noisy, use_image, masked, use_code = ROWS[row]
    kwargs: dict = {}
    if use_audio:
        waveform = items.waveforms[index]
        if noisy:
            waveform = add_awgn(waveform, NOISE_SNR_DB, np.random.default_rng([eval_seed, index, 0]))
        kwargs["audio"] = (waveform, items.sample_rate)
    if use_image:
        image = items.images[index]
        if masked:
            image = cutout(image, np.random.default_rng([eval_seed, index, 1]))
        kwargs["image"] = image
    if use_code:
        kwargs["code"] = "[" + ", ".join(str(a) for a in items.arms[index]) + "]"
    return kwargs


def run_cell(transcribe: Callable[..., object], items: RawItems, eval_seed: int, row: str,
             limit: int | None = None) -> CellResult:
    """Transcribe every item of ``items`` for ``row``; time each call (wall and thread CPU; features included,
    corruption excluded).

    A ValueError (unusable input) counts as a wrong answer.

    :param transcribe: ``InstructionGenerator.transcribe``.
    :param items: rendered items.
    :param eval_seed: corruption seed.
    :param row: a key of :data:`ROWS`.
    :param limit: only the first ``limit`` items.
    """
    count = len(items.arms) if limit is None else min(limit, len(items.arms))
    correct, seconds, cpu, confidence = np.zeros(count, bool), np.zeros(count), np.zeros(count), np.zeros(count)
    errors, digits = np.zeros(count, int), np.array([len(items.arms[i]) for i in range(count)])
    flagged = np.ones(count, bool)
    for i in range(count):
        kwargs = corrupted_inputs(items, eval_seed, i, row)
        start, start_cpu = time.perf_counter(), time.thread_time()
        try:
            result = transcribe(**kwargs)
        except ValueError:
            result = None
        seconds[i], cpu[i] = time.perf_counter() - start, time.thread_time() - start_cpu
        errors[i] = digits[i]
        if result is not None:
            correct[i] = tuple(result.instruction.arms) == tuple(items.arms[i])
            confidence[i] = result.confidence
            flagged[i] = bool(result.low_confidence)
            errors[i] = min(digits[i], edit_distance(tuple(items.arms[i]), tuple(result.instruction.arms)))
    return CellResult(correct, seconds, cpu, confidence, errors, digits, flagged)


def edit_distance(a: tuple[int, ...], b: tuple[int, ...]) -> int:
    """Levenshtein distance between two arm-id sequences (substitutions, insertions, deletions).

    :param a: reference.
    :param b: hypothesis.
    """
    row = list(range(len(b) + 1))
    for i, x in enumerate(a, 1):
        previous, row[0] = row[0], i
        for j, y in enumerate(b, 1):
            previous, row[j] = row[j], min(row[j] + 1, row[j - 1] + 1, previous + (x != y))
    return row[-1]


def dropped_and_inserted(reference: tuple[int, ...], read: tuple[int, ...]) -> tuple[list[int], list[int]]:
    """The digits of ``reference`` a reading lost and the digits it added (a swapped digit counts as both), by
    :mod:`difflib`'s alignment.

    :param reference: true arm ids.
    :param read: arm ids read.
    """
    import difflib

    dropped: list[int] = []
    inserted: list[int] = []
    for operation, a0, a1, b0, b1 in difflib.SequenceMatcher(None, reference, read).get_opcodes():
        if operation in ("delete", "replace"):
            dropped += reference[a0:a1]
        if operation in ("insert", "replace"):
            inserted += read[b0:b1]
    return dropped, inserted


def checkpoint_by_name(checkpoint: str) -> tuple[InstructionGenerator, str]:
    """A generator and its column name for the checkpoint-comparison benchmarks: ``"packaged"`` or a ``.pt`` file
    (with its ``.json`` beside it), named by the folder of its training run.

    :param checkpoint: ``"packaged"`` or a path.
    """
    from vafn_media.generator import InstructionGenerator

    if checkpoint == "packaged":
        return InstructionGenerator.load(), checkpoint
    return InstructionGenerator.load(checkpoint), Path(checkpoint).parent.name


@dataclass
class SpeechItem:
    """One spoken instruction of a robustness set: label, clean waveform and rate, a fast rendition, an image, and
    the phrasing template and voice that said it (for error analysis)."""

    arms: tuple[int, ...]
    waveform: np.ndarray
    sample_rate: int
    fast: np.ndarray
    fast_rate: int
    image: np.ndarray
    template: int
    voice: str


def speech_items(engine: str, count: int, seed: int, heldout: bool = True) -> list[SpeechItem]:
    """Spoken instructions (lengths 1-10, random phrasings) from ``engine``: "espeak" (synthesised in this process)
    or an evaluation engine of :mod:`vafn_media.engines`.

    "fast" renditions are made by the engine itself (espeak: 1.4x its rate; others: duration stretch 0.7).

    :param engine: "espeak" or a name from :func:`vafn_media.engines.available_engines`.
    :param count: number of items.
    :param seed: seed of labels, voices, phrasings and images.
    :param heldout: espeak only: held-out voices, variants and fonts (False: the training ones, for calibration).
    """
    from dataclasses import replace

    from vafn_media.engines import engine_voices, speak_with
    from vafn_media.speech import ESPEAK_SAMPLE_RATE, TEMPLATES, sample_voice, speak
    from vafn_media.strips import render_strip

    items = []
    for i in range(count):
        rng = np.random.default_rng([seed, i])
        arms = tuple(int(a) for a in rng.integers(1, 4, int(rng.integers(1, 11))))
        template = int(rng.integers(len(TEMPLATES)))
        image = render_strip(arms, np.random.default_rng([seed, i, 7]), heldout=heldout)
        if engine == "espeak":
            voice = sample_voice(rng, heldout=heldout)
            clean = speak(arms, voice, template)
            fast = speak(arms, replace(voice, rate=min(450, int(voice.rate * 1.4))), template)
            items.append(SpeechItem(arms, clean, ESPEAK_SAMPLE_RATE, fast, ESPEAK_SAMPLE_RATE, image, template,
                                    voice.full_name))
        else:
            voices = engine_voices(engine)
            voice = voices[i % len(voices)]
            clean, rate = speak_with(engine, arms, voice, template)
            fast, fast_rate = speak_with(engine, arms, voice, template, stretch=0.7)
            items.append(SpeechItem(arms, clean, rate, fast, fast_rate, image, template, voice))
    return items


def degraded_clip(item: SpeechItem, condition: str, seed: int, index: int) -> tuple[np.ndarray, int]:
    """The item's clip under ``condition`` with 0.25 s of silence around it (as a recording would have): (wave, rate).

    :param item: from :func:`speech_items`.
    :param condition: one of :data:`vafn_media.augment.CONDITIONS` ("fast" uses the engine's own fast rendition).
    :param seed: seed of the degradation noise and rooms.
    :param index: the item's index (the degradation of item ``index`` is seeded by ``[seed, index]``).
    """
    from vafn_media.augment import apply_condition

    source, rate = (item.fast, item.fast_rate) if condition == "fast" else (item.waveform, item.sample_rate)
    pad = np.zeros(int(0.25 * rate), np.float32)
    return apply_condition(np.concatenate([pad, source, pad]), rate, "clean" if condition == "fast" else condition,
                           np.random.default_rng([seed, index]))


def robust_cell(transcribe: Callable[..., object], items: list[SpeechItem], condition: str, seed: int,
                with_image: bool = False) -> dict[str, float]:
    """Accuracy of one (engine, condition) cell, audio alone or audio + the item's clean image.

    Returns exact-sequence accuracy, digit accuracy (1 - edit distance / reference digits), the share of results
    flagged ``low_confidence``, of inputs rejected with ValueError, of *wrong and unflagged* and of *right but
    flagged* results (the two costs a flagging threshold trades), and the mean thread-CPU time per call. Each clip is
    made by :func:`degraded_clip`.

    :param transcribe: ``InstructionGenerator.transcribe``.
    :param items: from :func:`speech_items`.
    :param condition: one of :data:`vafn_media.augment.CONDITIONS`.
    :param seed: seed of the degradation noise and rooms.
    :param with_image: also give the clean image.
    """
    exact, digits, total, flagged, rejected, silent_wrong, right_flagged, cpu = 0, 0, 0, 0, 0, 0, 0, []
    for i, item in enumerate(items):
        kwargs = {"audio": degraded_clip(item, condition, seed, i)}
        if with_image:
            kwargs["image"] = item.image
        start = time.thread_time()
        try:
            result = transcribe(**kwargs)
        except ValueError:
            result = None
        cpu.append(time.thread_time() - start)
        total += len(item.arms)
        if result is None:
            rejected += 1
            digits += len(item.arms)
            continue
        read = tuple(result.instruction.arms)
        exact += read == item.arms
        digits += min(len(item.arms), edit_distance(item.arms, read))
        flagged += bool(result.low_confidence)
        silent_wrong += read != item.arms and not result.low_confidence
        right_flagged += read == item.arms and result.low_confidence
    n = max(1, len(items))
    return {"exact": 100.0 * exact / n, "digit": 100.0 * (1 - digits / max(1, total)), "flagged": 100.0 * flagged / n,
            "rejected": 100.0 * rejected / n, "wrong_unflagged": 100.0 * silent_wrong / n,
            "right_flagged": 100.0 * right_flagged / n,
            "cpu_ms": 1000.0 * float(np.mean(cpu)) if cpu else 0.0}


#: Glyph sets of the camera evaluation: name -> (source, held-out). Only the last is seen in training (reference).
CAMERA_SETS: dict[str, tuple[str, bool]] = {
    "unseen TrueType fonts": ("font", True),
    "unseen Hershey fonts": ("hershey", True),
    "unseen handwriting": ("handwritten", True),
    "training TrueType fonts": ("font", False),
}


#: Digit sizes (the card's cell side, pixels, inclusive) the camera cells are also broken down by: thirds of
#: ``camera.CARD_CELL_RANGE``. Blur is in pixels, so it takes more of a small digit.
CELL_SIZE_BINS: tuple[tuple[int, int], ...] = ((40, 53), (54, 67), (68, 80))


@dataclass
class CardItem:
    """One card of the camera evaluation: label, ink map, TrueType font (None for other sources), digit cell (px)."""

    arms: tuple[int, ...]
    ink: np.ndarray
    font: str | None
    cell: int


def camera_items(glyph_set: str, count: int, seed: int) -> list[CardItem]:
    """Cards (lengths 1-10) of one glyph set of :data:`CAMERA_SETS`; TrueType sets cycle through their fonts.

    :param glyph_set: a key of :data:`CAMERA_SETS`.
    :param count: number of cards.
    :param seed: seed of labels and rendering.
    """
    from vafn_media.camera import HELDOUT_TTF_FONTS, TRAIN_TTF_FONTS, draw_card_cell, render_card_ink

    source, heldout = CAMERA_SETS[glyph_set]
    fonts = HELDOUT_TTF_FONTS if heldout else TRAIN_TTF_FONTS
    code = list(CAMERA_SETS).index(glyph_set)
    items = []
    for i in range(count):
        rng = np.random.default_rng([seed, code, i])
        arms = tuple(int(a) for a in rng.integers(1, 4, int(rng.integers(1, 11))))
        font = fonts[i % len(fonts)] if source == "font" else None
        cell = draw_card_cell(rng)  # drawn here, as render_card_ink would, so the card knows its digit size
        items.append(CardItem(arms, render_card_ink(arms, rng, source, heldout, font=font, cell=cell), font, cell))
    return items


def camera_cell(transcribe: Callable[..., object], items: list[CardItem], condition: str,
                seed: int) -> dict[str, object]:
    """Image-only accuracy of one (glyph set, camera condition) cell.

    Returns exact-sequence and per-digit accuracy (%), the share flagged ``low_confidence``, of wrong *and*
    unflagged and of right *but* flagged results, rejections (ValueError, counted wrong), and exact-match counts
    ``[hits, cards]`` per font and per digit size (``per_size``, keyed by the bins of :data:`CELL_SIZE_BINS`).

    :param transcribe: ``InstructionGenerator.transcribe``.
    :param items: from :func:`camera_items`.
    :param condition: one of :data:`vafn_media.camera.CAMERA_CONDITIONS`.
    :param seed: seed of the photo (palette, warp, light, noise).
    """
    from vafn_media.camera import CAMERA_CONDITIONS, apply_camera_condition

    code = CAMERA_CONDITIONS.index(condition)
    exact, errors, total, flagged, rejected, silent_wrong, right_flagged = 0, 0, 0, 0, 0, 0, 0
    per_font: dict[str, list[int]] = {}
    per_size: dict[tuple[int, int], list[int]] = {size: [0, 0] for size in CELL_SIZE_BINS}
    for i, item in enumerate(items):
        image = apply_camera_condition(item.ink, condition, np.random.default_rng([seed, i, code]))
        try:
            result = transcribe(image=image)
        except ValueError:
            result = None
        total += len(item.arms)
        hit = result is not None and tuple(result.instruction.arms) == item.arms
        if item.font is not None:
            per_font.setdefault(item.font, [0, 0])
            per_font[item.font][0] += hit
            per_font[item.font][1] += 1
        for low, high in CELL_SIZE_BINS:
            if low <= item.cell <= high:
                per_size[low, high][0] += hit
                per_size[low, high][1] += 1
        if result is None:
            rejected += 1
            errors += len(item.arms)
            continue
        read = tuple(result.instruction.arms)
        exact += hit
        errors += min(len(item.arms), edit_distance(item.arms, read))
        flagged += bool(result.low_confidence)
        silent_wrong += (not hit) and not result.low_confidence
        right_flagged += hit and result.low_confidence
    n = max(1, len(items))
    return {"exact": 100.0 * exact / n, "digit": 100.0 * (1 - errors / max(1, total)),
            "flagged": 100.0 * flagged / n, "rejected": 100.0 * rejected / n,
            "wrong_unflagged": 100.0 * silent_wrong / n, "right_flagged": 100.0 * right_flagged / n,
            "per_font": per_font, "per_size": per_size}
