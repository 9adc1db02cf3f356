"""What the speech reader is and is not invariant to: why it reads held-out espeak voices but not another engine.

Exact-sequence accuracy of the packaged reader (audio alone, clean 16 kHz, 0.25 s of silence around every clip) on
spoken instructions (lengths 1-10, random phrasings, a seed of its own) under probes that each change one thing:

- espeak-ng's held-out voices as they are, then with the **voice source replaced** (LPC resynthesis: the same
  spectral envelope every 10 ms, excited by a pulse train on a random, drifting f0 of 70-260 Hz mixed with noise by
  the frame's voicing), then with the number words said with **other vowels and consonants** (espeak-ng phoneme
  input: e.g. *two* as [tU], [tu], [tVu]; *three* as [tri:], [fri:], [TrI]), one variant per word;
- flite (never trained on) as it is, then warped at test time: vocal-tract length (the training VTLP, factors 0.75-1.25)
  and playback speed (0.85-1.15);
- every engine made faster with its pitch kept, to 0.7x its duration (the robustness table's "fast" for engines
  without a rate control) by two methods: WSOLA (``sox tempo``; skipped without sox) and a phase vocoder (librosa,
  the robustness table's method): does the reader fail on the rate, or on how the clip was compressed?
- both engines saying only the number words, as one sentence and then **one word at a time**, each word synthesised
  alone, trimmed and joined with 0, 100 or 250 ms of silence: where the words no longer touch, what is left of the
  errors lies in the words themselves, not in how an engine runs them together.

If the reader keeps its accuracy under the espeak probes but the flite warps do not bring flite up, what differs is
neither the voice source, the pronunciation, the vocal-tract length nor the rate, but how the other engine renders
the words: something no augmentation of espeak-ng's output here reproduces. Never asserts a number.

    OMP_NUM_THREADS=1 python benchmarks/speech_invariance.py --items 200 --out results/speech_invariance.md
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

#: Seed of the items: neither the robustness table's nor the checkpoint selection's.
ITEM_SEED = 777
#: Voice source of the resynthesis probe: LPC order, analysis frame (s), f0 range (Hz).
LPC_ORDER, LPC_FRAME_S, F0_RANGE = 18, 0.02, (70.0, 260.0)
#: Silence between number words said one at a time (s).
WORD_GAPS_S: tuple[float, ...] = (0.0, 0.1, 0.25)
#: Duration factor of the pitch-kept tempo probes (the robustness table's "fast" for engines without a rate control).
FAST_DURATION = 0.7
#: espeak-ng phoneme mnemonics of each number word: the default (first) and accent-like variants.
PRONUNCIATIONS: dict[int, tuple[str, ...]] = {
    1: ("w'Vn", "w'0n", "w'@n", "w'an"),
    2: ("t'u:", "t'U", "t'u", "t'Vu"),
    3: ("Tr'i:", "tr'i:", "fr'i:", "Tr'I"),
}


def resynthesise(waveform: np.ndarray, sample_rate: int, rng: np.random.Generator) -> np.ndarray:
    """The clip's spectral envelope (LPC, every half frame) on a new voice source: pulses at a random f0 plus noise."""
    from scipy.linalg import solve_toeplitz
    from scipy.signal import lfilter

    x = np.asarray(waveform, np.float64)
    frame = int(LPC_FRAME_S * sample_rate)
    hop, n = frame // 2, len(x)
    window = np.hanning(frame + 1)[:-1]  # periodic Hann: overlap-adds to one at 50 % overlap
    t = np.arange(n) / sample_rate
    f0 = rng.uniform(*F0_RANGE) * (1 + rng.uniform(0, 0.2) * np.sin(2 * np.pi * rng.uniform(0.3, 2) * t))
    pulses = np.diff(np.floor(np.cumsum(f0 / sample_rate)), prepend=0.0)
    noise = rng.normal(0, 1, n)
    emphasised = np.concatenate([np.append(x[0], x[1:] - 0.97 * x[:-1]), np.zeros(frame)])
    lags = slice(int(sample_rate / 400), int(sample_rate / 60))  # pitch lags of 60-400 Hz voices
    out = np.zeros(n)
    for start in range(0, n, hop):
        segment = emphasised[start:start + frame] * window
        r = np.correlate(segment, segment, "full")[frame - 1:]
        if r[0] < 1e-10:
            continue
        a = solve_toeplitz(r[:LPC_ORDER] * np.r_[1 + 1e-6, np.ones(LPC_ORDER - 1)], r[1:LPC_ORDER + 1])
        voicing = float(np.clip(r[lags].max() / r[0], 0.0, 1.0)) ** 2
        span = slice(start, min(start + frame, n))
        p, w = pulses[span], noise[span]
        source = (np.sqrt(voicing) * p / max(np.sqrt(np.mean(p ** 2)), 1e-9)
                  + np.sqrt(1 - voicing) * w / max(np.sqrt(np.mean(w ** 2)), 1e-9))
        y = lfilter([1.0], np.r_[1.0, -a], source) * window[: len(source)]
        out[span] += y * np.sqrt(np.sum(segment ** 2) / max(np.sum(y ** 2), 1e-12))
    y = lfilter([1.0], [1.0, -0.97], out)
    return (y * np.sqrt(np.mean(x ** 2) / max(np.mean(y ** 2), 1e-12))).astype(np.float32)


def espeak_with_pronunciation(arms: tuple[int, ...], voice: str, variant: int) -> np.ndarray:
    """The number words of ``arms`` said with pronunciation ``variant`` of :data:`PRONUNCIATIONS`, comma-separated."""
    from vafn_media.speech import EspeakSynthesizer, Voice

    text = ", ".join(f"[[{PRONUNCIATIONS[arm][variant]}]]" for arm in arms)
    return EspeakSynthesizer.shared().synthesize(text, Voice(*voice.split("+")), phonemes=True)


def sox_tempo(waveform: np.ndarray, rate: int, duration: float) -> np.ndarray:
    """``waveform`` compressed to ``duration`` x its length, pitch kept, by sox's WSOLA ``tempo`` effect."""
    import subprocess
    import tempfile

    import soundfile as sf

    with tempfile.TemporaryDirectory() as folder:
        source, target = Path(folder) / "in.wav", Path(folder) / "out.wav"
        sf.write(source, waveform, rate)
        subprocess.run(["sox", str(source), str(target), "tempo", "-s", f"{1.0 / duration:.6f}"], check=True)
        return sf.read(target, dtype="float32")[0]


def one_word_at_a_time(arms: tuple[int, ...], say: Callable[[str], tuple[np.ndarray, int]],
                       gap_s: float) -> tuple[np.ndarray, int]:
    """The number words of ``arms`` each synthesised alone by ``say``, trimmed and joined by ``gap_s`` of silence."""
    from vafn_media.speech import NUMBER_WORDS, splice_words

    words = [say(NUMBER_WORDS[arm]) for arm in arms]
    rate = words[0][1]
    return splice_words([waveform for waveform, _ in words], [gap_s] * (len(words) - 1), rate), rate


def accuracy(read: Callable[[np.ndarray, int], tuple[int, ...]], clips: list[tuple[np.ndarray, int]],
             labels: list[tuple[int, ...]]) -> float:
    """Exact-sequence accuracy (%) of ``read`` on padded clips; a rejected clip counts as wrong."""
    right = 0
    for (waveform, rate), arms in zip(clips, labels):
        pad = np.zeros(int(0.25 * rate), np.float32)
        try:
            right += read(np.concatenate([pad, waveform, pad]), rate) == arms
        except ValueError:
            pass
    return 100.0 * right / len(labels)


def main(argv: list[str] | None = None) -> list[tuple[str, str, float]]:
    """Run every probe; print (and with ``--out`` write) the markdown table; return its rows."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--items", type=int, default=200, help="instructions per engine")
    parser.add_argument("--out", type=Path, default=None, help="also write the markdown table here (None: print only)")
    args = parser.parse_args(argv)

    import torch

    from vafn_media import InstructionGenerator
    from vafn_media.augment import phase_vocoder_stretch, resample, speed
    from vafn_media.batching import warp_vocal_tract
    from vafn_media.constants import SAMPLE_RATE
    from vafn_media.engines import available_engines, speak_text
    from vafn_media.evaluation import speech_items
    from vafn_media.features import audio_features
    from vafn_media.speech import ESPEAK_SAMPLE_RATE, NUMBER_WORDS, EspeakSynthesizer, Voice

    torch.set_num_threads(1)
    started = time.perf_counter()
    generator = InstructionGenerator.load()

    def read(waveform: np.ndarray, rate: int) -> tuple[int, ...]:
        return tuple(generator.transcribe(audio=(waveform, rate)).arms)

    def read_warped(factor: float) -> Callable[[np.ndarray, int], tuple[int, ...]]:
        def run(waveform: np.ndarray, rate: int) -> tuple[int, ...]:
            features = warp_vocal_tract(audio_features(resample(waveform, rate, SAMPLE_RATE))[0].numpy(), factor)
            with torch.inference_mode():
                phi, _ = generator.model.encode("audio", torch.from_numpy(features)[None],
                                                torch.tensor([features.shape[1]]))
                return tuple(generator.read(phi[0], "audio").arms)
        return run

    rows: list[tuple[str, str, float]] = []
    # the phase vocoder is what makes the robustness table's "fast" recorded voice
    tempo_methods = {"phase vocoder (librosa)": lambda waveform, rate: phase_vocoder_stretch(waveform, FAST_DURATION)}
    if shutil.which("sox"):
        tempo_methods = {"WSOLA (sox tempo)": lambda waveform, rate: sox_tempo(waveform, rate, FAST_DURATION),
                         **tempo_methods}

    def tempo_rows(engine: str, clips: list[tuple[np.ndarray, int]], labels: list[tuple[int, ...]]) -> None:
        """The pitch-kept tempo probes of one engine's clips."""
        for method, compress in tempo_methods.items():
            faster = [(compress(waveform, rate), rate) for waveform, rate in clips]
            rows.append((engine, f"{FAST_DURATION}x duration, pitch kept: {method}", accuracy(read, faster, labels)))

    def word_rows(engine: str, spoken_items: list, synthesise: Callable[[str, str], tuple[np.ndarray, int]]) -> None:
        """The number-words-only rows of one engine, on its non-empty instructions."""
        # one synthesis per (voice, word): a word alone sounds the same in every instruction
        said: dict[tuple[str, str], tuple[np.ndarray, int]] = {}

        def say_in(voice: str) -> Callable[[str], tuple[np.ndarray, int]]:
            def say(word: str) -> tuple[np.ndarray, int]:
                if (voice, word) not in said:
                    said[voice, word] = synthesise(word, voice)
                return said[voice, word]
            return say

        spoken_items = [item for item in spoken_items if item.arms]
        arms_of = [item.arms for item in spoken_items]
        sentences = [synthesise(" ".join(NUMBER_WORDS[arm] for arm in item.arms), item.voice) for item in spoken_items]
        rows.append((engine, f"only the number words, as one sentence ({len(arms_of)} non-empty)",
                     accuracy(read, sentences, arms_of)))
        for gap_s in WORD_GAPS_S:
            joined = [one_word_at_a_time(item.arms, say_in(item.voice), gap_s) for item in spoken_items]
            rows.append((engine, f"only the number words, one at a time, {1000 * gap_s:.0f} ms apart",
                         accuracy(read, joined, arms_of)))
    items = speech_items("espeak", args.items, ITEM_SEED)
    clips = [(item.waveform, item.sample_rate) for item in items]
    labels = [item.arms for item in items]
    rows.append(("espeak held-out voices", "as synthesised", accuracy(read, clips, labels)))
    resynthesised = [(resynthesise(resample(w, r, SAMPLE_RATE), SAMPLE_RATE, np.random.default_rng([ITEM_SEED, i])),
                      SAMPLE_RATE) for i, (w, r) in enumerate(clips)]
    rows.append(("espeak held-out voices", "voice source replaced (LPC resynthesis, random f0)",
                 accuracy(read, resynthesised, labels)))
    tempo_rows("espeak held-out voices", clips, labels)
    for variant in range(len(PRONUNCIATIONS[1])):  # 0: the default words, said the same way (comma-separated)
        said = ", ".join(f"{word} [{PRONUNCIATIONS[arm][variant]}]" for arm, word in ((1, "one"), (2, "two"),
                                                                                       (3, "three")))
        spoken = [(espeak_with_pronunciation(item.arms, item.voice, variant), ESPEAK_SAMPLE_RATE) for item in items]
        rows.append(("espeak held-out voices", f"number words as {said}", accuracy(read, spoken, labels)))
    word_rows("espeak held-out voices", items,
              lambda text, voice: (EspeakSynthesizer.shared().synthesize(text, Voice(*voice.split("+"))),
                                   ESPEAK_SAMPLE_RATE))
    for engine in available_engines():
        items = speech_items(engine, args.items, ITEM_SEED)
        clips = [(item.waveform, item.sample_rate) for item in items]
        labels = [item.arms for item in items]
        rows.append((engine, "as synthesised", accuracy(read, clips, labels)))
        for factor in (0.75, 0.85, 0.9, 1.1, 1.15, 1.25):
            rows.append((engine, f"vocal-tract length x{factor} at test time", accuracy(read_warped(factor), clips,
                                                                                       labels)))
        for factor in (0.85, 0.9, 1.1, 1.15):
            sped = [(speed(resample(w, r, SAMPLE_RATE), factor), SAMPLE_RATE) for w, r in clips]
            rows.append((engine, f"played at {factor}x speed (tempo and pitch)", accuracy(read, sped, labels)))
        tempo_rows(engine, clips, labels)
        word_rows(engine, items, partial(speak_text, engine))
    lines = [f"Speech reader invariance: packaged checkpoint, audio alone, {args.items} instructions (lengths 1-10, "
             f"random phrasings, item seed {ITEM_SEED}) per engine, exact sequence.", "",
             "| Speech | Probe | Exact (%) |", "|---|---|---|"]
    lines += [f"| {engine} | {probe} | {value:.1f} |" for engine, probe, value in rows]
    lines += ["", f"Generated by `OMP_NUM_THREADS=1 python benchmarks/speech_invariance.py --items {args.items}` in "
              f"{time.perf_counter() - started:.0f} s."]
    print("\n".join(lines))
    if args.out is not None:
        args.out.write_text("\n".join(lines) + "\n")
    return rows


if __name__ == "__main__":
    main()
