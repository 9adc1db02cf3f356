"""Speech engines other than espeak-ng, used only to *evaluate* the reader on voices it was never trained on.

Nothing here is used for training. Each engine is an external program found on ``PATH`` (e.g. Debian's ``flite``);
:func:`available_engines` lists the ones present, and callers skip the others.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence

import numpy as np

#: flite voices that read arbitrary text (``awb_time`` only speaks times of day); ``kal`` synthesises at 8 kHz.
FLITE_VOICES: tuple[str, ...] = ("slt", "rms", "awb", "kal16", "kal")


def available_engines() -> list[str]:
    """Names of the evaluation engines installed on this machine (currently only ``"flite"`` is supported)."""
    return ["flite"] if shutil.which("flite") else []


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

    if engine != "flite":
        raise ValueError(f"unknown evaluation engine {engine!r}; available: {available_engines()}")
    return flite_speak(phrase(arms, template), voice, stretch)
