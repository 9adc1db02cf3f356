"""Live commands: audio sources, Silero VAD segmentation, the listener into a MultimediaStream, vafn-demo --listen."""

from __future__ import annotations

import io
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("silero_vad")
pytest.importorskip("soxr")
pytest.importorskip("librosa")

from vafn_media import listen as live  # noqa: E402

#: Commands of the made-up recording, and the silences before each (s); espeak-ng's default voice.
COMMANDS = ((2, 3, 1), (1,), (3, 2))
GAPS_S = (0.6, 1.2, 0.7)


@pytest.fixture(scope="module")
def recording() -> tuple[np.ndarray, int, list[tuple[float, float]]]:
    """Three spoken commands at espeak-ng's 22.05 kHz between silences, with where each command's sound lies."""
    pytest.importorskip("espeakng_loader")
    from vafn_media.speech import ESPEAK_SAMPLE_RATE, speak, trim_silence

    parts, spans, at = [], [], 0
    for arms, gap in zip(COMMANDS, GAPS_S):
        clip = trim_silence(speak(arms, template=0))
        parts += [np.zeros(int(gap * ESPEAK_SAMPLE_RATE), np.float32), clip]
        at += int(gap * ESPEAK_SAMPLE_RATE)
        spans.append((at / ESPEAK_SAMPLE_RATE, (at + len(clip)) / ESPEAK_SAMPLE_RATE))
        at += len(clip)
    parts.append(np.zeros(int(0.8 * ESPEAK_SAMPLE_RATE), np.float32))
    return np.concatenate(parts), ESPEAK_SAMPLE_RATE, spans


@pytest.fixture(scope="module")
def generator():
    from vafn_media import InstructionGenerator

    return InstructionGenerator.load()  # warmed up: the first reading is not slower than the others


def test_segmenter_finds_each_command_once_in_order(recording) -> None:
    waveform, rate, spans = recording
    listener = live.Listener(live.RecordingSource((waveform, rate)))  # 22.05 kHz: resampled to the VAD's 16 kHz
    utterances = listener.run()
    assert listener.errors == []
    assert len(utterances) == len(COMMANDS), [(u.start_s, u.end_s) for u in utterances]
    for utterance, (start, end) in zip(utterances, spans):
        assert abs(utterance.start_s - start) < 0.15 and abs(utterance.end_s - end) < 0.2
        assert utterance.detected_s - utterance.end_s == pytest.approx(0.4, abs=0.04)  # the default minimum silence
        # the pre-roll keeps the onset: the clip starts before the speech, and holds all of it
        assert len(utterance.waveform) / utterance.rate >= utterance.detected_s - utterance.start_s + 0.15


def test_listen_enqueues_each_command_with_its_end_of_speech_latency(recording, generator) -> None:
    from vafn_gym.queue import InstructionQueue
    from vafn_media import MultimediaStream

    waveform, rate, _ = recording
    instruction_queue = InstructionQueue(capacity=16)
    with MultimediaStream(instruction_queue, generator) as stream:
        listener = live.listen(stream, live.RecordingSource((waveform, rate)), background=False)
        assert stream.wait(10.0)
    entries = instruction_queue.snapshot()
    assert [entry.instruction.arms for entry in entries] == list(COMMANDS), stream.events
    assert [entry.metadata["utterance"] for entry in entries] == [0, 1, 2]
    assert sorted(listener.results.values()) == [event.ticket for event in stream.events]
    for entry in entries:
        latency = live.end_of_speech_latency(entry.metadata)
        # fed faster than real time: the 0.4 s of silence heard after the speech, plus reading and enqueueing
        assert 0.4 <= latency < 0.4 + 1.0, latency
    assert np.isnan(live.end_of_speech_latency({"latency_s": 0.1}))


def test_noise_alone_triggers_nothing() -> None:
    rng = np.random.default_rng(0)
    seconds = 12
    white = rng.normal(0, 0.02, seconds * 16_000).astype(np.float32)
    hum = (0.05 * np.sin(2 * np.pi * 50 * np.arange(seconds * 16_000) / 16_000)).astype(np.float32)
    for noise in (white, white + hum):
        listener = live.Listener(live.RecordingSource((noise, 16_000)))
        assert len(listener.run()) <= 1
        assert listener.errors == []


class _Trickle(io.RawIOBase):
    """A pipe that hands out at most ``step`` bytes per read, like stdin fed by another program."""

    def __init__(self, data: bytes, step: int = 777) -> None:
        self.data, self.step = data, step

    def readable(self) -> bool:
        return True

    def read(self, size: int = -1) -> bytes:
        n = self.step if size < 0 else min(size, self.step)
        piece, self.data = self.data[:n], self.data[n:]
        return piece


def test_stdin_pcm_gives_the_same_utterances(recording, monkeypatch: pytest.MonkeyPatch) -> None:
    from vafn_media.augment import resample

    waveform, rate, _ = recording
    pcm = (np.clip(resample(waveform, rate, 16_000), -1, 1) * 32767).astype("<i2").tobytes() + b"\x01"  # odd byte
    from_float = live.Listener(live.RecordingSource((resample(waveform, rate, 16_000), 16_000))).run()
    from_pcm = live.Listener(live.PcmSource(_Trickle(pcm), rate=16_000)).run()
    assert [round(u.start_s, 2) for u in from_pcm] == [round(u.start_s, 2) for u in from_float]
    assert len(from_pcm) == len(COMMANDS)
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(pcm)))
    source = live.open_source("-")
    assert isinstance(source, live.PcmSource) and len(live.Listener(source).run()) == len(COMMANDS)


def test_a_bad_chunk_or_callback_does_not_stop_listening(recording) -> None:
    waveform, rate, _ = recording

    class Faulty(live.RecordingSource):
        def chunks(self):
            for index, chunk in enumerate(super().chunks()):
                yield np.full(8, np.nan, np.float32) if index == 5 else chunk

    def on_utterance(utterance: live.Utterance) -> None:
        if utterance.index == 0:
            raise RuntimeError("downstream is full")

    listener = live.Listener(Faulty((waveform, rate)), on_utterance)
    assert len(listener.run()) == len(COMMANDS)
    assert len(listener.errors) == 2, listener.errors
    assert "NaN" in listener.errors[0] and "downstream is full" in listener.errors[1]


def test_missing_sounddevice_is_one_clear_line(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "sounddevice", None)  # import sounddevice -> ImportError
    with pytest.raises(live.LiveInputError, match="sounddevice.*libportaudio2"):
        live.open_source(None)
    with pytest.raises(live.LiveInputError, match="no such file"):
        live.open_source(str(tmp_path / "missing.wav"))
    from vafn_app import demo

    assert demo.main(["--listen", "--out", str(tmp_path)]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 1 and errors[0].startswith("vafn-demo: error: ") and "sounddevice" in errors[0], errors


def test_demo_listen_file_drives_the_arms(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("espeakng_loader")
    import soundfile

    from vafn_media.speech import ESPEAK_SAMPLE_RATE, speak
    from vafn_app import demo

    silence = np.zeros(int(0.5 * ESPEAK_SAMPLE_RATE), np.float32)
    path = tmp_path / "spoken.wav"
    soundfile.write(path, np.concatenate([silence, speak((2,)), silence, speak((3, 1)), silence]),
                    ESPEAK_SAMPLE_RATE)
    status = demo.main(["--listen", str(path), "--out", str(tmp_path / "run"), "--video", "none",
                        "--max-steps", "600"])
    out = capsys.readouterr().out
    rows = (tmp_path / "run" / "outcomes.csv").read_text().splitlines()
    assert len(rows) == 3, out
    assert "[2]" in out and "[3,1]" in out, out
    assert status == 0, out
