"""Calibration of each modality's confidence (Platt scaling) and of the fusion weights on validation data.

Never fitted on the benchmark's items, voices or engines. The calibration sets are the cached in-distribution validation
split (clean, and degraded audio + Cutout images) and new instructions in the *training* voices and glyph sets under
every benchmark condition (the speech channel conditions clean, 8 kHz, reverb, 10 dB noise and fast with a clean card;
Table 1's noisy audio with a Cutout card), with their own seed.

Run by the training command after training; also usable on an existing checkpoint:
``python -m vafn_media.calibration [--checkpoint PATH]`` (rebuilds the validation split its training used from the
arguments in its JSON metadata, and updates that metadata).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from vafn_media.constants import MODALITIES

#: Candidate reliability weights of the image relative to audio (1.0 = equal trust).
IMAGE_WEIGHT_GRID: tuple[float, ...] = (0.3, 0.4, 0.5, 0.6, 0.8, 1.0, 1.2, 1.5, 2.0)
#: Seed and size of the cached calibration split (in-distribution "test" split: training voices and glyph sets) of a
#: checkpoint whose metadata records no training arguments.
CALIBRATION_SEED: int = 0
CALIBRATION_ITEMS: int = 500
#: Seed and size of each benchmark-condition calibration set (training voices; the benchmarks use other seeds).
CONDITION_SEED: int = 7
CONDITION_ITEMS: int = 300


@dataclass
class CalibrationSet:
    """Per-item readings of one calibration condition: audio (None: rejected), image, and the true arm ids."""

    name: str
    audio: list
    image: list
    labels: list[tuple[int, ...]]

    def accuracy(self, modality: str) -> float:
        """Exact-sequence accuracy of one modality alone (a rejected input counts as wrong)."""
        reads = getattr(self, modality)
        return float(np.mean([r is not None and tuple(r.arms) == y for r, y in zip(reads, self.labels)]))


def readings_of(model, data, corrupted: bool, blank_penalty: dict | None = None,
                batch_size: int = 64) -> dict[str, list]:
    """Greedy readings of every cached item per modality (``corrupted``: noisy audio + Cutout strips).

    :param model: the network.
    :param data: cached items (:class:`~vafn_media.dataset.TrainingData`).
    :param corrupted: use the noisy/Cutout copies instead of the clean ones.
    :param blank_penalty: modality -> CTC blank penalty of the decoding (default: none).
    :param batch_size: batch size of the encoders.
    """
    import torch

    from vafn_media.batching import make_batch
    from vafn_media.decoding import greedy_decode

    out: dict[str, list] = {"audio": [], "image": []}
    with torch.inference_mode():
        for start in range(0, len(data), batch_size):
            batch = make_batch(data, np.arange(start, min(len(data), start + batch_size)), None, corrupted)
            for modality in out:
                phi, out_lengths = model.encode(modality, batch[modality], batch[f"{modality}_lengths"])
                logits = model.decode(phi)
                penalty = float((blank_penalty or {}).get(modality, 0.0))
                out[modality] += [greedy_decode(phi[b, : int(out_lengths[b])], logits[b, : int(out_lengths[b])],
                                                penalty) for b in range(len(out_lengths))]
    return out


def fit_platt(confidences: Sequence[float], correct: Sequence[bool]) -> tuple[float, float]:
    """Platt scaling: (slope, intercept) of P(correct) = sigmoid(slope * logit(confidence) + intercept).

    :param confidences: raw sequence confidences in [0, 1].
    :param correct: whether each reading was right.
    """
    from sklearn.linear_model import LogisticRegression

    c = np.clip(np.asarray(confidences, np.float64), 1e-6, 1 - 1e-6)
    y = np.asarray(correct, bool)
    if y.all() or not y.any():
        return 1.0, 0.0
    model = LogisticRegression(C=10.0).fit(np.log(c / (1 - c))[:, None], y)
    return float(model.coef_[0, 0]), float(model.intercept_[0])


def cached_sets(model, data, blank_penalty: dict | None = None, name: str = "validation") -> list[CalibrationSet]:
    """Calibration sets from cached validation items: clean pairs, and noisy audio with Cutout images.

    :param model: the network.
    :param data: cached items (:class:`~vafn_media.dataset.TrainingData`).
    :param blank_penalty: modality -> CTC blank penalty of the decoding (default: none).
    :param name: what the items are (the sets are "<name> clean" and "<name> degraded + Cutout").
    """
    labels = [tuple(data.arms[i, : data.lengths[i]].tolist()) for i in range(len(data))]
    sets = []
    for condition, corrupted in (("clean", False), ("degraded + Cutout", True)):
        reads = readings_of(model, data, corrupted, blank_penalty)
        sets.append(CalibrationSet(f"{name} {condition}", reads["audio"], reads["image"], labels))
    return sets


def _read_audio(generator, source):
    """Greedy audio reading of a ``(waveform, rate)`` source, or None when the input is rejected."""
    try:
        return generator.read_audio(source)[0]
    except ValueError:
        return None


def condition_sets(generator, count: int = CONDITION_ITEMS, seed: int = CONDITION_SEED) -> list[CalibrationSet]:
    """Calibration sets in the training voices and glyph sets under every benchmark condition: each speech channel
    condition with a clean card, and Table 1's noisy audio with a Cutout card.

    :param generator: an :class:`~vafn_media.generator.InstructionGenerator` around the network.
    :param count: items per set (the same items under every channel condition).
    :param seed: seed of the items and of the degradations.
    """
    from vafn_media.augment import CONDITIONS
    from vafn_media.dataset import generate_raw
    from vafn_media.evaluation import corrupted_inputs, degraded_clip, speech_items

    items = speech_items("espeak", count, seed, heldout=False)
    images = [generator.read_image(item.image) for item in items]
    sets = [CalibrationSet(f"training voices, {condition}",
                           [_read_audio(generator, degraded_clip(item, condition, seed, i)) for i, item in
                            enumerate(items)], images, [item.arms for item in items])
            for condition in CONDITIONS]
    raw = generate_raw(seed, "test", count)
    noisy = [corrupted_inputs(raw, seed, i, "Audio-Visual (noise)") for i in range(count)]
    sets.append(CalibrationSet("training voices, Table 1 noise + Cutout",
                               [_read_audio(generator, kwargs["audio"]) for kwargs in noisy],
                               [generator.read_image(kwargs["image"]) for kwargs in noisy],
                               [tuple(a) for a in raw.arms]))
    return sets


def calibrate_fusion(sets: Sequence[CalibrationSet], grid: Sequence[float] = IMAGE_WEIGHT_GRID) -> dict:
    """Fit each modality's confidence calibration on every set's unmasked readings, then pick the image reliability
    weight under which audio-visual reading loses least against the better single modality in the worst set (the
    fusion must never make things worse), ties broken by mean accuracy, then by the more even weighting.

    :param sets: calibration sets (:func:`cached_sets`, :func:`condition_sets`).
    :param grid: candidate image weights (audio weight is 1).
    :return: {"confidence_calibration": {...}, "fusion_weights": {...}, "calibration": {...}}.
    """
    from vafn_media.decoding import fuse, reading_confidence

    platt = {}
    for modality in MODALITIES:
        # A reading of a partly masked input is flagged by its mask warning whatever its confidence; fitted with the
        # rest, its guesses about the hidden digit flattened the image calibration until right readings of clean
        # handwriting fell under the threshold.
        pairs = [(r, y) for s in sets for r, y in zip(getattr(s, modality), s.labels)
                 if r is not None and r.masked is None]
        platt[modality] = fit_platt([reading_confidence(r) for r, _ in pairs], [tuple(r.arms) == y for r, y in pairs])
    accuracy: dict[float, list[float]] = {}
    for weight in grid:
        accuracy[weight] = [
            float(np.mean([tuple(fuse({"audio": a, "image": i} if a is not None else {"image": i}, None,
                                      {"audio": 1.0, "image": weight}, platt).arms) == y
                           for a, i, y in zip(s.audio, s.image, s.labels)]))
            for s in sets]
    single = {m: [s.accuracy(m) for s in sets] for m in MODALITIES}
    best_single = [max(accuracies) for accuracies in zip(*single.values())]
    worst_margin = {w: min(a - b for a, b in zip(accuracy[w], best_single)) for w in grid}
    best = max(grid, key=lambda w: (round(worst_margin[w], 6), round(float(np.mean(accuracy[w])), 6),
                                    -abs(np.log(w))))
    return {
        "confidence_calibration": {m: [round(a, 5), round(b, 5)] for m, (a, b) in platt.items()},
        "fusion_weights": {"audio": 1.0, "image": best},
        "calibration": {
            "sets": [s.name for s in sets],
            **{m: [round(a, 4) for a in values] for m, values in single.items()},
            "av_by_image_weight": {str(w): [round(a, 4) for a in accuracy[w]] for w in grid},
            "worst_margin_by_image_weight": {str(w): round(m, 4) for w, m in worst_margin.items()},
        },
    }


def calibrate_generator(generator, data, people=None) -> dict:
    """Calibrate the network of ``generator`` on the cached validation items ``data``, the condition sets and, when
    given, the cached items of real people's *selection* speakers and glyphs (:mod:`vafn_media.people`)."""
    sets = cached_sets(generator.model, data, generator.blank_penalty) + condition_sets(generator)
    if people is not None:
        sets += cached_sets(generator.model, people, generator.blank_penalty, "people selection")
    return calibrate_fusion(sets)


def training_validation_split(metadata: dict, cache_dir: Path):
    """The cached validation items a checkpoint's training command calibrated on, rebuilt from the arguments in its
    metadata (seed, size and synthesiser shares); the default split (CALIBRATION_SEED) when it records none.

    :param metadata: the checkpoint's JSON metadata.
    :param cache_dir: where shards are cached.
    """
    from vafn_media.dataset import build_cache, data_shares

    args = metadata.get("args", {})
    if "seed" not in args:
        return build_cache(CALIBRATION_SEED, "test", CALIBRATION_ITEMS, cache_dir)
    return build_cache(args["seed"], "test", args.get("val_items", CALIBRATION_ITEMS), cache_dir, **data_shares(args))


def main(argv=None) -> dict:
    """Calibrate an existing checkpoint and write the weights into its JSON metadata."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, default=None)
    parser.add_argument("--cache-dir", type=Path, default=None)
    parser.add_argument("--people-speech", type=Path, nargs="+", default=None,
                        help="the real people's recorded words (folder or folders) the checkpoint trained with "
                             "(calibrates on their selection speakers too, as training did)")
    parser.add_argument("--people-handwriting", type=Path, default=None, help="and their MNIST training files")
    args = parser.parse_args(argv)
    import torch

    from vafn_media.dataset import DEFAULT_CACHE
    from vafn_media.generator import DEFAULT_CHECKPOINT, InstructionGenerator

    torch.set_num_threads(1)
    path = args.checkpoint or DEFAULT_CHECKPOINT
    generator = InstructionGenerator.load(path, warm=False)
    meta_path = Path(path).with_suffix(".json")
    metadata = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    people = None
    if args.people_speech is not None:
        from vafn_media.people import people_training_data

        train_args = metadata.get("args", {})
        people = people_training_data(args.people_speech, args.people_handwriting, "selection",
                                      train_args.get("people_val_items", 300), train_args.get("seed", 0),
                                      args.cache_dir or DEFAULT_CACHE)
    result = calibrate_generator(generator, training_validation_split(metadata, args.cache_dir or DEFAULT_CACHE),
                                 people)
    metadata.update(result)
    meta_path.write_text(json.dumps(metadata, indent=2))
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
