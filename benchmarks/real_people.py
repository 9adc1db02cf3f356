"""Real people's commands: how often the robot acts on them correctly, and wrongly, per speaker and condition.

Instructions are said by the *test* speakers of a local spoken-word corpus and written with the *test* glyphs of
MNIST's training file (:mod:`vafn_media.people`); neither ever trains, validates, calibrates or chooses a checkpoint.
Each cell reports exact-sequence accuracy and the robot's two rates: *acted on correctly* (right and not flagged
``low_confidence``) and *acted on wrongly* (wrong and not flagged); a rejected input is neither.

    OMP_NUM_THREADS=1 python benchmarks/real_people.py --speech <corpus> --handwriting <mnist folder>

writes ``results/real_people/real_people.md`` (with the command and commit). ``--pocketsphinx`` adds
pocketsphinx 5's en-us model with a JSGF grammar of the command words as a reference reader (audio only).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from vafn_gym.files import repository_commit

RESULTS = Path(__file__).resolve().parents[1] / "results" / "real_people"
#: Seed of the benchmark's instructions and degradations (the selection split uses the training seed, never this).
SEED: int = 9100
#: Audio conditions: the corpus as recorded (16 kHz), telephone rate (8 kHz) and 8 kHz with 20 dB white noise.
AUDIO_CONDITIONS: tuple[str, ...] = ("clean", "8 kHz", "8 kHz + 20 dB")
#: Instruction lengths of the benchmark (the paper's easy and medium buckets).
LENGTHS: tuple[int, int] = (1, 5)


def audio_condition(waveform: np.ndarray, condition: str, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """The recorded instruction (at SAMPLE_RATE) under ``condition``: (waveform, rate)."""
    from vafn_media.augment import resample
    from vafn_media.constants import NOISE_SNR_DB, SAMPLE_RATE
    from vafn_media.corruptions import add_awgn

    if condition == "clean":
        return waveform, SAMPLE_RATE
    low = resample(waveform, SAMPLE_RATE, 8000)
    if condition == "8 kHz":
        return low, 8000
    return add_awgn(low, NOISE_SNR_DB, rng), 8000


def score(result, arms: tuple[int, ...]) -> tuple[bool, bool, bool]:
    """(exact, acted on correctly, acted on wrongly) of one reading (None: the input was rejected)."""
    if result is None:
        return False, False, False
    read = tuple(result.arms)
    flagged = bool(result.low_confidence)
    return read == arms, read == arms and not flagged, read != arms and not flagged


def safe(transcribe: Callable[..., object], **inputs):
    """``transcribe(**inputs)``, or None when the reader rejects the input (ValueError)."""
    try:
        return transcribe(**inputs)
    except ValueError:
        return None


def cells(transcribe: Callable[..., object], speech: Sequence[Path], handwriting: Path, sequences: int,
          strips: int) -> list[dict]:
    """Every cell of the table for one reader: each test recording alone and instructions of several test speakers'
    words, per condition and speaker, handwriting clean and Cutout, and audio + handwriting (8 kHz + 20 dB audio,
    Cutout handwriting).

    :param transcribe: ``InstructionGenerator.transcribe`` or a reference reader with the same signature.
    :param speech: the spoken-word corpus folder(s).
    :param handwriting: the MNIST training files.
    :param sequences: instructions of several words.
    :param strips: handwriting strips per condition.
    """
    from tqdm import tqdm

    from vafn_media.constants import SAMPLE_RATE
    from vafn_media.people import (SpokenWords, cutout_strip, handwriting_strip, handwritten_glyphs, load_word,
                                   say_instruction)

    words = SpokenWords.read(speech, "test")
    glyphs = handwritten_glyphs(str(handwriting), "test")
    outcomes: dict[tuple[str, str], list[tuple[bool, bool, bool]]] = {}
    singles = [(speaker, arm, path) for speaker, said in words.speakers.items() for arm, paths in said.items()
               for path in paths]
    bar = tqdm(total=len(singles) + sequences + strips, desc="real people", unit="command")
    for i, (speaker, arm, path) in enumerate(singles):  # every test recording alone, padded with silence
        rng = np.random.default_rng([SEED, 20_000, i])
        pad = np.zeros(int(0.3 * SAMPLE_RATE), np.float32)
        waveform = np.concatenate([pad, load_word(path), pad])
        for condition in AUDIO_CONDITIONS:
            outcomes.setdefault((f"one word, {condition}", speaker), []).append(
                score(safe(transcribe, audio=audio_condition(waveform, condition, rng)), (arm,)))
        bar.update()
    for i in range(sequences):
        rng = np.random.default_rng([SEED, i])
        arms = tuple(int(a) for a in rng.integers(1, 4, int(rng.integers(LENGTHS[0], LENGTHS[1] + 1))))
        waveform, _ = say_instruction(words, arms, rng)  # words of several speakers: reported together
        image = cutout_strip(handwriting_strip(glyphs, arms, rng), rng, fill=0)
        for condition in AUDIO_CONDITIONS:
            audio = audio_condition(waveform, condition, rng)
            outcomes.setdefault((f"sequence, {condition}", "all"), []).append(
                score(safe(transcribe, audio=audio), arms))
            if condition == AUDIO_CONDITIONS[-1]:
                outcomes.setdefault(("sequence, 8 kHz + 20 dB + handwriting Cutout", "all"), []).append(
                    score(safe(transcribe, audio=audio, image=image), arms))
        bar.update()
    for i in range(strips):
        rng = np.random.default_rng([SEED, 10_000, i])
        arms = tuple(int(a) for a in rng.integers(1, 4, int(rng.integers(LENGTHS[0], LENGTHS[1] + 1))))
        strip = handwriting_strip(glyphs, arms, rng)
        for name, image in (("clean", strip), ("Cutout", cutout_strip(strip, rng, fill=0))):
            outcomes.setdefault((f"handwriting {name}", "-"), []).append(score(safe(transcribe, image=image), arms))
        bar.update()
    bar.close()
    rows = [row(cell, who, results) for (cell, who), results in outcomes.items()]
    for cell in dict.fromkeys(c for c, _ in outcomes if c.startswith("one word")):  # every speaker together
        rows.append(row(cell, "all", [r for (c, w), rs in outcomes.items() if c == cell for r in rs]))
    return rows


def row(cell: str, who: str, results: list[tuple[bool, bool, bool]]) -> dict:
    """One table row: shares in % of exact readings, acted on correctly and acted on wrongly."""
    array = np.asarray(results, bool).reshape(-1, 3)
    return {"cell": cell, "speaker": who, "n": len(array), "exact": 100 * array[:, 0].mean(),
            "acted_right": 100 * array[:, 1].mean(), "acted_wrong": 100 * array[:, 2].mean()}


def pocketsphinx_reader() -> Callable[..., object]:
    """A ``transcribe(audio=(waveform, rate))`` of pocketsphinx 5's en-us model restricted by a JSGF grammar of the
    command words (its readings are never flagged)."""
    from types import SimpleNamespace

    from pocketsphinx import Decoder

    from vafn_media.augment import resample

    grammar = ("#JSGF V1.0; grammar arms; public <command> = [(move | arm)] <d> ([then | and] [arm] <d>)*; "
               "<d> = one | two | three;")
    decoder = Decoder(samprate=16000, lm=None)
    decoder.set_jsgf_string("arms", grammar)
    decoder.activate_search("arms")
    numbers = {"one": 1, "two": 2, "three": 3}

    def transcribe(audio) -> SimpleNamespace:
        waveform, rate = audio
        pcm = (np.clip(resample(waveform, rate, 16000), -1, 1) * 32767).astype(np.int16).tobytes()
        decoder.start_utt()
        decoder.process_raw(pcm, full_utt=True)
        decoder.end_utt()
        text = decoder.hyp().hypstr if decoder.hyp() is not None else ""
        return SimpleNamespace(arms=tuple(numbers[w] for w in text.split() if w in numbers), low_confidence=False)

    return lambda audio=None, image=None: None if audio is None else transcribe(audio)


def write(rows: list[dict], out: Path, header: str) -> None:
    """The table as markdown, every reader, cell and speaker."""
    out.mkdir(parents=True, exist_ok=True)
    lines = [header, "", "| reader | cell | speaker | n | exact % | acted on correctly % | acted on wrongly % |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['reader']} | {r['cell']} | {r['speaker']} | {r['n']} | {r['exact']:.1f} | {r['acted_right']:.1f} "
              f"| {r['acted_wrong']:.1f} |" for r in sorted(rows, key=lambda r: (r["reader"], r["cell"],
                                                                                  r["speaker"] != "all"))]
    (out / "real_people.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> list[dict]:
    """Run the benchmark and write its tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speech", type=Path, nargs="+", required=True,
                        help="the spoken-word corpus folder or folders (vafn_media.people)")
    parser.add_argument("--handwriting", type=Path, required=True, help="folder with MNIST's training files")
    parser.add_argument("--checkpoint", type=Path, default=None, help="reader checkpoint (default: the packaged one)")
    parser.add_argument("--sequences", type=int, default=300, help="instructions of 1-5 words of several speakers")
    parser.add_argument("--strips", type=int, default=300, help="handwriting strips per condition")
    parser.add_argument("--pocketsphinx", action="store_true", help="add the pocketsphinx reference (audio only)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    import torch

    from vafn_media.generator import InstructionGenerator

    torch.set_num_threads(1)
    started = time.time()
    generator = InstructionGenerator.load(args.checkpoint)
    rows = [{"reader": "vafn", **r} for r in cells(generator.transcribe, args.speech, args.handwriting,
                                                   args.sequences, args.strips)]
    if args.pocketsphinx:
        rows += [{"reader": "pocketsphinx", **r} for r in cells(pocketsphinx_reader(), args.speech, args.handwriting,
                                                                args.sequences, 0) if "handwriting" not in r["cell"]]
    corpora = " ".join(f"<{p.name}>" for p in args.speech)
    command = (f"python benchmarks/real_people.py --speech {corpora} --handwriting <MNIST training files> "
               f"--sequences {args.sequences} --strips {args.strips}" + " --pocketsphinx" * args.pocketsphinx
               + (f" --checkpoint {args.checkpoint.name}" if args.checkpoint else ""))
    root = Path(__file__).resolve().parents[1]
    header = (f"# Real people's commands\n\nCommit {repository_commit(root)}; `{command}`; "
              f"{time.time() - started:.0f} s. Test speakers and glyphs only (vafn_media.people).")
    write(rows, args.out, header)
    print((args.out / "real_people.md").read_text())
    return rows


if __name__ == "__main__":
    main()
