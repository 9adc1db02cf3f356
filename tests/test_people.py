"""Real people's corpora (vafn_media.people): speaker splits, spoken instructions, MNIST glyphs, training items."""

from __future__ import annotations

import gzip
import wave
from pathlib import Path

import numpy as np
import pytest

from vafn_media.people import (GLYPH_SPLITS, WORDS, SpokenWords, handwriting_strip, handwritten_glyphs,
                               people_training_data, say_instruction, speaker_split, word_span)

RATE = 16_000


def _write_wav(path: Path, samples: np.ndarray, rate: int = RATE) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with wave.open(str(path), "wb") as handle:
        handle.setnchannels(1)
        handle.setsampwidth(2)
        handle.setframerate(rate)
        handle.writeframes((np.clip(samples, -1, 1) * 32767).astype(np.int16).tobytes())


def _word(arm: int, rng: np.random.Generator) -> np.ndarray:
    """One second: silence, a tone burst whose pitch names the arm, silence (a stand-in for a recorded word)."""
    t = np.arange(int(0.3 * RATE)) / RATE
    burst = 0.5 * np.sin(2 * np.pi * 200 * arm * t) * np.hanning(len(t))
    quiet = rng.normal(0, 1e-4, RATE).astype(np.float32)
    quiet[RATE // 3: RATE // 3 + len(t)] += burst
    return quiet


def _speakers(split: str, count: int) -> list[str]:
    found, k = [], 0
    while len(found) < count:
        name = f"{k:08x}"
        if speaker_split(name) == split:
            found.append(name)
        k += 1
    return found


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("words")
    rng = np.random.default_rng(0)
    for split in ("train", "selection", "test"):
        for speaker in _speakers(split, 3):
            for arm, word in WORDS.items():
                _write_wav(root / word / f"{speaker}_nohash_0.wav", _word(arm, rng))
    return root


@pytest.fixture(scope="module")
def mnist(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("mnist")
    count = GLYPH_SPLITS["test"][1]
    labels = (np.arange(count) % 4).astype(np.uint8)  # 0 (never an arm), 1, 2, 3
    images = np.zeros((count, 28, 28), np.uint8)
    images[:, 6:22, 12:16] = 255  # a vertical bar
    header = (2051).to_bytes(4, "big") + b"".join(n.to_bytes(4, "big") for n in (count, 28, 28))
    with gzip.open(root / "train-images-idx3-ubyte.gz", "wb") as handle:
        handle.write(header + images.tobytes())
    (root / "train-labels-idx1-ubyte").write_bytes((2049).to_bytes(4, "big") + count.to_bytes(4, "big")
                                                   + labels.tobytes())
    return root


def test_speaker_split_is_stable_and_covers_every_split():
    names = [f"{k:08x}" for k in range(2000)]
    splits = [speaker_split(n) for n in names]
    assert splits == [speaker_split(n) for n in names]
    shares = {s: splits.count(s) / len(names) for s in ("train", "selection", "test")}
    assert 0.6 < shares["train"] < 0.8 and 0.05 < shares["selection"] < 0.15 and 0.15 < shares["test"] < 0.25


def test_spoken_words_keep_only_their_split(corpus):
    for split in ("train", "selection", "test"):
        words = SpokenWords.read(corpus, split)
        assert words.complete_speakers() == sorted(words.speakers)
        assert all(speaker_split(s) == split for s in words.speakers) and words.clips() == 9


def test_training_words_get_their_own_level(corpus):
    words = SpokenWords.read(corpus, "train")
    speaker = sorted(words.speakers)[0]
    plain, _ = say_instruction(words, (1, 1, 1, 1), np.random.default_rng(3), speaker)
    varied, _ = say_instruction(words, (1, 1, 1, 1), np.random.default_rng(3), speaker, word_gain_db=12.0)

    def word_peaks(waveform):
        frames = np.abs(waveform[: len(waveform) // 160 * 160]).reshape(-1, 160).max(axis=1)
        loud = np.flatnonzero(frames > 0.01)
        return [frames[run].max() for run in np.split(loud, np.flatnonzero(np.diff(loud) > 1) + 1)]

    assert len(word_peaks(plain)) == len(word_peaks(varied)) == 4
    assert np.ptp(word_peaks(plain)) < 0.01 * max(word_peaks(plain))  # the same word at the same level
    assert 20 * np.log10(max(word_peaks(varied)) / min(word_peaks(varied))) > 3.0


def test_spoken_words_pool_several_corpora(corpus, tmp_path):
    more = tmp_path / "more"
    speaker = _speakers("train", 4)[-1]  # a train speaker the first corpus does not have
    for arm, word in WORDS.items():
        _write_wav(more / word / f"{speaker}_nohash_0.wav", _word(arm, np.random.default_rng(arm)))
    _write_wav(more / "one" / f"{_speakers('train', 1)[0]}_nohash_0.wav", np.zeros(RATE))  # already in the first
    pooled = SpokenWords.read([corpus, more], "train")
    assert speaker in pooled.speakers and pooled.clips() == 12
    assert all(p.parent.parent == corpus for p in pooled.speakers[_speakers("train", 1)[0]][1])
    with pytest.raises(ValueError, match="no spoken-word corpus"):
        SpokenWords.read([], "train")


def test_spoken_words_reject_a_folder_that_is_not_a_corpus(tmp_path):
    with pytest.raises(ValueError, match="no folder one, two, three"):
        SpokenWords.read(tmp_path, "train")
    with pytest.raises(ValueError, match="unknown split"):
        SpokenWords.read(tmp_path, "validation")


def test_said_instruction_has_one_burst_per_word(corpus):
    words = SpokenWords.read(corpus, "train")
    waveform, speaker = say_instruction(words, (2, 3, 1, 3), np.random.default_rng(1))
    assert speaker in words.speakers
    frames = np.abs(waveform[: len(waveform) // 160 * 160]).reshape(-1, 160).max(axis=1)
    loud = np.concatenate([[0], (frames > 0.05).astype(int)])
    assert np.count_nonzero(np.diff(loud) == 1) == 4  # four separate bursts
    with pytest.raises(ValueError, match="not in the train split"):
        say_instruction(words, (1,), np.random.default_rng(1), speaker="nobody")


def test_word_span_cuts_the_silence_around_a_word():
    word = _word(2, np.random.default_rng(0))
    span = word_span(word, RATE)
    assert 0.3 <= (span.stop - span.start) / RATE <= 0.45 and span.start > 0.2 * RATE


def test_handwritten_glyphs_by_index_split(mnist, tmp_path):
    pools = {split: handwritten_glyphs(str(mnist), split) for split in GLYPH_SPLITS}
    for split, (start, stop) in GLYPH_SPLITS.items():
        assert sum(len(g) for g in pools[split].values()) == 3 * (stop - start) // 4
    strip = handwriting_strip(pools["test"], (1, 2, 3), np.random.default_rng(0))
    assert strip.dtype == np.uint8 and strip.shape[1] > strip.shape[0]
    assert strip.mean() > 128  # dark ink on light paper
    (tmp_path / "train-images-idx3-ubyte").write_bytes(b"<html>not mnist</html>")
    (tmp_path / "train-labels-idx1-ubyte").write_bytes(b"<html>not mnist</html>")
    with pytest.raises(ValueError, match="not an MNIST idx file"):
        handwritten_glyphs(str(tmp_path), "train")


def test_people_training_items_are_cached_and_never_from_the_test_split(corpus, mnist, tmp_path):
    data = people_training_data(corpus, mnist, "train", 12, seed=0, cache_dir=tmp_path, progress=False)
    assert len(data) == 12 and len(data.augmented_audio) == 2 and len(data.clean) == 12
    assert all(f.shape[0] == 40 for f in data.clean_audio)
    again = people_training_data(corpus, mnist, "train", 12, seed=0, cache_dir=tmp_path, progress=False)
    assert np.array_equal(data.arms, again.arms) and len(list(tmp_path.glob("*.npz"))) == 1
    with pytest.raises(ValueError, match="benchmark only"):
        people_training_data(corpus, mnist, "test", 12, seed=0, cache_dir=tmp_path, progress=False)


def test_a_mask_over_a_digit_is_found_painted_over_and_its_columns_returned():
    from vafn_media.images import find_mask, read_strip, to_gray

    glyphs = {arm: (np.pad(np.ones((20, 6), np.float32), ((0, 0), (7, 7))),) for arm in (1, 2, 3)}
    strip = handwriting_strip(glyphs, (1, 2, 3), np.random.default_rng(3))
    assert find_mask(to_gray(strip)) is None and read_strip(strip)[1] is None
    masked = strip.copy()
    height, width = strip.shape
    masked[:, width // 2 - height // 3: width // 2 + height // 3] = 0  # a black block over the middle digit
    top, bottom, left, right = find_mask(to_gray(masked))
    assert (top, bottom) == (0, height) and right - left == 2 * (height // 3)
    canonical, hidden = read_strip(masked)
    assert hidden is not None and 0 < hidden[0] < hidden[1] < canonical.shape[1]
    assert canonical[:, hidden[0]:hidden[1]].max() < 0.3  # painted with the paper, not read as a block of ink
    thin = strip.copy()
    thin[height // 2 - 1: height // 2 + 2, :] = 0  # a thin bar: every digit still shows
    assert read_strip(thin)[1] is None


def test_saturated_paper_is_not_a_mask():
    from vafn_media.images import find_mask

    card = np.full((40, 200), 255, np.uint8)
    card[10:30, 20:26] = 0
    card[10:30, 80:86] = 0
    assert find_mask(card.astype(np.float32)) is None


def test_hidden_frames_read_as_blank_and_weigh_nothing():
    import torch

    from vafn_media.decoding import greedy_decode, sequence_log_likelihood

    logits = torch.full((12, 4), -5.0)
    logits[:, 0] = 5.0
    logits[2, 1] = logits[6, 2] = logits[10, 3] = 10.0  # reads 1, 2, 3
    phi = torch.zeros(12, 8)
    assert greedy_decode(phi, logits).arms == [1, 2, 3]
    hidden = greedy_decode(phi, logits, hidden=(5, 8))
    assert hidden.arms == [1, 3] and hidden.masked == (5, 8)
    # under the mask, the sequence with and without the hidden digit are equally likely to within the blank frames
    with_digit = sequence_log_likelihood(hidden.log_probs, [1, 2, 3])
    assert with_digit > sequence_log_likelihood(greedy_decode(phi, logits).log_probs, [1, 3])


def test_audio_fills_the_digit_a_cutout_hides_without_a_disagreement_flag():
    from vafn_media.generator import InstructionGenerator
    from vafn_media.images import read_strip
    from vafn_media.speech import ESPEAK_SAMPLE_RATE, speak
    from vafn_media.strips import render_strip

    generator = InstructionGenerator.load()
    arms = (2, 3, 1)
    card = render_strip(arms, np.random.default_rng(5))
    rows, cols = np.nonzero(np.abs(card.astype(float) - np.median(card)) > 60)
    middle = (cols.min() + cols.max()) // 2
    half = (cols.max() - cols.min()) // 6
    masked = card.copy()
    masked[:, middle - half: middle + half] = 0 if np.median(card) > 128 else 255  # hides the middle digit
    assert read_strip(masked)[1] is not None
    alone = generator.transcribe(image=masked)
    assert alone.low_confidence and any("masked" in w for w in alone.warnings)
    both = generator.transcribe(audio=(speak(arms), ESPEAK_SAMPLE_RATE), image=masked)
    assert both.arms == arms
    assert not any("disagree" in w for w in both.warnings)


def test_training_command_keeps_no_machine_path_of_any_corpus():
    from vafn_media.train import without_machine_paths

    argv = ["--people-speech", "/data/sc", "/home/me/more", "--steps", "5", "--init=/x/model.pt"]
    assert without_machine_paths(argv) == ["--people-speech", "<sc>", "<more>", "--steps", "5", "--init=<model.pt>"]
