"""CTC decoding of Φ: greedy paths with per-token confidence, token embeddings, and audio-visual fusion in Φ."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from vafn_media.constants import BLANK


@dataclass
class Decoded:
    """Greedy CTC reading of one Φ sequence.

    ``arms``: decoded arm ids; ``confidences``: per-token probability at its peak frame; ``peaks``: frame index of each
    token; ``embeddings``: (len(arms), LATENT_DIM) token embeddings (posterior-weighted mean of the token's frames);
    ``weakest``: lowest max-probability over all frames (the least certain decision of the path).
    """

    arms: list[int]
    confidences: list[float]
    peaks: list[int]
    embeddings: torch.Tensor
    weakest: float
    log_probs: torch.Tensor = field(repr=False)


def path_segments(best: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) of the runs of equal labels in a non-empty best path (the collapse step of CTC decoding).

    :param best: (T,) frame-wise argmax labels, T >= 1.
    """
    starts = np.flatnonzero(np.r_[True, best[1:] != best[:-1]])
    return starts, np.r_[starts[1:], len(best)]


def greedy_decode(phi: torch.Tensor, logits: torch.Tensor) -> Decoded:
    """Best-path CTC decoding of one sequence.

    :param phi: (T, LATENT_DIM) latent frames.
    :param logits: (T, VOCAB_SIZE) decoder logits of those frames.
    """
    log_probs = torch.log_softmax(logits, dim=-1)
    probs = log_probs.exp().numpy()
    best = probs.argmax(-1)
    length = len(best)
    if length == 0:
        return Decoded([], [], [], phi.new_zeros((0, phi.shape[-1])), 0.0, log_probs)
    best_prob = probs[np.arange(length), best]
    starts, ends = path_segments(best)
    arms, confidences, peaks, embeddings = [], [], [], []
    phi_np = phi.numpy()
    for start, end in zip(starts, ends):
        label = int(best[start])
        if label == BLANK:
            continue
        segment = probs[start:end, label]
        arms.append(label)
        confidences.append(float(segment.max()))
        peaks.append(int(start + segment.argmax()))
        embeddings.append((segment / segment.sum()) @ phi_np[start:end])
    stacked = (
        torch.from_numpy(np.stack(embeddings).astype(np.float32)) if embeddings else phi.new_zeros((0, phi.shape[-1]))
    )
    return Decoded(arms, confidences, peaks, stacked, float(best_prob.min()), log_probs)


def sequence_log_likelihood(log_probs: torch.Tensor, arms: list[int]) -> float:
    """CTC log-likelihood log P(arms | frames) (-inf when the sequence cannot be aligned).

    :param log_probs: (T, VOCAB_SIZE) log posteriors.
    :param arms: candidate arm ids.
    """
    frames = log_probs.shape[0]
    targets = torch.tensor(list(arms), dtype=torch.long).reshape(1, len(arms))
    loss = torch.nn.functional.ctc_loss(log_probs[:, None, :], targets, torch.tensor([frames]),
                                        torch.tensor([len(arms)]), blank=BLANK, reduction="sum",
                                        zero_infinity=False)
    return float(-loss)


@dataclass
class Fused:
    """Result of fusing several modalities: the arm ids, per-token confidences and how they were obtained."""

    arms: list[int]
    confidences: list[float]
    method: str
    weakest: float


def fuse(readings: dict[str, Decoded], decoder: torch.nn.Module, weights: dict[str, float] | None = None) -> Fused:
    """Fuse per-modality readings in Φ.

    When all modalities read the same number of tokens, each token's Φ embeddings are averaged with weights
    proportional to modality reliability x token confidence and decoded again by the shared decoder ("latent"
    fusion). When the counts disagree, every modality's reading is rescored by the reliability-weighted sum over
    modalities of its CTC log-likelihood and the best candidate wins ("rescored"); its confidence is the candidate's
    posterior among the candidates, so a disagreement between modalities shows up as low confidence.

    :param readings: modality -> greedy reading.
    :param decoder: the shared decoder (pointwise: Φ vector -> CTC logits).
    :param weights: modality -> reliability weight (calibrated on validation data; default 1 each).
    """
    reliability = {name: 1.0 if weights is None else float(weights.get(name, 1.0)) for name in readings}
    names = list(readings)
    if len(names) == 1:
        only = readings[names[0]]
        return Fused(only.arms, only.confidences, names[0], only.weakest)
    counts = {len(readings[n].arms) for n in names}
    if len(counts) == 1:
        count = counts.pop()
        if count == 0:
            return Fused([], [], "latent", max(readings[n].weakest for n in names))
        # (M, L)
        mix = torch.tensor([[reliability[n] * readings[n].confidences[j] for j in range(count)] for n in names])
        mix = mix / mix.sum(0, keepdim=True).clamp_min(1e-12)
        stacked = torch.stack([readings[n].embeddings for n in names])  # (M, L, D)
        fused = (mix[:, :, None] * stacked).sum(0)
        probs = torch.softmax(decoder(fused), dim=-1)
        probs[:, BLANK] = 0.0  # a token position was agreed on; only its identity is decided here
        probs = probs / probs.sum(-1, keepdim=True)
        confidence, arms = probs.max(-1)
        return Fused([int(a) for a in arms], [float(c) for c in confidence], "latent",
                     max(readings[n].weakest for n in names))
    candidates = [readings[n].arms for n in names]
    scores = np.array([sum(reliability[m] * sequence_log_likelihood(readings[m].log_probs, cand) for m in names)
                       for cand in candidates])
    scores = np.nan_to_num(scores, nan=-1e9, neginf=-1e9)
    posterior = np.exp(scores - scores.max())
    posterior /= posterior.sum()
    best = int(np.argmax(scores))
    winner = readings[names[best]]
    return Fused(list(winner.arms), [min(c, float(posterior[best])) for c in winner.confidences], "rescored",
                 min(winner.weakest, float(posterior[best])))
