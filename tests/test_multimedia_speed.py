"""The faster audio path of the reader computes what the plain one computes (vafn_media features, encoder, transcribe).

The single-clip features, the per-frame speech statistics and the module-free audio encoder were rewritten for speed;
these tests pin them to the straightforward code they replace: bit for bit where the same kernels run, within float
rounding where the old path went through oneDNN (long clips).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("librosa")
pytest.importorskip("soxr")

from vafn_media.constants import N_MELS, SAMPLE_RATE  # noqa: E402

torch.set_num_threads(1)


def _signal(seconds: float, seed: int = 0) -> np.ndarray:
    """A fixed speech-like test signal: a gliding harmonic tone with on/off bursts, plus a little noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * SAMPLE_RATE)) / SAMPLE_RATE
    pitch = 120 + 40 * np.sin(2 * np.pi * 0.7 * t)
    phase = 2 * np.pi * np.cumsum(pitch) / SAMPLE_RATE
    voiced = sum(np.sin(k * phase) / k for k in range(1, 8)) * (np.sin(2 * np.pi * 2.5 * t) > 0)
    return (0.2 * voiced + 0.01 * rng.normal(size=t.size)).astype(np.float32)


def _frame_stats_reference(waveform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The per-frame level and flatness as first written (window, bins and mask rebuilt on every call)."""
    from vafn_media.audio import _FLATNESS_BAND, _FRAME_SECONDS

    size = int(_FRAME_SECONDS * SAMPLE_RATE)
    count = max(1, len(waveform) // size)
    frames = np.resize(waveform, count * size).reshape(count, size) if len(waveform) >= size else waveform[None]
    power = np.mean(np.square(frames, dtype=np.float64), axis=1)
    spectrum = np.abs(np.fft.rfft(frames * np.hanning(frames.shape[1]), axis=1)) ** 2 + 1e-20
    hz = np.fft.rfftfreq(frames.shape[1], 1.0 / SAMPLE_RATE)
    spectrum = spectrum[:, (hz >= _FLATNESS_BAND[0]) & (hz <= _FLATNESS_BAND[1])]
    flatness = np.exp(np.mean(np.log(spectrum), axis=1)) / np.mean(spectrum, axis=1)
    return 10 * np.log10(power + 1e-20), flatness


@pytest.mark.parametrize("seconds", [0.0125, 0.3, 2.0, 7.3])
def test_frame_stats_equal_the_reference_bit_for_bit(seconds):
    from vafn_media.audio import _frame_flatness, _frame_levels, _frames

    waveform = _signal(seconds, seed=int(seconds * 10))
    frames = _frames(waveform)
    for got, want in zip((_frame_levels(frames), _frame_flatness(frames)), _frame_stats_reference(waveform)):
        assert np.array_equal(got, want)


def test_percentiles_equal_numpy_bit_for_bit():
    from vafn_media.audio import _percentiles

    rng = np.random.default_rng(0)
    for size in list(range(1, 40)) + [99, 100, 101, 270, 1000]:
        for values in (rng.normal(-40, 15, size), np.round(rng.normal(0, 3, size)), np.full(size, -200.0)):
            for percents in ((10, 95), (10,), (0, 50, 100), (12.5, 99.9)):
                want = np.percentile(values, percents)
                assert np.array_equal(_percentiles(values, percents), want), (size, percents)


def test_the_floor_of_at_peak_leaves_the_features_unchanged():
    """at_peak zeroes the low cut's ringing over digital silence far below the peak; the features stay the same."""
    from vafn_media.constants import READ_PEAK
    from vafn_media.features import at_peak, log_mel, low_cut

    waveform = np.concatenate([np.zeros(SAMPLE_RATE // 4, np.float32), _signal(1.0), np.zeros(SAMPLE_RATE // 2,
                                                                                               np.float32)])
    filtered = low_cut(waveform, SAMPLE_RATE)
    floored = at_peak(filtered)
    plain = (filtered * (READ_PEAK / float(np.abs(filtered).max()))).astype(np.float32)
    assert np.count_nonzero(floored != plain) > 1000  # the ringing's tail is gone ...
    assert np.array_equal(floored[np.abs(plain) > READ_PEAK * 1e-10], plain[np.abs(plain) > READ_PEAK * 1e-10])
    assert torch.equal(log_mel(floored, SAMPLE_RATE), log_mel(plain, SAMPLE_RATE))  # ... and the features are equal


@pytest.mark.parametrize("rate", [SAMPLE_RATE, 8_000, 44_100])
def test_single_clip_features_equal_the_batch_path_and_librosa(rate):
    """log_mel (one clip, no mask) == log_mel_batch of a batch of one, bit for bit; both == librosa's log-mel."""
    import librosa

    from vafn_media.features import frame_params, log_mel, log_mel_batch, mel_filterbank
    from vafn_media.constants import LOG_EPS

    waveform = _signal(3.1, seed=rate)
    if rate != SAMPLE_RATE:
        import soxr

        waveform = soxr.resample(waveform, SAMPLE_RATE, rate).astype(np.float32)
    single = log_mel(waveform, rate)
    tensor = torch.from_numpy(waveform)[None]
    batch, frames = log_mel_batch(tensor, torch.tensor([waveform.size]), rate)
    assert single.shape == batch.shape == (1, N_MELS, int(frames[0]))
    assert torch.equal(single, batch)
    # an independent computation: librosa's power spectrogram, the same filterbank, the same normalisation
    n_fft, win, hop = frame_params(rate)
    power = np.abs(librosa.stft(waveform.astype(np.float64), n_fft=n_fft, hop_length=hop, win_length=win,
                                window="hann", center=True, pad_mode="constant")) ** 2
    logmel = np.log(mel_filterbank(rate)[0].numpy().astype(np.float64) @ power + LOG_EPS)
    reference = (logmel - logmel.mean(-1, keepdims=True)) / np.sqrt(logmel.var(-1, keepdims=True) + 1e-5)
    assert np.abs(single[0].numpy() - reference).max() < 2e-3


def _folded_model():
    from vafn_media.model import InstructionModel, fold_batchnorm

    torch.manual_seed(0)
    model = InstructionModel()
    model.train()
    with torch.no_grad():  # non-trivial BatchNorm statistics, so folding matters
        for _ in range(3):
            model.encode("audio", torch.randn(4, N_MELS, 60) * 3 + 1, torch.tensor([60] * 4))
    return model.eval(), fold_batchnorm(model.eval())


def test_audio_inference_equals_model_encode():
    """Within float rounding: 1e-5 while model.encode uses the native kernels (short clips; bit for bit on some CPUs,
    about 1e-6 apart on others), 1e-4 for long clips, where model.encode goes through oneDNN."""
    from vafn_media.model import AudioInference

    unfolded, folded = _folded_model()
    assert AudioInference.build(unfolded) is None  # BatchNorm left in: the caller falls back to model.encode
    fast = AudioInference.build(folded)
    assert fast is not None
    with torch.inference_mode():
        # up to 426 frames no convolution input exceeds 20,480 values (oneDNN's threshold for a batch of one)
        for frames, atol in ((7, 1e-5), (100, 1e-5), (426, 1e-5), (513, 1e-4), (900, 1e-4)):
            features = torch.randn(1, N_MELS, frames)
            want, _ = folded.encode("audio", features, torch.tensor([frames]))
            got = fast(features)
            assert got.shape == want.shape
            assert torch.allclose(got, want, rtol=0, atol=atol), frames


def test_dilated_convolutions_by_phases_equal_the_dilated_kernel():
    """AudioInference runs a dilated convolution as undilated ones of the input's phases: the same numbers within float
    rounding at every length (bit for bit on some CPUs; a length up to the dilation goes to the dilated kernel)."""
    from vafn_media.model import _NATIVE_DILATED2D, AudioInference

    torch.manual_seed(0)
    with torch.inference_mode():
        for dilation in (2, 4):
            spec = AudioInference._conv_spec(torch.nn.Conv1d(96, 96, 3, padding=dilation, dilation=dilation))
            for batch, length in [(1, n) for n in range(1, 300)] + [(2, 37), (3, 130)]:
                x = torch.randn(batch, 96, length)
                want = _NATIVE_DILATED2D(x[:, :, None, :], spec[1], (1, 3), spec[2], (1, 1), (0, dilation),
                                         (1, dilation))[:, :, 0]
                assert torch.allclose(AudioInference._conv(x, spec), want, rtol=0, atol=1e-5), (dilation, batch, length)


@pytest.fixture(scope="module")
def generator():
    from vafn_media import InstructionGenerator

    return InstructionGenerator.load()


def test_transcribe_reads_the_same_with_and_without_the_fast_encoder(generator):
    """Spoken instructions of 1-10 arm ids and a 12 s one: same arm ids, flags and warnings, confidences within 1e-5."""
    pytest.importorskip("espeakng_loader")
    import copy

    from vafn_media.audio import load_audio
    from vafn_media.speech import ESPEAK_SAMPLE_RATE, sample_voice, speak

    assert generator._audio_inference is not None
    plain = copy.copy(generator)
    plain._audio_inference = None
    rng = np.random.default_rng(7)
    clips = []
    for length in range(1, 11):
        arms = [int(a) for a in rng.integers(1, 4, length)]
        clips.append(speak(arms, sample_voice(rng, heldout=True), int(rng.integers(3))))
    clips.append(np.concatenate([clips[-1], clips[-2]]))  # about 12 s: the old path takes oneDNN there
    for clip in clips:
        fast, slow = (g.transcribe(audio=(clip, ESPEAK_SAMPLE_RATE)) for g in (generator, plain))
        assert fast.arms == slow.arms and fast.low_confidence == slow.low_confidence
        assert fast.warnings == slow.warnings and fast.method == slow.method
        assert abs(fast.confidence - slow.confidence) <= 1e-5
        assert np.allclose(fast.confidences, slow.confidences, rtol=0, atol=1e-5)
        waveform = load_audio((clip, ESPEAK_SAMPLE_RATE)).waveform
        phi_fast = generator.encode_audio(waveform, SAMPLE_RATE)
        phi_slow = plain.encode_audio(waveform, SAMPLE_RATE)
        assert torch.allclose(phi_fast, phi_slow, atol=1e-4)
