"""Speech engines other than espeak-ng's own voices, used only to *evaluate* the reader on voices it never trained on.

Nothing here is used for training. Each engine is an external program found on ``PATH`` (Debian's ``flite``; the
``espeak-ng`` program with the ``mbrola-us2`` voice, which ``vafn_media.train --mbrola-probability`` keeps out of
training; ``pico2wave`` with the ``en-GB`` voice, which ``--pico-probability`` keeps out of training);
:func:`available_engines` lists the ones present, and callers skip the others.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

#: flite voices that read arbitrary text (``awb_time`` only speaks times of day); ``kal`` synthesises at 8 kHz.
FLITE_VOICES: tuple[str, ...] = ("slt", "rms", "awb", "kal16", "kal")
#: MBROLA's voice directory (Debian's ``mbrola-<voice>`` packages).
MBROLA_DIR = Path("/usr/share/mbrola")


def engine_voices(engine: str) -> tuple[str, ...]:
    """The voices an evaluation engine speaks with, in the order items cycle through them."""
    from vafn_media.speech import MBROLA_HELDOUT_VOICES, PICO_HELDOUT_VOICES

    voices = {"flite": FLITE_VOICES, "mbrola": MBROLA_HELDOUT_VOICES, "pico": PICO_HELDOUT_VOICES}
    if engine not in voices:
        raise ValueError(f"unknown evaluation engine {engine!r}; choose from {list(voices)}")
    return voices[engine]


def available_engines() -> list[str]:
    """Names of the evaluation engines installed on this machine: ``"flite"``; ``"mbrola"`` and ``"pico"`` (their
    held-out voices)."""
    engines = ["flite"] if shutil.which("flite") else []
    mbrola_voices = [MBROLA_DIR / voice.removeprefix("mb-") for voice in engine_voices("mbrola")]
    if shutil.which("espeak-ng") and all(path.is_dir() for path in mbrola_voices):
        engines.append("mbrola")
    if shutil.which("pico2wave"):
        engines.append("pico")
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


def speak_text(engine: str, text: str, voice: str, stretch: float = 1.0) -> tuple[np.ndarray, int]:
    """Say ``text`` with an evaluation engine; returns (float32 waveform, sample rate).

    :param engine: a name from :func:`available_engines`.
    :param text: what to say.
    :param voice: one of the engine's :func:`engine_voices`.
    :param stretch: duration stretch (< 1 is faster; MBROLA and Pico: espeak-ng's 175 words per minute divided by it).
    """
    from vafn_media.speech import DEFAULT_RATE, ESPEAK_SAMPLE_RATE, Voice, synthesizer_for

    if voice not in engine_voices(engine):
        raise ValueError(f"unknown {engine} voice {voice!r}; choose from {engine_voices(engine)}")
    if engine == "flite":
        return flite_speak(text, voice, stretch)
    settings = Voice(voice, rate=round(DEFAULT_RATE / stretch))
    return synthesizer_for(settings)(text, settings), ESPEAK_SAMPLE_RATE


def speak_with(engine: str, arms: Sequence[int], voice: str, template: int = 0,
               stretch: float = 1.0) -> tuple[np.ndarray, int]:
    """Say an instruction with an evaluation engine, phrased like the training phrasings.

    :param engine: a name from :func:`available_engines`.
    :param arms: 1-based arm ids.
    :param voice: the engine's voice.
    :param template: phrasing template index (see :data:`vafn_media.speech.TEMPLATES`).
    :param stretch: duration stretch (< 1 is faster).
    """
    from vafn_media.speech import phrase

    return speak_text(engine, phrase(arms, template), voice, stretch)
