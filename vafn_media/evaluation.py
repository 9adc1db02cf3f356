"""Evaluation helpers shared by the Table-1 benchmark and the tests: corrupted inputs, exact-match accuracy, timing."""

from __future__ import annotations

import time
from dataclasses import dataclass
from collections.abc import Callable

import numpy as np

from vafn_media.constants import NOISE_SNR_DB
from vafn_media.corruptions import add_awgn, cutout
from vafn_media.dataset import RawItems

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


@dataclass
class CellResult:
    """Per-item outcomes of one (row, split) cell: correctness, wall and thread-CPU latency, confidence."""

    correct: np.ndarray
    seconds: np.ndarray
    cpu_seconds: np.ndarray
    confidence: np.ndarray


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
    for i in range(count):
        kwargs = corrupted_inputs(items, eval_seed, i, row)
        start, start_cpu = time.perf_counter(), time.thread_time()
        try:
            result = transcribe(**kwargs)
        except ValueError:
            result = None
        seconds[i], cpu[i] = time.perf_counter() - start, time.thread_time() - start_cpu
        if result is not None:
            correct[i] = tuple(result.instruction.arms) == tuple(items.arms[i])
            confidence[i] = result.confidence
    return CellResult(correct, seconds, cpu, confidence)
