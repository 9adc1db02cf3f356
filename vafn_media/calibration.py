"""Calibration of each modality's confidence (Platt scaling) and of the fusion weights on validation data.

Never fitted on the benchmark's items: it uses the cached in-distribution validation split, clean and degraded.

Run by the training command after training; also usable on an existing checkpoint:
``python -m vafn_media.calibration [--checkpoint PATH]`` (updates the checkpoint's JSON metadata).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from collections.abc import Sequence

import numpy as np

#: Candidate reliability weights of the image relative to audio (1.0 = equal trust).
IMAGE_WEIGHT_GRID: tuple[float, ...] = (1.0, 2.0, 1.5, 1.2, 0.8, 0.6, 0.5, 0.4, 0.3)
#: Seed and size of the calibration split (in-distribution "test" split: training voices and glyph sets).
CALIBRATION_SEED: int = 0
CALIBRATION_ITEMS: int = 500


def readings_of(model, data, corrupted: bool, batch_size: int = 64) -> dict[str, list]:
    """Greedy readings of every cached item per modality (``corrupted``: noisy audio + Cutout strips).

    :param model: the network.
    :param data: cached items (:class:`~vafn_media.dataset.TrainingData`).
    :param corrupted: use the noisy/Cutout copies instead of the clean ones.
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
                out[modality] += [greedy_decode(phi[b, : int(out_lengths[b])], logits[b, : int(out_lengths[b])])
                                  for b in range(len(out_lengths))]
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


def calibrate_fusion(model, data, grid: Sequence[float] = IMAGE_WEIGHT_GRID) -> dict:
    """Fit each modality's confidence calibration, then pick the image reliability weight that maximises fused
    exact-match accuracy on clean and degraded pairs.

    :param model: the network.
    :param data: in-distribution validation items.
    :param grid: candidate image weights (audio weight is 1).
    :return: {"confidence_calibration": {...}, "fusion_weights": {...}, "calibration": {weight: accuracy}}.
    """
    from vafn_media.decoding import fuse, reading_confidence

    labels = [tuple(data.arms[i, : data.lengths[i]].tolist()) for i in range(len(data))]
    pairs = [readings_of(model, data, corrupted=False), readings_of(model, data, corrupted=True)]
    platt = {}
    for modality in ("audio", "image"):
        reads = [r[modality][i] for r in pairs for i in range(len(labels))]
        platt[modality] = fit_platt([reading_confidence(d) for d in reads],
                                    [tuple(d.arms) == labels[i % len(labels)] for i, d in enumerate(reads)])
    scores = {}
    for weight in grid:
        hits = [tuple(fuse({"audio": r["audio"][i], "image": r["image"][i]}, None,
                           {"audio": 1.0, "image": weight}, platt).arms) == labels[i]
                for r in pairs for i in range(len(labels))]
        scores[weight] = float(np.mean(hits))
    best = max(grid, key=lambda w: (scores[w], w))  # ties: the more even weighting
    return {
        "confidence_calibration": {m: [round(a, 5), round(b, 5)] for m, (a, b) in platt.items()},
        "fusion_weights": {"audio": 1.0, "image": best},
        "calibration": {str(w): round(a, 4) for w, a in scores.items()},
    }


def main(argv=None) -> dict:
    """Calibrate an existing checkpoint and write the weights into its JSON metadata."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, default=None)
    parser.add_argument("--cache-dir", type=Path, default=None)
    args = parser.parse_args(argv)
    import torch

    from vafn_media.dataset import DEFAULT_CACHE, build_cache
    from vafn_media.generator import DEFAULT_CHECKPOINT, InstructionGenerator

    torch.set_num_threads(1)
    path = args.checkpoint or DEFAULT_CHECKPOINT
    generator = InstructionGenerator.load(path, warm=False)
    data = build_cache(CALIBRATION_SEED, "test", CALIBRATION_ITEMS, args.cache_dir or DEFAULT_CACHE)
    result = calibrate_fusion(generator.model, data)
    meta_path = Path(path).with_suffix(".json")
    metadata = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    metadata.update(result)
    meta_path.write_text(json.dumps(metadata, indent=2))
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
