"""Seeded, sharded, cached generation of paired (speech, digit strip, arm ids) items.

Item ``i`` of a split draws everything from ``np.random.default_rng([seed, split_code, i])``, so labels, voices and
images do not depend on sharding. espeak-ng keeps internal state, so audio is bit-identical only when the same
fixed-size shard is synthesised in a fresh process: every shard runs in its own spawned process.
"""

from __future__ import annotations

import hashlib
import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from vafn_gym.constants import DIFFICULTY_LENGTHS
from vafn_media.constants import IMAGE_HEIGHT, MAX_INSTRUCTION_LENGTH, MIN_IMAGE_WIDTH, NUM_ARMS, SAMPLE_RATE

if TYPE_CHECKING:  # pragma: no cover
    from vafn_media.speech import Voice

#: Splits: training voices/glyphs; fresh items of the same voices/glyphs; held-out voices, variants and glyphs.
SPLIT_CODES: dict[str, int] = {"train": 0, "test": 1, "heldout": 2}
#: Items per shard; part of the dataset's identity because espeak output depends on the shard's call history.
SHARD_SIZE: int = 500
#: Default cache directory for generated training data.
DEFAULT_CACHE = Path(os.environ.get("VAFN_CACHE", Path.home() / ".cache" / "vafn" / "multimedia"))
#: Degraded copies (random :func:`vafn_media.augment.augment` chains) cached per utterance beside the clean one.
AUGMENTED_COPIES: int = 2
#: Quantisation of cached strips (ink in [0, 1] stored as uint8).
INK_LEVELS: float = 255.0


@dataclass(frozen=True)
class ItemSpec:
    """Everything needed to render one item: the arm ids, how they are spoken and how they are drawn."""

    arms: tuple[int, ...]
    voice: Voice
    template: int
    empty_phrase: int
    image_seed: int
    heldout: bool
    #: Said one word at a time with these joins (:func:`vafn_media.speech.splice_words`); None: one utterance.
    joins: tuple[float, ...] | None = None


def item_spec(seed: int, split: str, index: int, difficulty: str | None = None, mbrola: float = 0.0,
              splice: float = 0.0, pico: float = 0.0, rhvoice: float = 0.0, dectalk: float = 0.0) -> ItemSpec:
    """The deterministic specification of item ``index`` of ``split``.

    :param seed: dataset seed.
    :param split: "train", "test" or "heldout".
    :param index: item index.
    :param difficulty: restrict the length to a paper bucket ("easy", "medium", "hard"); None = uniform 0..10.
    :param mbrola: share of items spoken by an MBROLA voice (held-out ones in "heldout"); 0 leaves every item as it
        was, since the choice is drawn from a stream of its own.
    :param splice: share of items said one word at a time, joined with random gaps and overlaps in
        :data:`~vafn_media.speech.SPLICE_GAP_RANGE` (a stream of its own too).
    :param pico: share of items spoken by a Pico voice (held-out ones in "heldout"), drawn on MBROLA's stream after
        its share, so ``mbrola + pico`` must not exceed 1 and pico = 0 leaves every item as it was.
    :param rhvoice: share of items spoken by an RHVoice voice (held-out ones in "heldout"), drawn on the same stream
        after Pico's share; rhvoice = 0 leaves every item as it was.
    :param dectalk: share of items spoken by a DECtalk speaker (held-out ones in "heldout"), drawn on the same stream
        after RHVoice's share; the four shares sum to at most 1 and dectalk = 0 leaves every item as it was.
    """
    from vafn_media.speech import (EMPTY_PHRASES, SPLICE_GAP_RANGE, TEMPLATES, dectalk_voice, mbrola_voice, phrase,
                                   pico_voice, rhvoice_voice, sample_voice)

    if split not in SPLIT_CODES:
        raise ValueError(f"unknown split {split!r}; choose from {list(SPLIT_CODES)}")
    if min(mbrola, pico, rhvoice, dectalk) < 0 or mbrola + pico + rhvoice + dectalk > 1:
        raise ValueError(f"the MBROLA, Pico, RHVoice and DECtalk shares must be >= 0 and sum to at most 1, got "
                         f"{mbrola}, {pico}, {rhvoice} and {dectalk}")
    difficulty_code = 0 if difficulty is None else 1 + list(DIFFICULTY_LENGTHS).index(difficulty)
    rng = np.random.default_rng([seed, SPLIT_CODES[split], difficulty_code, index])
    low, high = (0, MAX_INSTRUCTION_LENGTH) if difficulty is None else DIFFICULTY_LENGTHS[difficulty]
    length = int(rng.integers(low, high + 1))
    arms = tuple(int(a) for a in rng.integers(1, NUM_ARMS + 1, length))
    heldout = split == "heldout"
    voice = sample_voice(rng, heldout)

    def stream(purpose: int) -> np.random.Generator:  # draws that leave the item's main stream untouched
        return np.random.default_rng([seed, SPLIT_CODES[split], difficulty_code, index, purpose])

    # in this order
    synthesisers = ((mbrola, mbrola_voice), (pico, pico_voice), (rhvoice, rhvoice_voice), (dectalk, dectalk_voice))
    if any(share > 0 for share, _ in synthesisers):
        choice = stream(3)
        draw, bound = choice.random(), 0.0
        for share, other_voice in synthesisers:
            bound += share
            if draw < bound:
                voice = other_voice(choice, heldout, voice)
                break
    template, empty_phrase = int(rng.integers(len(TEMPLATES))), int(rng.integers(len(EMPTY_PHRASES)))
    joins = None
    if splice > 0:
        choice = stream(4)
        if choice.random() < splice:
            n_joins = len(phrase(arms, template, empty_phrase).split()) - 1
            joins = tuple(float(g) for g in np.round(choice.uniform(*SPLICE_GAP_RANGE, n_joins), 4))
    return ItemSpec(arms, voice, template, empty_phrase, int(rng.integers(2**31)), heldout, joins)


def render_item(spec: ItemSpec) -> tuple[np.ndarray, np.ndarray]:
    """Synthesise the speech (float32 at espeak's rate) and render the strip (uint8) of one item.

    :param spec: the item specification.
    """
    from vafn_media.speech import speak
    from vafn_media.strips import render_strip

    waveform = speak(spec.arms, spec.voice, spec.template, spec.empty_phrase, spec.joins)
    image = render_strip(spec.arms, np.random.default_rng(spec.image_seed), heldout=spec.heldout)
    return waveform, image


@dataclass
class RawItems:
    """Raw rendered items: arm ids, waveforms at ``sample_rate`` and uint8 strips."""

    arms: list[tuple[int, ...]]
    waveforms: list[np.ndarray]
    sample_rate: int
    images: list[np.ndarray]
    specs: list[ItemSpec]


def _render_range(args: tuple[int, str, int, int, str | None, tuple[tuple[str, float], ...]]) -> RawItems:
    from vafn_media.speech import ESPEAK_SAMPLE_RATE

    seed, split, start, count, difficulty, shares = args
    specs = [item_spec(seed, split, i, difficulty, **dict(shares)) for i in range(start, start + count)]
    rendered = [render_item(spec) for spec in specs]
    return RawItems([s.arms for s in specs], [r[0] for r in rendered], ESPEAK_SAMPLE_RATE,
                    [r[1] for r in rendered], specs)


def run_shards(function: Callable[[tuple], Any], jobs: Sequence[tuple], workers: int) -> Iterator[tuple[tuple, Any]]:
    """``(job, function(job))`` as each job finishes, every job in a fresh single-threaded spawn process.

    A worker that dies (a speech engine's native crash) raises ``RuntimeError`` naming the unfinished jobs instead of
    leaving the caller waiting forever, as ``multiprocessing.Pool`` would.
    """
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max(1, workers), mp_context=context, initializer=_quiet_worker,
                             max_tasks_per_child=1) as pool:
        futures = {pool.submit(function, job): job for job in jobs}
        try:
            for future in as_completed(futures):
                yield futures[future], future.result()
        except BrokenProcessPool as error:
            unfinished = [job for future, job in futures.items()
                          if future.cancelled() or not future.done() or future.exception() is not None]
            raise RuntimeError(f"a worker process died while running {function.__name__} (a native crash, e.g. in the "
                               f"speech engine); unfinished jobs: {unfinished}") from error


def _quiet_worker() -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def generate_raw(seed: int, split: str, count: int, difficulty: str | None = None, start: int = 0,
                 workers: int = 1) -> RawItems:
    """Render ``count`` items in fresh processes (one per shard), so the audio is reproducible.

    :param seed: dataset seed.
    :param split: "train", "test" or "heldout".
    :param count: number of items.
    :param difficulty: optional paper difficulty bucket.
    :param start: index of the first item.
    :param workers: parallel processes.
    """
    jobs = [
        (seed, split, s, min(SHARD_SIZE, start + count - s), difficulty, ())
        for s in range(start, start + count, SHARD_SIZE)
    ]
    done = dict(run_shards(_render_range, jobs, workers))
    parts = [done[job] for job in jobs]
    return RawItems([a for p in parts for a in p.arms], [w for p in parts for w in p.waveforms], parts[0].sample_rate,
                    [im for p in parts for im in p.images], [s for p in parts for s in p.specs])


def stored_strip(image: np.ndarray, labels: Sequence[int], fallback: np.ndarray | None) -> np.ndarray:
    """Canonical strip of a training image as uint8 ink; an image the reader rejects (a Cutout or a photo that looks
    like noise) or on which a mask may hide a digit is stored as the ``fallback`` image's strip, or as a blank strip
    when it shows the empty instruction or has no fallback.

    :param image: the image to store.
    :param labels: its instruction's arm ids.
    :param fallback: an image of the same instruction the reader accepts (or None).
    """
    from vafn_media.images import canonical_strip, read_strip

    try:
        strip, hidden = read_strip(image)
        if hidden is not None:  # a mask hides a digit the label still names: the reader marks it, never guesses it
            raise ValueError("a digit may be hidden")
    except ValueError:
        if not labels or fallback is None:
            strip = np.zeros((IMAGE_HEIGHT, MIN_IMAGE_WIDTH), np.float32)
        else:
            strip = canonical_strip(fallback)
    return np.rint(strip * INK_LEVELS).astype(np.uint8)


def _compact_shard(args: tuple[int, str, int, int, str, tuple[tuple[str, float], ...], float]) -> str:
    """Render one shard and store training-ready arrays: log-mel features of the clean utterance (resampled to
    SAMPLE_RATE) and of AUGMENTED_COPIES degraded copies (tempo, speed, silences, room, noise, telephone,
    gain/clipping), and canonical strips of the clean and of a Cutout copy of each image."""
    import torch

    from vafn_media.augment import augment, random_tempo, resample
    from vafn_media.corruptions import cutout
    from vafn_media.features import log_mel

    torch.set_num_threads(1)
    seed, split, start, count, path, shares, tempo = args
    raw = _render_range((seed, split, start, count, None, shares))
    audio: list[list[np.ndarray]] = [[] for _ in range(1 + AUGMENTED_COPIES)]
    clean, masked = [], []
    for index, waveform, image, arms in zip(range(start, start + count), raw.waveforms, raw.images, raw.arms):
        rng = np.random.default_rng([seed, SPLIT_CODES[split], index, 1])
        tempo_rng = np.random.default_rng([seed, SPLIT_CODES[split], index, 3])  # 2: the camera cache's
        wave = resample(waveform, raw.sample_rate, SAMPLE_RATE)
        if wave.size == 0:
            wave = np.zeros(SAMPLE_RATE // 4, np.float32)
        copies = [wave] + [augment(random_tempo(wave, tempo_rng, tempo), rng) for _ in range(AUGMENTED_COPIES)]
        for store, copy in zip(audio, copies):
            store.append(log_mel(copy, SAMPLE_RATE)[0].numpy().astype(np.float16))
        clean.append(stored_strip(image, arms, None))
        masked.append(stored_strip(cutout(image, rng), arms, image))
    return save_items(path, raw.arms, audio, clean, masked)


def save_items(path: str | Path, arms: Sequence[Sequence[int]], audio: Sequence[Sequence[np.ndarray]],
               clean: Sequence[np.ndarray], masked: Sequence[np.ndarray]) -> str:
    """Write training-ready items atomically in the layout :meth:`TrainingData.load` reads; returns ``path``.

    :param path: the ``.npz`` file.
    :param arms: each item's arm ids.
    :param audio: per copy (clean first, then the degraded ones), each item's (N_MELS, T) float16 features.
    :param clean: each item's uint8 strip.
    :param masked: each item's uint8 Cutout strip.
    """
    from vafn_gym.files import atomic_write

    arrays = {}
    for k, store in enumerate(audio):
        arrays[f"audio{k}"] = np.concatenate(store, axis=1)
        arrays[f"frames{k}"] = np.array([a.shape[1] for a in store], np.int64)
    atomic_write(path, lambda tmp: np.savez(
        tmp, arms=np.array([list(a) + [0] * (MAX_INSTRUCTION_LENGTH - len(a)) for a in arms], np.int8),
        lengths=np.array([len(a) for a in arms], np.int8), **arrays,
        clean=np.concatenate(clean, axis=1), clean_widths=np.array([c.shape[1] for c in clean], np.int64),
        masked=np.concatenate(masked, axis=1), masked_widths=np.array([m.shape[1] for m in masked], np.int64)))
    return str(path)


@dataclass
class TrainingData:
    """Training-ready arrays of a cached split (ragged arrays stored flat with lengths).

    ``clean_audio`` holds the clean utterances' features, ``augmented_audio[k]`` the k-th degraded copy of each.
    """

    arms: np.ndarray
    lengths: np.ndarray
    clean_audio: list[np.ndarray]
    augmented_audio: list[list[np.ndarray]]
    clean: list[np.ndarray]
    masked: list[np.ndarray]

    def __len__(self) -> int:
        return len(self.lengths)

    @property
    def noisy_audio(self) -> list[np.ndarray]:
        """The first degraded copy of every utterance (the "corrupted" evaluation input)."""
        return self.augmented_audio[0]

    @classmethod
    def concatenate(cls, parts: Sequence[TrainingData]) -> TrainingData:
        """The items of ``parts``, in order, as one set."""
        return cls(np.concatenate([p.arms for p in parts]), np.concatenate([p.lengths for p in parts]),
                   [a for p in parts for a in p.clean_audio],
                   [[a for p in parts for a in p.augmented_audio[k]] for k in range(AUGMENTED_COPIES)],
                   [s for p in parts for s in p.clean], [s for p in parts for s in p.masked])

    @classmethod
    def load(cls, paths: Sequence[str]) -> TrainingData:
        """Concatenate cached shard files.

        :param paths: shard files written by :func:`build_cache`.
        """
        arms, lengths, clean, masked = [], [], [], []
        audio: list[list[np.ndarray]] = [[] for _ in range(1 + AUGMENTED_COPIES)]
        for path in paths:
            with np.load(path) as shard:
                arms.append(shard["arms"])
                lengths.append(shard["lengths"])
                for k, store in enumerate(audio):
                    store += np.split(shard[f"audio{k}"], np.cumsum(shard[f"frames{k}"])[:-1], axis=1)
                clean += np.split(shard["clean"], np.cumsum(shard["clean_widths"])[:-1], axis=1)
                masked += np.split(shard["masked"], np.cumsum(shard["masked_widths"])[:-1], axis=1)
        return cls(np.concatenate(arms), np.concatenate(lengths), audio[0], audio[1:], clean, masked)


def cache_key(seed: int, split: str, count: int, mbrola: float = 0.0, splice: float = 0.0, pico: float = 0.0,
              tempo: float = 0.0, rhvoice: float = 0.0, dectalk: float = 0.0) -> str:
    """Name of a cached dataset, including a hash of the generator's source so stale caches are not reused.

    :param seed: dataset seed.
    :param split: split name.
    :param count: number of items.
    :param mbrola: share of items spoken by MBROLA voices.
    :param splice: share of items said one word at a time.
    :param pico: share of items spoken by Pico voices.
    :param tempo: chance that a degraded copy's tempo is changed.
    :param rhvoice: share of items spoken by RHVoice voices.
    :param dectalk: share of items spoken by DECtalk speakers.
    """
    digest = source_digest("dataset.py", "speech.py", "strips.py", "images.py", "corruptions.py", "constants.py",
                           "features.py", "augment.py")
    options = (("mbrola", mbrola), ("splice", splice), ("pico", pico), ("tempo", tempo), ("rhvoice", rhvoice),
               ("dectalk", dectalk))
    shares = "".join(f"-{name}{share:g}" for name, share in options if share > 0)
    return f"{split}-seed{seed}-n{count}{shares}-shard{SHARD_SIZE}-{digest}"


def source_digest(*names: str) -> str:
    """Short SHA-1 of these ``vafn_media`` source files, in order: a cache built by other code is never reused."""
    here = Path(__file__).parent
    digest = hashlib.sha1()
    for name in names:
        digest.update((here / name).read_bytes())
    return digest.hexdigest()[:10]


#: The synthesisers besides espeak-ng's own voices whose shares :func:`item_spec` draws, in its order, on one stream
#: (their shares sum to at most 1).
SYNTHESISERS: tuple[str, ...] = ("mbrola", "pico", "rhvoice", "dectalk")


def data_shares(args: dict[str, Any]) -> dict[str, float]:
    """The :func:`build_cache` shares (``mbrola``, ``pico``, ``rhvoice``, ``dectalk``, ``tempo``) of a training
    command's arguments (``vars`` of its namespace, as a checkpoint's metadata stores them; a missing option is 0), so
    that a checkpoint's validation split can be rebuilt exactly as its training built it.

    :param args: the training command's arguments by name (``mbrola_probability``, ...).
    """
    return {name: args.get(f"{name}_probability", 0.0) for name in (*SYNTHESISERS, "tempo")}


def build_cache(seed: int, split: str, count: int, cache_dir: Path = DEFAULT_CACHE, workers: int = 2,
                progress: bool = True, mbrola: float = 0.0, splice: float = 0.0, pico: float = 0.0,
                tempo: float = 0.0, rhvoice: float = 0.0, dectalk: float = 0.0) -> TrainingData:
    """Generate (or reuse) the cached training arrays of a split, one fresh process per shard, with a progress bar.

    :param seed: dataset seed.
    :param split: "train", "test" or "heldout".
    :param count: number of items.
    :param cache_dir: where shards are stored.
    :param workers: parallel processes.
    :param progress: show a tqdm progress bar.
    :param mbrola: share of items spoken by MBROLA voices (:func:`item_spec`).
    :param splice: share of items said one word at a time (:func:`item_spec`).
    :param pico: share of items spoken by Pico voices (:func:`item_spec`).
    :param tempo: chance that a degraded copy's tempo is changed (:func:`vafn_media.augment.random_tempo`).
    :param rhvoice: share of items spoken by RHVoice voices (:func:`item_spec`).
    :param dectalk: share of items spoken by DECtalk speakers (:func:`item_spec`).
    """
    from tqdm import tqdm

    directory = Path(cache_dir) / cache_key(seed, split, count, mbrola, splice, pico, tempo, rhvoice, dectalk)
    directory.mkdir(parents=True, exist_ok=True)
    starts = range(0, count, SHARD_SIZE)
    paths = [str(directory / f"shard{s // SHARD_SIZE:04d}.npz") for s in starts]
    # item_spec's keyword arguments, as a tuple (jobs are hashed)
    shares = (("mbrola", mbrola), ("splice", splice), ("pico", pico), ("rhvoice", rhvoice), ("dectalk", dectalk))
    jobs = [(seed, split, s, min(SHARD_SIZE, count - s), path, shares, tempo) for s, path in zip(starts, paths)]
    todo = [job for job, path in zip(jobs, paths) if not os.path.exists(path)]
    if todo:
        with tqdm(total=len(jobs), initial=len(jobs) - len(todo), disable=not progress,
                  desc=f"generating {split} data", unit="shard") as bar:
            for _ in run_shards(_compact_shard, todo, workers):
                bar.update()
    return TrainingData.load(paths)
