"""Waveform degradations that model real recordings: speed, tempo, rooms, noise, telephone, silences, gain and clipping.

Used twice: a random chain (:func:`augment`) makes the training copies of each synthesised utterance, and the named,
seeded evaluation conditions (:data:`CONDITIONS`, :func:`apply_condition`) make the benchmark's degraded rows.
Everything works on float32 mono waveforms at :data:`~vafn_media.constants.SAMPLE_RATE` unless stated otherwise.
"""

from __future__ import annotations

import numpy as np

from vafn_media.constants import SAMPLE_RATE

#: Telephone band (Hz) and rate.
PHONE_BAND: tuple[float, float] = (300.0, 3400.0)
PHONE_RATE: int = 8_000
#: Training ranges of the random chain.
SPEED_RANGE: tuple[float, float] = (0.85, 1.18)
RT60_RANGE: tuple[float, float] = (0.15, 0.9)
SNR_RANGE_DB: tuple[float, float] = (5.0, 30.0)
GAIN_RANGE_DB: tuple[float, float] = (-30.0, 6.0)
MAX_SILENCE_SECONDS: float = 1.0
#: Probabilities of each stage of the random chain.
P_SPEED, P_SILENCE, P_REVERB, P_PHONE, P_NOISE, P_CLIP = 0.5, 0.5, 0.45, 0.3, 0.75, 0.12
NOISE_COLOURS: tuple[str, ...] = ("white", "pink", "brown", "babble")
#: Speaking rates of the pitch-kept tempo change (:func:`random_tempo`); its probability is a training option.
TEMPO_RATE_RANGE: tuple[float, float] = (0.7, 1.5)


def resample(waveform: np.ndarray, rate_in: int, rate_out: int) -> np.ndarray:
    """Band-limited resampling with soxr (float32 out).

    :param waveform: float32 samples.
    :param rate_in: input rate (Hz).
    :param rate_out: output rate (Hz).
    """
    import soxr

    if rate_in == rate_out:
        return np.asarray(waveform, np.float32)
    return soxr.resample(np.asarray(waveform, np.float32), rate_in, rate_out).astype(np.float32, copy=False)


def speed(waveform: np.ndarray, factor: float) -> np.ndarray:
    """Speed perturbation: play ``factor`` times faster (tempo and pitch together, like a tape).

    :param waveform: samples at SAMPLE_RATE.
    :param factor: > 1 faster and higher, < 1 slower and lower.
    """
    return resample(waveform, int(round(SAMPLE_RATE * factor)), SAMPLE_RATE)


def phase_vocoder_stretch(waveform: np.ndarray, stretch: float) -> np.ndarray:
    """``waveform`` at ``stretch`` x its duration with its pitch kept, by librosa's phase vocoder (float32).

    :param waveform: float32 samples.
    :param stretch: duration factor (< 1 is faster).
    """
    import librosa

    return librosa.effects.time_stretch(np.asarray(waveform, np.float32), rate=1.0 / stretch).astype(np.float32)


def random_tempo(waveform: np.ndarray, rng: np.random.Generator, probability: float) -> np.ndarray:
    """With ``probability``, the clip said at a random rate in :data:`TEMPO_RATE_RANGE`, its pitch kept (a tempo
    change, unlike :func:`speed`); otherwise the clip itself, and ``rng`` is not drawn from when ``probability`` is 0.

    :param waveform: samples at SAMPLE_RATE.
    :param rng: random generator of its own (so that other draws do not depend on ``probability``).
    :param probability: chance of a tempo change.
    """
    if probability <= 0 or rng.random() >= probability:
        return waveform
    return phase_vocoder_stretch(waveform, 1.0 / rng.uniform(*TEMPO_RATE_RANGE))


def pad_silence(waveform: np.ndarray, before_s: float, after_s: float) -> np.ndarray:
    """Add leading and trailing digital silence (noise stages later fill it like a real room).

    :param waveform: samples at SAMPLE_RATE.
    :param before_s: seconds before.
    :param after_s: seconds after.
    """
    return np.concatenate([np.zeros(int(before_s * SAMPLE_RATE), np.float32), waveform,
                           np.zeros(int(after_s * SAMPLE_RATE), np.float32)])


def room_impulse(rng: np.random.Generator, rt60: float) -> np.ndarray:
    """A simulated room impulse response: direct path, sparse early reflections, exponentially decaying late tail.

    :param rng: random generator.
    :param rt60: reverberation time (seconds, 60 dB decay).
    """
    length = int(min(1.2, rt60) * SAMPLE_RATE)
    t = np.arange(length) / SAMPLE_RATE
    tail = rng.normal(0.0, 1.0, length) * np.exp(-6.9078 * t / rt60)
    onset = int(rng.uniform(0.002, 0.008) * SAMPLE_RATE)
    tail[:onset] = 0.0
    for _ in range(int(rng.integers(3, 9))):  # early reflections
        k = int(rng.uniform(0.003, 0.04) * SAMPLE_RATE)
        tail[k] += rng.uniform(-0.8, 0.8) * 4.0
    rir = tail * rng.uniform(0.05, 0.3)
    rir[0] = 1.0
    return (rir / np.sqrt(np.sum(rir**2))).astype(np.float32)


def reverberate(waveform: np.ndarray, rir: np.ndarray) -> np.ndarray:
    """Convolve with a room impulse response, keeping the level and the length plus the tail.

    :param waveform: samples at SAMPLE_RATE.
    :param rir: impulse response at SAMPLE_RATE.
    """
    from scipy.signal import fftconvolve

    wet = fftconvolve(waveform, rir)[: len(waveform) + len(rir) // 2]
    scale = np.sqrt(np.mean(waveform**2) / max(np.mean(wet**2), 1e-12))
    return (wet * scale).astype(np.float32)


def telephone(waveform: np.ndarray, rng: np.random.Generator | None = None, mu_law: bool = False) -> np.ndarray:
    """Telephone channel: 300-3400 Hz band, 8 kHz sampling, optional 8-bit mu-law codec; returned at 8 kHz.

    :param waveform: samples at SAMPLE_RATE.
    :param rng: randomises the band edges slightly (None: exact band).
    :param mu_law: quantise with 8-bit mu-law (G.711-like).
    """
    from scipy.signal import butter, sosfilt

    low, high = PHONE_BAND
    if rng is not None:
        low, high = low * rng.uniform(0.7, 1.3), high * rng.uniform(0.9, 1.05)
    sos = butter(4, [low, high], btype="bandpass", fs=SAMPLE_RATE, output="sos")
    narrow = resample(sosfilt(sos, waveform).astype(np.float32), SAMPLE_RATE, PHONE_RATE)
    if mu_law:
        peak = max(float(np.abs(narrow).max()), 1e-6)
        x = np.clip(narrow / peak, -1, 1)
        y = np.sign(x) * np.log1p(255 * np.abs(x)) / np.log1p(255)
        y = np.round(y * 127) / 127
        narrow = (np.sign(y) * np.expm1(np.abs(y) * np.log1p(255)) / 255 * peak).astype(np.float32)
    return narrow.astype(np.float32)


def coloured_noise(rng: np.random.Generator, length: int, colour: str) -> np.ndarray:
    """Unit-power noise of a colour: white, pink (1/f), brown (1/f^2) or babble-like (speech-shaped, modulated).

    :param rng: random generator.
    :param length: samples.
    :param colour: one of :data:`NOISE_COLOURS`.
    """
    if colour not in NOISE_COLOURS:
        raise ValueError(f"unknown noise colour {colour!r}; choose from {NOISE_COLOURS}")
    white = rng.normal(0.0, 1.0, length)
    if colour == "white":
        noise = white
    else:
        spectrum = np.fft.rfft(white)
        f = np.maximum(np.fft.rfftfreq(length, 1.0 / SAMPLE_RATE), 20.0)
        if colour == "pink":
            spectrum /= np.sqrt(f)
        elif colour == "brown":
            spectrum /= f
        else:  # babble: speech-shaped spectrum (peak near 500 Hz) with a slow syllabic amplitude modulation
            spectrum *= np.exp(-0.5 * (np.log(f / 500.0) / 0.8) ** 2)
        noise = np.fft.irfft(spectrum, length)
        if colour == "babble":
            t = np.arange(length) / SAMPLE_RATE
            noise *= 1.0 + 0.6 * np.sin(2 * np.pi * rng.uniform(2.0, 5.0) * t + rng.uniform(0, 2 * np.pi))
    return (noise / max(np.sqrt(np.mean(noise**2)), 1e-12)).astype(np.float32)


def add_noise(waveform: np.ndarray, snr_db: float, rng: np.random.Generator, colour: str = "white") -> np.ndarray:
    """Add noise at ``snr_db`` relative to the clip's power (silences included, as in the Table-1 convention).

    :param waveform: samples.
    :param snr_db: signal-to-noise ratio in dB.
    :param rng: random generator.
    :param colour: noise colour.
    """
    power = float(np.mean(np.square(waveform, dtype=np.float64)))
    noise = coloured_noise(rng, len(waveform), colour) * np.sqrt(power / 10 ** (snr_db / 10))
    return (waveform + noise).astype(np.float32)


def gain_clip(waveform: np.ndarray, gain_db: float, clip: bool) -> np.ndarray:
    """Scale by ``gain_db`` relative to a 0.5 peak; with ``clip``, drive 2-4x into saturation and hard-clip.

    :param waveform: samples.
    :param gain_db: gain in dB.
    :param clip: overdrive and clip at full scale.
    """
    peak = max(float(np.abs(waveform).max()), 1e-9)
    out = waveform * (0.5 / peak) * 10 ** (gain_db / 20)
    if clip:
        out = np.clip(out * 3.0, -1.0, 1.0)
    return np.clip(out, -1.0, 1.0).astype(np.float32)


def augment(waveform: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The random training chain; returns float32 at SAMPLE_RATE.

    :param waveform: clean samples at SAMPLE_RATE.
    :param rng: random generator (one per item and copy, for reproducibility).
    """
    x = np.asarray(waveform, np.float32)
    if rng.random() < P_SPEED:
        x = speed(x, rng.uniform(*SPEED_RANGE))
    if rng.random() < P_SILENCE:
        x = pad_silence(x, rng.uniform(0, MAX_SILENCE_SECONDS), rng.uniform(0, MAX_SILENCE_SECONDS))
    if rng.random() < P_REVERB:
        x = reverberate(x, room_impulse(rng, rng.uniform(*RT60_RANGE)))
    if rng.random() < P_NOISE:
        x = add_noise(x, rng.uniform(*SNR_RANGE_DB), rng, NOISE_COLOURS[int(rng.integers(len(NOISE_COLOURS)))])
    if rng.random() < P_PHONE:
        x = resample(telephone(x, rng, mu_law=rng.random() < 0.5), PHONE_RATE, SAMPLE_RATE)
    return gain_clip(x, rng.uniform(*GAIN_RANGE_DB), rng.random() < P_CLIP)


#: Named evaluation conditions of the benchmark (never used for training draws: they are fixed settings).
CONDITIONS: tuple[str, ...] = ("clean", "8 kHz", "reverb", "10 dB noise", "fast")
#: Settings of the evaluation conditions.
EVAL_RT60: float = 0.6
EVAL_SNR_DB: float = 10.0
FAST_FACTOR: float = 1.3


def apply_condition(waveform: np.ndarray, sample_rate: int, condition: str,
                    rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Degrade a clean clip for an evaluation condition; returns (waveform, rate).

    "8 kHz" returns telephone-band audio *at 8 kHz* (the reader must accept it); "fast" is a tempo-only change
    made by the speech engine when it can (see the benchmark), else a 1.3x speed-up here.

    :param waveform: clean samples.
    :param sample_rate: their rate.
    :param condition: one of :data:`CONDITIONS`.
    :param rng: random generator (noise, room).
    """
    if condition not in CONDITIONS:
        raise ValueError(f"unknown condition {condition!r}; choose from {CONDITIONS}")
    x = resample(waveform, sample_rate, SAMPLE_RATE)
    if condition == "clean":
        return x, SAMPLE_RATE
    if condition == "8 kHz":
        return telephone(x), PHONE_RATE
    if condition == "reverb":
        return reverberate(x, room_impulse(rng, EVAL_RT60)), SAMPLE_RATE
    if condition == "10 dB noise":
        return add_noise(x, EVAL_SNR_DB, rng, "white"), SAMPLE_RATE
    return speed(x, FAST_FACTOR), SAMPLE_RATE
