"""CTC decoding of Φ: greedy paths with per-token confidence, token embeddings, and calibrated audio-visual fusion."""

from __future__ import annotations

from collections.abc import Sequence
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
    #: Frames [start, stop) the input hid (see :func:`greedy_decode`'s ``hidden``).
    masked: tuple[int, int] | None = None


def path_segments(best: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) of the runs of equal labels in a non-empty best path (the collapse step of CTC decoding).

    :param best: (T,) frame-wise argmax labels, T >= 1.
    """
    starts = np.flatnonzero(np.r_[True, best[1:] != best[:-1]])
    return starts, np.r_[starts[1:], len(best)]


def greedy_decode(phi: torch.Tensor, logits: torch.Tensor, blank_penalty: float = 0.0,
                  hidden: tuple[int, int] | None = None) -> Decoded:
    """Best-path CTC decoding of one sequence.

    :param phi: (T, LATENT_DIM) latent frames.
    :param logits: (T, VOCAB_SIZE) decoder logits of those frames.
    :param blank_penalty: subtracted from the blank logit before decoding, so a token the frames half-hear is kept
        rather than swallowed by the blank; the confidences and the log posteriors fusion rescores with are those of
        the penalised logits.
    :param hidden: frames [start, stop) the input hid (a mask on an image): they read as blank and their log
        posteriors are uniform, so they are no evidence for or against any sequence when readings are rescored.
    """
    if blank_penalty:
        logits = logits.clone()
        logits[..., BLANK] -= blank_penalty
    log_probs = torch.log_softmax(logits, dim=-1)
    if hidden is not None:
        hidden = (max(0, hidden[0]), min(len(log_probs), hidden[1]))
        log_probs[hidden[0]:hidden[1]] = -float(np.log(log_probs.shape[-1]))
    probs = log_probs.exp().numpy()
    best = probs.argmax(-1)  # a hidden frame's uniform posterior reads as BLANK, the first label
    length = len(best)
    if length == 0:
        return Decoded([], [], [], phi.new_zeros((0, phi.shape[-1])), 0.0, log_probs, hidden)
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
    if hidden is not None:  # the least certain decision is among the frames that were seen
        best_prob[hidden[0]:hidden[1]] = 1.0
    return Decoded(arms, confidences, peaks, stacked, float(best_prob.min()), log_probs, hidden)


def best_path_arms(log_probs: torch.Tensor, blank_penalty: float = 0.0) -> list[int]:
    """Arm ids of the best CTC path of ``log_probs`` with the blank's log-probability lowered by ``blank_penalty``.

    Cheap (no confidences or embeddings): for checking whether a reading would change under a larger blank penalty.

    :param log_probs: (T, VOCAB_SIZE) log posteriors (e.g. :attr:`Decoded.log_probs`).
    :param blank_penalty: subtracted from the blank's log-probability of every frame.
    """
    scores = log_probs.numpy().copy()
    if len(scores) == 0:
        return []
    scores[:, BLANK] -= blank_penalty
    best = scores.argmax(-1)
    starts, _ = path_segments(best)
    return [int(best[start]) for start in starts if best[start] != BLANK]


def sequence_log_likelihood(log_probs: torch.Tensor, arms: list[int]) -> float:
    """CTC log-likelihood log P(arms | frames) (-inf when the sequence cannot be aligned).

    :param log_probs: (T, VOCAB_SIZE) log posteriors.
    :param arms: candidate arm ids (empty: the all-blank path).
    """
    frames = log_probs.shape[0]
    if not arms:
        return float(log_probs[:, BLANK].sum())
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


def calibrated(confidence: float, platt: tuple[float, float] | None) -> float:
    """Probability that a reading is right, from its raw sequence confidence by Platt scaling (fitted on validation).

    :param confidence: raw confidence in [0, 1].
    :param platt: (slope, intercept) on the logit of the raw confidence; None leaves the confidence unchanged.
    """
    if platt is None:
        return float(confidence)
    c = min(max(float(confidence), 1e-6), 1 - 1e-6)
    z = platt[0] * np.log(c / (1 - c)) + platt[1]
    return float(1.0 / (1.0 + np.exp(-z)))


def reading_confidence(reading: Decoded | Fused) -> float:
    """Raw sequence confidence of a reading: its least certain token (the weakest decision when it read none).

    Blank frames are left out on purpose: a noisy pause lowers their certainty on readings that are right, while a
    voice the model never heard shows up as a weak *token*; with blank frames included, the confidence separated right
    from wrong readings of an unseen speech engine much worse.
    """
    return float(min(reading.confidences)) if reading.confidences else float(reading.weakest)


def unseen_positions(arms: Sequence[int], seen: Sequence[int]) -> list[int] | None:
    """Positions of ``arms`` that a partial reading ``seen`` leaves out, matching ``seen`` as a subsequence from the
    left (None when it is not one): the tokens a masked input could not have shown.

    :param arms: the full reading.
    :param seen: the masked modality's own reading.
    """
    matched, j = set(), 0
    for i, arm in enumerate(arms):
        if j < len(seen) and seen[j] == arm:
            matched.add(i)
            j += 1
    return None if j < len(seen) else [i for i in range(len(arms)) if i not in matched]


def fuse(readings: dict[str, Decoded], decoder: torch.nn.Module, weights: dict[str, float] | None = None,
         calibration: dict[str, tuple[float, float]] | None = None) -> Fused:
    """Fuse per-modality readings; a disagreement is decided by every modality's evidence, never by one alone.

    - All modalities read the same sequence: that sequence ("agree"); each token's confidence is the probability that
      not every modality is wrong about it.
    - Otherwise the candidates are each modality's reading plus, when they have the same length, the token-by-token
      choice of the modality with the higher calibrated confidence. Each candidate is scored by the reliability-
      weighted sum over modalities of its CTC log-likelihood (a product of experts: a sequence the sharp modality
      rules out loses even if the other modality is confident) and the best wins ("rescored").

    The winner's confidence is its posterior among the candidates, capped by the calibrated probability that the
    modality it agrees with most is right, so a disagreement never looks certain.

    :param readings: modality -> greedy reading.
    :param decoder: the shared decoder (unused: readings are already decoded; kept for API compatibility).
    :param weights: modality -> reliability weight of its log-likelihood (calibrated on validation; default 1 each).
    :param calibration: modality -> Platt (slope, intercept) of its sequence confidence (default: uncalibrated).
    """
    del decoder
    names = list(readings)
    if len(names) == 1:
        only = readings[names[0]]
        return Fused(only.arms, only.confidences, names[0], only.weakest)
    reliability = {n: 1.0 if weights is None else float(weights.get(n, 1.0)) for n in names}
    trust = {n: calibrated(reading_confidence(readings[n]), (calibration or {}).get(n)) for n in names}
    sequences = {tuple(readings[n].arms) for n in names}
    if len(sequences) == 1:
        arms = list(readings[names[0]].arms)
        confidences = [1.0 - float(np.prod([1.0 - readings[n].confidences[j] for n in names]))
                       for j in range(len(arms))]
        return Fused(arms, confidences, "agree", max(readings[n].weakest for n in names))
    candidates = [tuple(readings[n].arms) for n in names]
    if len({len(c) for c in candidates}) == 1:
        mixed = tuple(int(readings[max(names, key=lambda n: trust[n] * readings[n].confidences[j])].arms[j])
                      for j in range(len(candidates[0])))
        candidates.append(mixed)
    candidates = list(dict.fromkeys(candidates))
    scores = np.array([sum(reliability[m] * sequence_log_likelihood(readings[m].log_probs, list(c)) for m in names)
                       for c in candidates])
    scores = np.nan_to_num(scores, nan=-1e9, neginf=-1e9)
    posterior = np.exp(scores - scores.max())
    posterior /= posterior.sum()
    best = int(np.argmax(scores))
    winner = list(candidates[best])
    backer = max(names, key=lambda n: (tuple(readings[n].arms) == candidates[best], trust[n]))
    cap = min(float(posterior[best]), trust[backer])
    token_conf = [max(float(readings[n].log_probs[:, a].max().exp()) for n in names) for a in winner]
    return Fused(winner, [min(c, cap) for c in token_conf], "rescored", cap)
