"""InstructionGenerator: any non-empty subset of {speech, image, machine code} -> an :class:`Instruction`."""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vafn_gym.instructions import Instruction
from vafn_media.audio import AudioSource, load_audio, with_quiet_edges
from vafn_media.constants import ENCODER_STRIDE, LOW_CONFIDENCE, MAX_INSTRUCTION_LENGTH, NUM_ARMS, SAMPLE_RATE
from vafn_media.images import ImageSource, read_strip

#: The packaged checkpoint (weights + metadata JSON), produced by ``python -m vafn_media.train``.
DEFAULT_CHECKPOINT = Path(__file__).parent / "checkpoints" / "instruction_model.pt"
#: A masked image does not contradict a fused reading whose CTC log-likelihood under its visible frames is at most this
#: much below that of its own reading (nats): the difference lies under the mask.
MASK_TOLERANCE_NATS: float = 2.0
#: Frames beside a mask that are read as hidden too: the encoder's receptive field spreads the mask's edge into them.
MASK_EDGE_FRAMES: int = 1
#: Largest checkpoint (bytes) and metadata file :meth:`InstructionGenerator.load` reads, and the largest channel or
#: hidden size its metadata may give the network (all checked before anything is read or built).
MAX_CHECKPOINT_BYTES = 64 * 2**20
MAX_METADATA_BYTES = 2**20
MAX_MODEL_SIZE = 1024


def _bounded_file(path: Path, limit: int) -> Path:
    """``path`` unless it is larger than ``limit`` bytes (``ValueError`` naming it)."""
    size = path.stat().st_size
    if size > limit:
        raise ValueError(f"{path} is {size:,} bytes; at most {limit:,} are read")
    return path


def _checked_config(metadata: Any, meta_path: Path) -> dict:
    """The metadata's network sizes, ``ValueError`` naming the file unless each is an integer in [1, MAX_MODEL_SIZE]."""
    config = metadata.get("config", {}) if isinstance(metadata, dict) else None
    if not isinstance(config, dict):
        raise ValueError(f"{meta_path}: expected a JSON object with a 'config' object")
    sizes = [value for item in config.values() for value in (item if isinstance(item, list) else [item])]
    if len(sizes) > 16 or not all(type(size) is int and 1 <= size <= MAX_MODEL_SIZE for size in sizes):
        raise ValueError(f"{meta_path}: network sizes {str(config)[:120]} outside [1, {MAX_MODEL_SIZE}]")
    return config


def _check_finite_weights(model: Any, checkpoint: Path) -> None:
    """``ValueError`` naming the file when a weight or buffer of the loaded model holds NaN or infinite values."""
    import torch

    for key, tensor in model.state_dict().items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise ValueError(f"checkpoint {checkpoint}: {key} holds NaN or infinite values")


@dataclass(frozen=True)
class Transcription:
    """What the generator read.

    :param instruction: the decoded instruction.
    :param confidences: per-token probability of each arm id (1.0 for machine code).
    :param confidence: sequence confidence: for one modality the calibrated probability that the reading is right,
        from its least certain token; for several, the least certain fused token, where an image was masked the
        least certain digit it could not see (1.0 for machine code).
    :param low_confidence: True when ``confidence`` is below the threshold, the input had quality warnings (clipped,
        possibly cut off, a modality dropped), or the modalities disagreed on the sequence. Treat such a result as a
        guess; :class:`MultimediaStream` does not enqueue it.
    :param modalities: the modalities that contributed.
    :param method: "code", "audio", "image", or for several modalities "agree" (same reading), "token" (token-wise
        choice by calibrated confidence) or "select" (the reading with the higher calibrated confidence).
    :param readings: each modality's own reading (arm ids).
    :param warnings: non-fatal input problems (clipping, dropped modalities, disagreement).
    :param dropped: modalities that were given but unusable, with the reason.
    :param latency_s: wall time of the call (features included), seconds.
    """

    instruction: Instruction
    confidences: tuple[float, ...]
    confidence: float
    low_confidence: bool
    modalities: tuple[str, ...]
    method: str
    readings: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    dropped: dict = field(default_factory=dict)
    latency_s: float = 0.0

    @property
    def arms(self) -> tuple[int, ...]:
        """The decoded arm ids."""
        return self.instruction.arms


class InstructionGenerator:
    """Reads instructions from speech, digit-strip images and machine code with one trained model.

    :param model: a trained :class:`~vafn_media.model.InstructionModel`.
    :param metadata: the checkpoint's metadata (training command, validation history).
    :param low_confidence: threshold under which a result is flagged ``low_confidence``.
    """

    def __init__(self, model: Any, metadata: dict | None = None, low_confidence: float = LOW_CONFIDENCE) -> None:
        import torch

        self.model = model.eval()
        self.metadata = metadata or {}
        self.low_confidence = float(low_confidence)
        #: Modality reliability weights of the fusion, calibrated by the training command (default: equal).
        self.fusion_weights: dict = dict(self.metadata.get("fusion_weights", {}))
        #: Per-modality Platt scaling of the sequence confidence (fitted on validation data; default: none).
        self.confidence_calibration: dict = {
            name: tuple(value) for name, value in self.metadata.get("confidence_calibration", {}).items()
        }
        #: Per-modality CTC blank penalty of greedy decoding (chosen by ``benchmarks/blank_penalty.py``; default: 0).
        self.blank_penalty: dict = dict(self.metadata.get("blank_penalty", {}))
        #: Per-modality blank penalty of the half-heard check: a reading that changes when decoded with this larger
        #: penalty is flagged (chosen by ``benchmarks/blank_penalty.py``; default: no check).
        self.blank_probe: dict = dict(self.metadata.get("blank_probe", {}))
        self._torch = torch
        from vafn_media.model import AudioInference

        #: The audio path as plain function calls on the model's weights (None when the model has layers it does not
        #: know, e.g. unfolded BatchNorm: then ``model.encode``); see :class:`~vafn_media.model.AudioInference`.
        self._audio_inference = AudioInference.build(self.model)

    @classmethod
    def load(cls, path: str | os.PathLike | None = None, warm: bool = True,
             low_confidence: float = LOW_CONFIDENCE) -> InstructionGenerator:
        """Load a checkpoint (default: the packaged one); ``warm`` pays librosa's slow first call now.

        :param path: ``.pt`` file written by the training command (its ``.json`` metadata must sit beside it).
        :param warm: build the mel filterbanks of common sample rates and run one dummy pass per encoder.
        :param low_confidence: threshold under which a result is flagged ``low_confidence``.
        """
        import torch

        from vafn_media.model import InstructionModel, ModelConfig, fold_batchnorm

        checkpoint = Path(path) if path is not None else DEFAULT_CHECKPOINT
        if not checkpoint.is_file():
            raise FileNotFoundError(
                f"no checkpoint at {checkpoint}; train one with `python -m vafn_media.train`"
            )
        meta_path = checkpoint.with_suffix(".json")
        _bounded_file(checkpoint, MAX_CHECKPOINT_BYTES)
        try:
            metadata = json.loads(_bounded_file(meta_path, MAX_METADATA_BYTES).read_text()) if meta_path.is_file() \
                else {}
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            raise ValueError(f"checkpoint metadata {meta_path} is not JSON: {error}") from error
        config = _checked_config(metadata, meta_path)
        try:
            model = InstructionModel(ModelConfig.from_dict(config) if config else ModelConfig())
            # weights_only: tensors and plain containers only, a pickle carrying code is refused, never run
            model.load_state_dict(torch.load(checkpoint, map_location="cpu", weights_only=True))
        except Exception as error:  # noqa: BLE001 - torch/pickle/zip/JSON raise many types for a damaged file
            raise ValueError(f"checkpoint {checkpoint} (or its metadata {meta_path.name}) is corrupt or does not "
                             f"match the model: {type(error).__name__}: {str(error)[:200]}") from error
        _check_finite_weights(model, checkpoint)
        generator = cls(fold_batchnorm(model.eval()), metadata, low_confidence)
        if warm:
            generator.warm_up()
        return generator

    def warm_up(self) -> None:
        """Build cached filterbanks, import the I/O libraries and run each path once so the first real call is fast."""
        import soundfile  # noqa: F401  (first import is slow; file input uses it)
        import soxr  # noqa: F401

        from vafn_media.features import mel_filterbank

        mel_filterbank(SAMPLE_RATE)

        rng = np.random.default_rng(0)
        self.encode_audio(rng.normal(0, 0.1, SAMPLE_RATE).astype(np.float32), SAMPLE_RATE)
        from vafn_media.strips import render_strip

        self.read_image(render_strip([1, 2, 3], rng))

    # --- encoders ---
    def encode_audio(self, waveform: np.ndarray, sample_rate: int):
        """Φ frames (T, LATENT_DIM) of a validated mono waveform (resampled to SAMPLE_RATE first if needed).

        :param waveform: float32 samples.
        :param sample_rate: its rate in Hz.
        """
        from vafn_media.augment import resample
        from vafn_media.features import audio_features

        torch = self._torch
        with torch.inference_mode():
            features = audio_features(resample(waveform, sample_rate, SAMPLE_RATE))
            if self._audio_inference is not None:
                return self._audio_inference(features)[0]
            phi, _ = self.model.encode("audio", features, torch.tensor([features.shape[-1]]))
        return phi[0]

    def encode_strip(self, strip: np.ndarray):
        """Φ frames (W', LATENT_DIM) of a canonical strip (see :func:`canonical_strip`).

        :param strip: float32 (IMAGE_HEIGHT, W) ink image.
        """
        torch = self._torch
        with torch.inference_mode():
            tensor = torch.from_numpy(np.ascontiguousarray(strip, dtype=np.float32))[None, None]
            phi, _ = self.model.encode("image", tensor, torch.tensor([strip.shape[1]]))
        return phi[0]

    def read(self, phi, modality: str, hidden: tuple[int, int] | None = None):
        """Greedy CTC reading of Φ frames by the shared decoder, with the modality's blank penalty.

        :param phi: (T, LATENT_DIM) latent frames.
        :param modality: "audio" or "image": the encoder the frames came from.
        :param hidden: frames [start, stop) the input hid (:func:`~vafn_media.decoding.greedy_decode`).
        """
        from vafn_media.decoding import greedy_decode

        with self._torch.inference_mode():
            return greedy_decode(phi, self.model.decode(phi), float(self.blank_penalty.get(modality, 0.0)), hidden)

    def read_audio(self, audio: AudioSource, sample_rate: int | None = None):
        """Greedy reading of validated audio (with silence added at an end that is in a sound) and its warnings (the
        clip's quality, and :meth:`half_heard`); ValueError when it is unusable.

        :param audio: as :meth:`transcribe`'s ``audio``.
        :param sample_rate: sample rate of a bare waveform.
        """
        clip = load_audio(audio, sample_rate)
        reading = self.read(self.encode_clip(clip), "audio")
        return reading, list(clip.warnings) + self.half_heard(reading, "audio")

    def encode_clip(self, clip):
        """Φ frames of a validated clip (from :func:`load_audio`) as :meth:`read_audio` reads it: with silence added at
        an end that is in a sound.

        :param clip: a validated clip.
        """
        return self.encode_audio(with_quiet_edges(clip), clip.sample_rate)

    def half_heard(self, reading, modality: str) -> list[str]:
        """A warning when the reading changes under the modality's probe blank penalty (a word the frames only
        half-hear, kept or dropped depending on the penalty); none without a probe or when the reading is stable.

        :param reading: the modality's greedy reading (its ``log_probs`` already carry the decoding penalty).
        :param modality: "audio" or "image".
        """
        from vafn_media.decoding import best_path_arms

        probe = self.blank_probe.get(modality)
        if probe is None:
            return []
        extra = float(probe) - float(self.blank_penalty.get(modality, 0.0))
        changed = best_path_arms(reading.log_probs, extra)
        if changed == list(reading.arms):
            return []
        return [f"{modality} may have a half-heard word: with a larger blank penalty it reads {changed}, "
                f"not {list(reading.arms)}"]

    def read_image(self, image: ImageSource):
        """Greedy reading of an image of digits in a row; ValueError when it is unusable.

        :param image: as :meth:`transcribe`'s ``image``.
        """
        strip, masked = read_strip(image)
        hidden = None if masked is None else (masked[0] // ENCODER_STRIDE - MASK_EDGE_FRAMES,
                                              -(-masked[1] // ENCODER_STRIDE) + MASK_EDGE_FRAMES)
        return self.read(self.encode_strip(strip), "image", hidden)

    def contradicted_by(self, readings: dict, arms: list[int]) -> list[str]:
        """The modalities whose reading differs from ``arms`` in what they saw: all that read another sequence, less
        a masked one (:attr:`~vafn_media.decoding.Decoded.masked`) whose visible frames fit ``arms`` within
        :data:`MASK_TOLERANCE_NATS` of its own reading.

        :param readings: modality -> greedy reading.
        :param arms: the fused reading.
        """
        from vafn_media.decoding import sequence_log_likelihood

        against = []
        for name, reading in readings.items():
            if list(reading.arms) == list(arms):
                continue
            if reading.masked is not None:
                own = sequence_log_likelihood(reading.log_probs, list(reading.arms))
                if sequence_log_likelihood(reading.log_probs, list(arms)) >= own - MASK_TOLERANCE_NATS:
                    continue
            against.append(name)
        return against

    def hidden_token_confidence(self, readings: dict, arms: list[int]) -> float | None:
        """Calibrated confidence of ``arms`` token-wise when one modality saw everything and read ``arms``, and the
        other was masked and read ``arms`` less some tokens: the tokens both read are confirmed, the hidden ones rest
        on the full reading alone, so its least certain hidden token decides. None in any other case (then a masked
        input adds no certainty; also when the mask hid no token, so a word both readings missed cannot look certain).

        :param readings: modality -> greedy reading.
        :param arms: the fused reading.
        """
        from vafn_media.decoding import calibrated, unseen_positions

        seen = [(n, r) for n, r in readings.items() if r.masked is None]
        masked = [r for r in readings.values() if r.masked is not None]
        if len(seen) != 1 or len(masked) != 1 or list(seen[0][1].arms) != list(arms):
            return None
        name, full = seen[0]
        hidden = unseen_positions(arms, masked[0].arms)
        if not hidden:
            return None
        return min(calibrated(full.confidences[j], self.confidence_calibration.get(name)) for j in hidden)

    # --- public API ---
    def transcribe(self, audio: AudioSource | None = None, image: ImageSource | None = None,
                   code: str | list | Instruction | None = None, sample_rate: int | None = None) -> Transcription:
        """Read an instruction from any non-empty subset of modalities.

        With several modalities, unusable ones (silent audio, blank image, …) are dropped with a warning; if none is
        usable, ValueError names every problem. Machine code, when given, is authoritative (parsed, not inferred).

        :param audio: path to an audio file, a waveform (with ``sample_rate``) or a ``(waveform, rate)`` tuple.
        :param image: path or array (gray/BGR/BGRA) of digits in a left-to-right row.
        :param code: machine code (``"2,3,1"``, ``"[2, 3, 1]"``, JSON, a list of arm ids or an Instruction).
        :param sample_rate: sample rate of a bare ``audio`` waveform.
        """
        from vafn_media.decoding import calibrated, fuse, reading_confidence

        started = time.perf_counter()
        given = {
            name: value for name, value in (("audio", audio), ("image", image), ("code", code)) if value is not None
        }
        if not given:
            raise ValueError("transcribe needs at least one of audio=, image=, code=")
        warnings: list[str] = []
        dropped: dict[str, str] = {}
        readings = {}
        if "code" in given:
            instruction = Instruction.coerce(given["code"], n_arms=NUM_ARMS)  # ValueError on malformed code
        if "audio" in given:
            try:
                readings["audio"], clip_warnings = self.read_audio(given["audio"], sample_rate)
                warnings += clip_warnings
            except ValueError as error:
                dropped["audio"] = str(error)
        if "image" in given:
            try:
                readings["image"] = self.read_image(given["image"])
            except ValueError as error:
                dropped["image"] = str(error)
        if "code" in given:
            return self._code_result(instruction, readings, warnings, dropped, started)
        if not readings:
            raise ValueError("no usable input: " + "; ".join(f"{name}: {why}" for name, why in dropped.items()))
        warnings += [f"{name} ignored: {why}" for name, why in dropped.items()]
        with self._torch.inference_mode():
            fused = fuse(readings, self.model.decode, self.fusion_weights, self.confidence_calibration)
        if len(readings) > 1 and self.contradicted_by(readings, fused.arms):
            warnings.append("modalities disagree: " + ", ".join(f"{n}={list(r.arms)}" for n, r in readings.items()))
        if len(readings) == 1 and next(iter(readings.values())).masked is not None:
            warnings.append(f"{next(iter(readings))} is partly masked (a solid rectangle of one grey level): a digit "
                            f"under it may be missing")
        arms = fused.arms[:MAX_INSTRUCTION_LENGTH]
        if len(fused.arms) > MAX_INSTRUCTION_LENGTH:
            warnings.append(f"read {len(fused.arms)} arm ids; only the first {MAX_INSTRUCTION_LENGTH} are kept")
        confidence = reading_confidence(fused)  # a single modality's fused reading is that reading itself
        if len(readings) == 1:
            confidence = calibrated(confidence, self.confidence_calibration.get(next(iter(readings))))
        seen = {n: r for n, r in readings.items() if r.masked is None}
        if len(seen) < len(readings) and seen:  # a masked image adds no certainty about what it could not see
            token_wise = self.hidden_token_confidence(readings, list(fused.arms))
            confidence = token_wise if token_wise is not None else min(confidence, max(
                calibrated(reading_confidence(r), self.confidence_calibration.get(n)) for n, r in seen.items()))
        low = confidence < self.low_confidence or bool(warnings)
        return Transcription(
            instruction=Instruction.from_arms(arms, n_arms=NUM_ARMS),
            confidences=tuple(fused.confidences[: len(arms)]),
            confidence=confidence,
            low_confidence=low,
            modalities=tuple(readings),
            method=fused.method,
            readings={name: tuple(r.arms) for name, r in readings.items()},
            warnings=tuple(warnings),
            dropped=dropped,
            latency_s=time.perf_counter() - started,
        )

    @staticmethod
    def _code_result(
        instruction: Instruction, readings: dict, warnings: list, dropped: dict, started: float
    ) -> Transcription:
        for name, reading in readings.items():
            if tuple(reading.arms) != instruction.arms:
                warnings.append(f"{name} reads {list(reading.arms)} but the code says {list(instruction.arms)}")
        return Transcription(
            instruction=instruction,
            confidences=(1.0,) * len(instruction),
            confidence=1.0,
            low_confidence=False,
            modalities=("code",) + tuple(readings),
            method="code",
            readings={"code": instruction.arms, **{name: tuple(r.arms) for name, r in readings.items()}},
            warnings=tuple(warnings),
            dropped=dropped,
            latency_s=time.perf_counter() - started,
        )
