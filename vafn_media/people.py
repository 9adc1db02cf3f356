"""Real people's commands: recorded words of many speakers and handwritten digits, split by speaker, joined into
instructions.

Two local corpora, each read from a copy the user made (nothing is downloaded or shipped):

- spoken words in Google Speech Commands' layout, ``<root>/{one,two,three}/<speaker>_nohash_<n>.wav`` (CC BY 4.0);
  speakers are split by a hash of their id (:func:`speaker_split`), so a speaker is in exactly one split for good;
- MNIST's *training* file (``train-images-idx3-ubyte[.gz]`` and ``train-labels-idx1-ubyte[.gz]``); its glyphs are
  split by index (:data:`GLYPH_SPLITS`). MNIST's test split is never read here.

An instruction is said word by word with natural pauses by a speaker of the split (a word that speaker never said comes
from another speaker of the same split) and written as a row of handwritten digits on paper
(:func:`handwriting_strip`).
"""

from __future__ import annotations

import gzip
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from vafn_media.constants import CUTOUT_FRACTION, MAX_INSTRUCTION_LENGTH, NUM_ARMS, SAMPLE_RATE

#: Folder name of each arm id's word in the speech corpus.
WORDS: dict[int, str] = {1: "one", 2: "two", 3: "three"}
#: Speaker splits: a speaker's split is the first byte of the SHA-1 of its id, modulo 10, in these residues.
SPEAKER_SPLITS: dict[str, tuple[int, ...]] = {"train": (0, 1, 2, 3, 4, 5, 6), "selection": (7,), "test": (8, 9)}
#: Glyph splits of MNIST's training file by image index (its writers are not labelled, so they may recur).
GLYPH_SPLITS: dict[str, tuple[int, int]] = {"train": (0, 50_000), "selection": (50_000, 55_000),
                                            "test": (55_000, 60_000)}
#: Pause between two words of a spoken instruction, and silence before the first and after the last (seconds).
PAUSE_RANGE: tuple[float, float] = (0.1, 0.9)
EDGE_SILENCE_RANGE: tuple[float, float] = (0.05, 0.5)
#: A word's sound is the loudest run of its 10 ms frames within this many dB of its loudest frame, runs closer than
#: WORD_JOIN_S counting as one, plus a margin each side.
WORD_DYNAMIC_DB: float = 30.0
WORD_JOIN_S: float = 0.12
WORD_MARGIN_S: float = 0.05
#: Paper and ink grey levels, glyph height range (pixels) and the gap between digits (fraction of the glyph height).
PAPER_RANGE: tuple[int, int] = (170, 255)
INK_RANGE: tuple[int, int] = (0, 90)
GLYPH_HEIGHT_RANGE: tuple[int, int] = (20, 64)
SPACING_RANGE: tuple[float, float] = (-0.05, 0.6)
#: Training items whose instruction is empty (silence and blank paper), the chance that a degraded copy is
#: telephone-band (8 kHz) audio, and that it then also gets white noise of 15-25 dB.
EMPTY_PROBABILITY: float = 0.03
PHONE_PROBABILITY: float = 0.6
PHONE_NOISE_PROBABILITY: float = 0.5
#: Largest change of a word's level (dB, either way, per word) in the training items.
WORD_GAIN_DB: float = 12.0


def speaker_split(speaker: str) -> str:
    """The split ("train", "selection" or "test") a speaker belongs to, from a hash of its id (stable forever).

    :param speaker: the speaker id (Speech Commands: the file name's part before ``_nohash_``).
    """
    residue = hashlib.sha1(speaker.encode()).digest()[0] % 10
    return next(name for name, residues in SPEAKER_SPLITS.items() if residue in residues)


def _check_split(split: str, splits: Sequence[str]) -> None:
    if split not in splits:
        raise ValueError(f"unknown split {split!r}; choose from {list(splits)}")


@dataclass(frozen=True)
class SpokenWords:
    """The recorded words of one split: speaker id -> arm id -> WAV files."""

    split: str
    speakers: dict[str, dict[int, tuple[Path, ...]]]

    @classmethod
    def read(cls, root: str | Path | Sequence[str | Path], split: str) -> SpokenWords:
        """Index ``<root>/{one,two,three}/*.wav`` of one corpus folder or several (their speakers pooled; a file name
        already seen in an earlier folder is skipped) and keep the speakers of ``split``.

        :param root: the corpus folder, or a sequence of them.
        :param split: "train", "selection" or "test".
        """
        _check_split(split, list(SPEAKER_SPLITS))
        roots = [Path(root)] if isinstance(root, (str, Path)) else [Path(r) for r in root]
        if not roots:
            raise ValueError("no spoken-word corpus folder given")
        speakers: dict[str, dict[int, list[Path]]] = {}
        seen: set[tuple[str, str]] = set()
        for folder in roots:
            missing = [word for word in WORDS.values() if not (folder / word).is_dir()]
            if missing:
                raise ValueError(f"{folder} is not a spoken-word corpus: it has no folder {', '.join(missing)} "
                                 f"(expected <root>/one, two, three/<speaker>_nohash_<n>.wav)")
            for arm, word in WORDS.items():
                for path in sorted((folder / word).glob("*.wav")):
                    speaker = path.name.split("_nohash_")[0]
                    if speaker_split(speaker) == split and (word, path.name) not in seen:
                        seen.add((word, path.name))
                        speakers.setdefault(speaker, {}).setdefault(arm, []).append(path)
        if not speakers:
            raise ValueError(f"{', '.join(map(str, roots))} has no recordings of {split} speakers")
        return cls(split, {s: {a: tuple(p) for a, p in words.items()} for s, words in sorted(speakers.items())})

    def complete_speakers(self) -> list[str]:
        """Speakers who said every word."""
        return [s for s, words in self.speakers.items() if len(words) == NUM_ARMS]

    def clips(self) -> int:
        """Number of recordings."""
        return sum(len(paths) for words in self.speakers.values() for paths in words.values())


@lru_cache(maxsize=4096)
def load_word(path: Path) -> np.ndarray:
    """One recorded word at SAMPLE_RATE, cut to where it sounds (:func:`word_span`).

    :param path: a WAV file.
    """
    from vafn_media.audio import read_audio_file
    from vafn_media.augment import resample

    samples, rate = read_audio_file(path)
    waveform = resample(samples.mean(axis=1), rate, SAMPLE_RATE)
    return waveform[word_span(waveform, SAMPLE_RATE)]


def word_span(waveform: np.ndarray, rate: int) -> slice:
    """Where a recorded word sounds: the loudest run of 10 ms frames within :data:`WORD_DYNAMIC_DB` of the loudest
    frame (runs closer than :data:`WORD_JOIN_S` are one run; a click or breath apart from the word is left out),
    widened by :data:`WORD_MARGIN_S` each side (the whole clip when it is silent).

    :param waveform: float32 samples.
    :param rate: their rate in Hz.
    """
    hop = max(1, rate // 100)
    frames = len(waveform) // hop
    if frames == 0:
        return slice(0, len(waveform))
    energy = np.mean(np.square(waveform[: frames * hop].reshape(frames, hop), dtype=np.float64), axis=1)
    if energy.max() <= 0:
        return slice(0, len(waveform))
    loud = np.flatnonzero(energy >= energy.max() * 10 ** (-WORD_DYNAMIC_DB / 10))
    breaks = np.flatnonzero(np.diff(loud) > int(WORD_JOIN_S * 100)) + 1
    runs = np.split(loud, breaks)
    run = max(runs, key=lambda r: energy[r[0]: r[-1] + 1].sum())
    margin = int(WORD_MARGIN_S * rate)
    return slice(max(0, run[0] * hop - margin), min(len(waveform), (run[-1] + 1) * hop + margin))


def say_instruction(words: SpokenWords, arms: Sequence[int], rng: np.random.Generator,
                    speaker: str | None = None, word_gain_db: float = 0.0) -> tuple[np.ndarray, str]:
    """A spoken instruction at SAMPLE_RATE: one recording per arm id, with pauses; returns (waveform, speaker).

    :param words: the split's recordings.
    :param arms: the instruction's arm ids (none: a short silence).
    :param rng: random generator (speaker, recordings, pauses).
    :param speaker: who says it (default: a random speaker of the split); a word this speaker never said is taken
        from another speaker of the split (few people of a corpus say every word).
    :param word_gain_db: each word louder or quieter by up to this many dB, drawn per word (training items: a reader
        that hears one word of a command much quieter than the next must still hear it).
    """
    if speaker is None:
        speaker = list(words.speakers)[int(rng.integers(len(words.speakers)))]
    elif speaker not in words.speakers:
        raise ValueError(f"speaker {speaker!r} is not in the {words.split} split")
    pieces = [np.zeros(int(rng.uniform(*EDGE_SILENCE_RANGE) * SAMPLE_RATE), np.float32)]
    for position, arm in enumerate(arms):
        said = words.speakers[speaker].get(int(arm))
        if said is None:
            others = [s for s, w in words.speakers.items() if int(arm) in w]
            said = words.speakers[others[int(rng.integers(len(others)))]][int(arm)]
        if position:
            pieces.append(np.zeros(int(rng.uniform(*PAUSE_RANGE) * SAMPLE_RATE), np.float32))
        word = load_word(said[int(rng.integers(len(said)))])
        if word_gain_db:
            word = word * np.float32(10 ** (rng.uniform(-word_gain_db, word_gain_db) / 20))
        pieces.append(word)
    pieces.append(np.zeros(int(rng.uniform(*EDGE_SILENCE_RANGE) * SAMPLE_RATE), np.float32))
    return np.concatenate(pieces).astype(np.float32), speaker


def _read_idx(path: Path) -> np.ndarray:
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rb") as handle:
        data = handle.read()
    magic = int.from_bytes(data[:4], "big")
    if magic not in (2049, 2051):
        raise ValueError(f"{path} is not an MNIST idx file (magic number {magic}, expected 2049 or 2051)")
    dims = [int.from_bytes(data[4 + 4 * k: 8 + 4 * k], "big") for k in range(magic & 0xFF)]
    array = np.frombuffer(data, np.uint8, offset=4 + 4 * len(dims))
    if array.size != int(np.prod(dims)):
        raise ValueError(f"{path} is truncated: {array.size} values for shape {dims}")
    return array.reshape(dims)


def _idx_file(root: Path, name: str) -> Path:
    for candidate in (root / name, root / f"{name}.gz"):
        if candidate.is_file():
            return candidate
    raise ValueError(f"{root} has no {name} or {name}.gz (MNIST's training split)")


@lru_cache(maxsize=8)
def handwritten_glyphs(root: str, split: str) -> dict[int, tuple[np.ndarray, ...]]:
    """MNIST training-file glyphs of 1, 2 and 3 in ``split``, each cropped to its ink and padded square (float32 ink
    in [0, 1]).

    :param root: folder with ``train-images-idx3-ubyte[.gz]`` and ``train-labels-idx1-ubyte[.gz]``.
    :param split: "train", "selection" or "test" (index ranges :data:`GLYPH_SPLITS`).
    """
    _check_split(split, list(GLYPH_SPLITS))
    folder = Path(root)
    images = _read_idx(_idx_file(folder, "train-images-idx3-ubyte"))
    labels = _read_idx(_idx_file(folder, "train-labels-idx1-ubyte"))
    if images.ndim != 3 or len(images) != len(labels):
        raise ValueError(f"{folder}: {images.shape} images for {labels.shape} labels")
    start, stop = GLYPH_SPLITS[split]
    images, labels = images[start:stop], labels[start:stop]
    from vafn_media.strips import square_glyph

    return {arm: tuple(square_glyph(image) for image in images[labels == arm].astype(np.float32) / 255.0)
            for arm in range(1, NUM_ARMS + 1)}


def handwriting_strip(glyphs: dict[int, Sequence[np.ndarray]], arms: Sequence[int],
                      rng: np.random.Generator) -> np.ndarray:
    """A row of handwritten digits on paper (uint8, dark ink on light paper): random glyph size, spacing, baseline,
    stroke weight, paper tone and shading.

    :param glyphs: arm id -> square glyphs (ink in [0, 1]).
    :param arms: the instruction's arm ids (none: blank paper).
    :param rng: random generator.
    """
    import cv2

    if len(arms) > MAX_INSTRUCTION_LENGTH:
        raise ValueError(f"at most {MAX_INSTRUCTION_LENGTH} digits fit a strip, got {len(arms)}")
    height = int(rng.integers(GLYPH_HEIGHT_RANGE[0], GLYPH_HEIGHT_RANGE[1] + 1))
    margin = int(height * rng.uniform(0.2, 0.8))
    cells = []
    for arm in arms:
        pool = glyphs[int(arm)]
        glyph = pool[int(rng.integers(len(pool)))]
        size = max(6, int(round(height * rng.uniform(0.8, 1.1))))
        ink = cv2.resize(glyph, (max(4, int(size * rng.uniform(0.8, 1.15))), size), interpolation=cv2.INTER_AREA)
        ink = np.clip(ink, 0.0, 1.0) ** rng.uniform(0.6, 1.5)
        cell = np.zeros((height + 2 * margin, ink.shape[1]), np.float32)
        top = int(np.clip(margin + (height - size) / 2 + rng.normal(0, 0.06 * height), 0, cell.shape[0] - size))
        cell[top: top + size] = ink
        gap = int(round(height * rng.uniform(*SPACING_RANGE)))
        cells.append((cell, gap))
    width = max(height, margin * 2 + sum(c.shape[1] + max(g, 0) for c, g in cells))
    ink_map = np.zeros((height + 2 * margin, width), np.float32)
    x = margin
    for cell, gap in cells:
        x = max(0, x)
        span = min(cell.shape[1], width - x)
        ink_map[:, x: x + span] = np.maximum(ink_map[:, x: x + span], cell[:, :span])
        x += cell.shape[1] + gap
    paper = rng.uniform(*PAPER_RANGE)
    ink_level = rng.uniform(*INK_RANGE)
    shade = np.linspace(0.0, rng.uniform(-25, 25), width)[None, :]
    image = paper + shade - ink_map * (paper - ink_level) + rng.normal(0.0, rng.uniform(2, 8), ink_map.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def cutout_strip(image: np.ndarray, rng: np.random.Generator, fill: int | None = None) -> np.ndarray:
    """Table 1's Cutout of a handwriting strip: one rectangle of 10-20 % of its area filled with ``fill`` (default:
    black or white at random).

    :param image: uint8 strip.
    :param rng: random generator.
    :param fill: grey level of the rectangle.
    """
    from vafn_media.corruptions import cutout

    return cutout(image, rng, CUTOUT_FRACTION, int(rng.choice([0, 255])) if fill is None else fill)



def _degraded(waveform: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A training copy of a recorded instruction: telephone band (often with 20 dB white noise) or the random chain of
    :func:`vafn_media.augment.augment`, at SAMPLE_RATE."""
    from vafn_media.augment import PHONE_RATE, augment, resample, telephone
    from vafn_media.corruptions import add_awgn

    if rng.random() >= PHONE_PROBABILITY:
        return augment(waveform, rng)
    phone = telephone(waveform, rng, mu_law=rng.random() < 0.3)
    if rng.random() < PHONE_NOISE_PROBABILITY:
        phone = add_awgn(phone, float(rng.uniform(15.0, 25.0)), rng)
    return resample(phone, PHONE_RATE, SAMPLE_RATE)


def people_training_data(speech_root: str | Path | Sequence[str | Path], handwriting_root: str | Path, split: str,
                         count: int, seed: int, cache_dir: Path, progress: bool = True):
    """Training-ready items (:class:`~vafn_media.dataset.TrainingData`) of real people: instructions said by the
    split's speakers (clean and two degraded copies) and written with the split's glyphs (clean and a Cutout copy),
    cached under ``cache_dir`` by the corpora's file lists, the split, count, seed and this code.

    :param speech_root: the spoken-word corpus folder or folders (:class:`SpokenWords`).
    :param handwriting_root: the MNIST training files (:func:`handwritten_glyphs`).
    :param split: "train" or "selection" ("test" is for the benchmark only).
    :param count: number of instructions.
    :param seed: seed of the instructions, speakers, glyphs and degradations.
    :param cache_dir: where the arrays are stored.
    :param progress: show a progress bar.
    """
    from tqdm import tqdm

    from vafn_media.dataset import AUGMENTED_COPIES, TrainingData, save_items, source_digest, stored_strip
    from vafn_media.features import log_mel

    if split == "test":
        raise ValueError("the test speakers and glyphs are for the benchmark only, never for training")
    words = SpokenWords.read(speech_root, split)
    glyphs = handwritten_glyphs(str(handwriting_root), split)
    files = hashlib.sha1("\n".join(str(p.name) for s in words.speakers.values() for ps in s.values()
                                   for p in ps).encode()).hexdigest()[:10]
    key = f"people-{split}-seed{seed}-n{count}-{files}-{source_digest('people.py', 'features.py', 'augment.py')}"
    path = Path(cache_dir) / f"{key}.npz"
    if not path.exists():
        audio: list[list[np.ndarray]] = [[] for _ in range(1 + AUGMENTED_COPIES)]
        arms_list, clean, masked = [], [], []
        for index in tqdm(range(count), desc=f"people {split} items", unit="item", disable=not progress):
            rng = np.random.default_rng([seed, index])
            length = 0 if rng.random() < EMPTY_PROBABILITY else int(rng.integers(1, MAX_INSTRUCTION_LENGTH + 1))
            arms = tuple(int(a) for a in rng.integers(1, NUM_ARMS + 1, length))
            waveform, _ = say_instruction(words, arms, rng, word_gain_db=WORD_GAIN_DB)
            copies = [waveform] + [_degraded(waveform, rng) for _ in range(AUGMENTED_COPIES)]
            for store, copy in zip(audio, copies):
                store.append(log_mel(copy, SAMPLE_RATE)[0].numpy().astype(np.float16))
            strip = handwriting_strip(glyphs, arms, rng)
            clean.append(stored_strip(strip, arms, None))
            masked.append(stored_strip(cutout_strip(strip, rng), arms, strip))
            arms_list.append(arms)
        save_items(path, arms_list, audio, clean, masked)
    return TrainingData.load([str(path)])
