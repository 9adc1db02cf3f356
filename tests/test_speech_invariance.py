"""benchmarks/speech_invariance.py: the voice-source swap keeps the words, and the probe table is written."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("librosa")
pytest.importorskip("espeakng_loader")


def test_resynthesis_replaces_the_source_but_keeps_what_is_said(load_benchmark):
    from vafn_media import InstructionGenerator
    from vafn_media.augment import resample
    from vafn_media.constants import SAMPLE_RATE
    from vafn_media.evaluation import speech_items

    module = load_benchmark("speech_invariance")
    generator = InstructionGenerator.load()
    pad = np.zeros(SAMPLE_RATE // 4, np.float32)
    read = []
    for i, item in enumerate(speech_items("espeak", 10, module.ITEM_SEED)):  # the benchmark's first ten
        clean = resample(item.waveform, item.sample_rate, SAMPLE_RATE)
        new = module.resynthesise(clean, SAMPLE_RATE, np.random.default_rng([module.ITEM_SEED, i]))
        assert new.shape == clean.shape
        assert np.sqrt(np.mean(new**2)) == pytest.approx(np.sqrt(np.mean(clean**2)), rel=1e-3)
        assert abs(np.corrcoef(new, clean)[0, 1]) < 0.5  # a new waveform, not the old one filtered
        read.append(generator.transcribe(audio=(np.concatenate([pad, new, pad]), SAMPLE_RATE)).arms == item.arms)
    assert sum(read) >= 8, read  # 96 % of 200 in the benchmark


def test_probe_table_is_written(load_benchmark, tmp_path):
    from vafn_media.engines import available_engines

    module = load_benchmark("speech_invariance")
    rows = module.main(["--items", "2", "--out", str(tmp_path / "table.md")])
    espeak = [row for row in rows if row[0].startswith("espeak")]
    word_rows = 1 + len(module.WORD_GAPS_S)  # one sentence, then one word at a time per gap
    tempo_rows = 1 + (shutil.which("sox") is not None)  # phase vocoder, and WSOLA where sox is installed
    assert len(espeak) == 2 + tempo_rows + len(module.PRONUNCIATIONS[1]) + word_rows
    assert all(0 <= row[2] <= 100 for row in rows)
    assert len(rows) == len(espeak) + (11 + tempo_rows + word_rows) * len(available_engines())
    assert "| espeak held-out voices | as synthesised |" in (tmp_path / "table.md").read_text()


def test_words_said_one_at_a_time_are_joined_by_the_gap_and_read(load_benchmark):
    from vafn_media import InstructionGenerator
    from vafn_media.speech import ESPEAK_SAMPLE_RATE, EspeakSynthesizer, Voice, trim_silence

    module = load_benchmark("speech_invariance")
    words = {}

    def say(word: str) -> tuple[np.ndarray, int]:
        words[word] = EspeakSynthesizer.shared().synthesize(word, Voice("en-gb-scotland"))  # a held-out voice
        return words[word], ESPEAK_SAMPLE_RATE

    waveform, rate = module.one_word_at_a_time((2, 3, 1), say, 0.1)
    trimmed = [trim_silence(words[w]) for w in ("two", "three", "one")]
    assert rate == ESPEAK_SAMPLE_RATE and all(len(t) < len(words[w]) for t, w in zip(trimmed, ("two", "three", "one")))
    assert len(waveform) == sum(len(t) for t in trimmed) + 2 * int(0.1 * rate)
    assert np.array_equal(waveform[:len(trimmed[0])], trimmed[0])
    pad = np.zeros(rate // 4, np.float32)
    assert InstructionGenerator.load().transcribe(audio=(np.concatenate([pad, waveform, pad]), rate)).arms == (2, 3, 1)


@pytest.mark.parametrize("method", ["phase_vocoder_stretch", "sox_tempo"])
def test_tempo_probes_shorten_the_clip_and_keep_its_pitch(load_benchmark, method):
    if method == "sox_tempo" and shutil.which("sox") is None:
        pytest.skip("sox is not installed")
    from vafn_media.augment import phase_vocoder_stretch

    module = load_benchmark("speech_invariance")
    rate = 16_000
    t = np.arange(rate) / rate
    tone = (0.3 * np.sin(2 * np.pi * 440.0 * t)).astype(np.float32)
    faster = module.sox_tempo(tone, rate, 0.7) if method == "sox_tempo" else phase_vocoder_stretch(tone, 0.7)
    assert len(faster) == pytest.approx(0.7 * len(tone), rel=0.02)
    spectrum = np.abs(np.fft.rfft(faster * np.hanning(len(faster))))
    assert np.fft.rfftfreq(len(faster), 1 / rate)[np.argmax(spectrum)] == pytest.approx(440.0, abs=5.0)
