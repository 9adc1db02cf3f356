"""benchmarks/speech_invariance.py: the voice-source swap keeps the words, and the probe table is written."""

from __future__ import annotations

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
    assert len(espeak) == 2 + len(module.PRONUNCIATIONS[1]) and all(0 <= row[2] <= 100 for row in rows)
    assert len(rows) == len(espeak) + 11 * len(available_engines())
    assert "| espeak held-out voices | as synthesised |" in (tmp_path / "table.md").read_text()
