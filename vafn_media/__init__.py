"""Multimedia instruction generator: speech, digit-strip images and machine code -> one latent Φ -> an Instruction.

Public API (torch, librosa and OpenCV are imported lazily, on first use)::

    from vafn_media import InstructionGenerator, MultimediaStream
    generator = InstructionGenerator.load()            # the packaged checkpoint
    result = generator.transcribe(audio="cmd.wav", image="card.png")
    result.instruction, result.confidences, result.low_confidence

Speech synthesis for data generation (``speech.py``) uses espeak-ng (GPL) through the optional ``espeakng-loader``;
the inference path never imports it.
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "InstructionGenerator",
    "Transcription",
    "MultimediaStream",
    "StreamEvent",
    "DEFAULT_CHECKPOINT",
    "load_audio",
    "canonical_strip",
    "read_strip",
    "find_mask",
    "render_strip",
    "SpokenWords",
    "handwritten_glyphs",
    "say_instruction",
    "handwriting_strip",
    "add_awgn",
    "cutout",
]

_LOCATIONS = {
    "InstructionGenerator": "generator",
    "Transcription": "generator",
    "DEFAULT_CHECKPOINT": "generator",
    "MultimediaStream": "stream",
    "StreamEvent": "stream",
    "load_audio": "audio",
    "canonical_strip": "images",
    "read_strip": "images",
    "find_mask": "images",
    "render_strip": "strips",
    "SpokenWords": "people",
    "handwritten_glyphs": "people",
    "say_instruction": "people",
    "handwriting_strip": "people",
    "add_awgn": "corruptions",
    "cutout": "corruptions",
}


def __getattr__(name: str) -> Any:
    """Import public names lazily so ``import vafn_media`` stays cheap."""
    if name in _LOCATIONS:
        import importlib

        module = importlib.import_module(f"vafn_media.{_LOCATIONS[name]}")
        return getattr(module, name)
    raise AttributeError(f"module 'vafn_media' has no attribute {name!r}")
