"""Live commands: long recordings of spoken commands read through ``vafn_media.listen`` into the instruction queue.

Each recording holds ``--commands`` commands (1-4 arm ids, random phrasings) said by voices the reader never trained
on (espeak-ng's held-out voices, and Piper's neural voice where installed), separated by 0.3-5 s of silence, then a
30 s stretch without commands. The same speech is read under each condition: clean, white noise, and speech-like
babble (five overlapped streams of reversed espeak-ng sentences) at a signal-to-noise ratio relative to the commands'
speech. The recording is fed to the segmenter in 32 ms chunks (as fast as it is read, or in real time with
``--realtime``), every utterance goes through a :class:`vafn_media.MultimediaStream` into an ``InstructionQueue``.

Reported per condition: commands present, found (an utterance overlaps it), read right (exactly its arms enqueued, and
nothing else for it), acted on wrongly (something else enqueued for it), false triggers per minute (utterances
overlapping no command) and how many of those were enqueued, and end of speech -> enqueued latency (median, p95)
from the true end of each command's sound to the enqueue of its last piece. Fed faster than real time, that latency
is the audio the segmenter had to hear after the end (stream time) plus the wall time from closing the utterance to
the enqueue; ``--realtime`` measures it on the wall clock. Never asserts a number; the Free Spoken Digit Dataset is
not used.

    OMP_NUM_THREADS=1 python benchmarks/live_listen.py --commands 24 --out results/live
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

#: Conditions: name -> (white-noise SNR dB or None, babble SNR dB or None), relative to the commands' speech power.
CONDITIONS: dict[str, tuple[float | None, float | None]] = {
    "clean": (None, None),
    "white noise 20 dB": (20.0, None),
    "babble 20 dB": (None, 20.0),
    "babble 10 dB + white 30 dB": (30.0, 10.0),
}
GAP_S: tuple[float, float] = (0.3, 5.0)
TAIL_S: float = 30.0
LENGTHS: tuple[int, int] = (1, 4)
#: An utterance belongs to a command when their speech overlaps, with this tolerance (s) at both ends.
MATCH_TOLERANCE_S: float = 0.1
#: Text of the babble: ordinary sentences without the command words, said by espeak-ng and played backwards.
BABBLE_TEXT: tuple[str, ...] = (
    "the weather was lovely this morning so we walked along the river",
    "could you pass me the salt and the pepper please",
    "I think the meeting has been moved to the afternoon",
    "she bought a new bicycle last week and rides it to work",
    "the library closes early on saturdays in the summer",
    "we should paint the kitchen before the guests arrive",
    "my brother is learning to play the violin",
    "the train was late again because of the snow",
)
SEED = 6060


@dataclass
class Command:
    """One command in the recording: its arms, phrasing, voice and where its sound lies (seconds)."""

    arms: tuple[int, ...]
    text: str
    voice: str
    start_s: float
    end_s: float


def commit() -> str:
    """HEAD's short hash, with ``+dirty`` when this benchmark or vafn_media/listen.py differ from it."""
    root = Path(__file__).resolve().parents[1]
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=root).stdout
    changed = subprocess.run(["git", "status", "--porcelain", "--", "benchmarks/live_listen.py",
                              "vafn_media/listen.py"], capture_output=True, text=True, cwd=root).stdout
    return head.strip() + ("+dirty" if changed.strip() else "")


def command_speech(n_commands: int, rng: np.random.Generator) -> tuple[np.ndarray, list[Command]]:
    """The clean speech track at 16 kHz (commands between silences, then :data:`TAIL_S` without) and its commands."""
    from vafn_media.augment import resample
    from vafn_media.constants import SAMPLE_RATE
    from vafn_media.engines import available_engines, speak_with
    from vafn_media.speech import ESPEAK_SAMPLE_RATE, TEMPLATES, phrase, sample_voice, speak, trim_silence

    piper = "piper" in available_engines()
    parts, commands, at = [np.zeros(int(1.0 * SAMPLE_RATE), np.float32)], [], 1.0
    for index in range(n_commands):
        arms = tuple(int(a) for a in rng.integers(1, 4, rng.integers(LENGTHS[0], LENGTHS[1] + 1)))
        template = int(rng.integers(len(TEMPLATES)))
        if piper and index % 3 == 2:
            waveform, rate, voice = *speak_with("piper", arms, "joe", template), "piper joe"
        else:
            settings = sample_voice(rng, heldout=True)
            waveform, rate, voice = speak(arms, settings, template), ESPEAK_SAMPLE_RATE, settings.full_name
        clip = trim_silence(resample(waveform, rate, SAMPLE_RATE))
        clip = (clip * (0.3 / max(float(np.abs(clip).max()), 1e-6))).astype(np.float32)  # peak -10 dBFS
        commands.append(Command(arms, phrase(arms, template), voice, at, at + len(clip) / SAMPLE_RATE))
        gap = float(rng.uniform(*GAP_S))
        parts += [clip, np.zeros(int(gap * SAMPLE_RATE), np.float32)]
        at += (len(clip) + int(gap * SAMPLE_RATE)) / SAMPLE_RATE
    parts.append(np.zeros(int(TAIL_S * SAMPLE_RATE), np.float32))
    return np.concatenate(parts), commands


def babble(length: int, rng: np.random.Generator, streams: int = 5) -> np.ndarray:
    """Speech-like babble of ``length`` samples at 16 kHz: overlapped streams of reversed espeak-ng sentences."""
    from vafn_media.augment import resample
    from vafn_media.constants import SAMPLE_RATE
    from vafn_media.speech import ESPEAK_SAMPLE_RATE, EspeakSynthesizer, sample_voice, trim_silence

    synthesizer = EspeakSynthesizer.shared()
    sentences = [trim_silence(resample(synthesizer.synthesize(text, sample_voice(rng, heldout=False)),
                                       ESPEAK_SAMPLE_RATE, SAMPLE_RATE))[::-1] for text in BABBLE_TEXT]
    mix = np.zeros(length, np.float32)
    for _ in range(streams):
        at = int(rng.integers(0, SAMPLE_RATE))
        while at < length:
            sentence = sentences[rng.integers(len(sentences))]
            piece = sentence[: length - at] / max(float(np.sqrt(np.mean(sentence ** 2))), 1e-6)
            mix[at:at + len(piece)] += piece
            at += len(piece) + int(rng.uniform(0.05, 0.4) * SAMPLE_RATE)
    return mix


def condition_audio(speech: np.ndarray, commands: list[Command], condition: str,
                    rng: np.random.Generator) -> np.ndarray:
    """The speech track with the condition's noise and babble, each scaled to its SNR over the commands' speech."""
    from vafn_media.constants import SAMPLE_RATE

    noise_snr, babble_snr = CONDITIONS[condition]
    spans = np.concatenate([speech[int(c.start_s * SAMPLE_RATE):int(c.end_s * SAMPLE_RATE)] for c in commands])
    power = float(np.mean(spans.astype(np.float64) ** 2))
    audio = speech.copy()
    makers = ((noise_snr, lambda: rng.normal(size=len(speech))), (babble_snr, lambda: babble(len(speech), rng)))
    for snr, make in makers:
        if snr is None:
            continue
        noise = make().astype(np.float32)
        audio += noise * np.float32(np.sqrt(power / 10 ** (snr / 10) / float(np.mean(noise.astype(np.float64) ** 2))))
    return audio


def ideal_cut_right(audio: np.ndarray, commands: list[Command], generator) -> float:
    """Percent of commands read right (and not flagged) when each is cut from the recording exactly, 0.25 s around."""
    from vafn_media.constants import SAMPLE_RATE

    pad, right = int(0.25 * SAMPLE_RATE), 0
    for command in commands:
        clip = audio[max(0, int(command.start_s * SAMPLE_RATE) - pad):int(command.end_s * SAMPLE_RATE) + pad]
        result = generator.transcribe(audio=(clip, SAMPLE_RATE))
        right += result.arms == command.arms and not result.low_confidence
    return 100 * right / len(commands)


def run_condition(audio: np.ndarray, commands: list[Command], generator, realtime: bool,
                  segmenter_options: dict | None = None) -> dict:
    """Listen to one recording through a MultimediaStream; the condition's row of measurements."""
    from vafn_gym.queue import InstructionQueue
    from vafn_media import MultimediaStream
    from vafn_media.constants import SAMPLE_RATE
    from vafn_media.listen import RecordingSource, VoiceActivitySegmenter, listen

    instruction_queue = InstructionQueue(capacity=10_000)
    segmenter = VoiceActivitySegmenter(**(segmenter_options or {}))
    source = RecordingSource((audio, SAMPLE_RATE), realtime=realtime)
    with MultimediaStream(instruction_queue, generator) as stream:
        started = time.process_time()
        listener = listen(stream, source, segmenter, background=False)
        listen_cpu = time.process_time() - started
        stream.wait()
    events = {event.ticket: event for event in stream.events}
    entries = {entry.metadata["utterance"]: entry for entry in instruction_queue.snapshot()}
    matched: dict[int, list] = {i: [] for i in range(len(commands))}
    false_triggers = false_enqueued = 0
    for utterance in listener.utterances:
        overlapping = [i for i, c in enumerate(commands) if utterance.start_s < c.end_s + MATCH_TOLERANCE_S
                       and utterance.end_s > c.start_s - MATCH_TOLERANCE_S]
        for i in overlapping:
            matched[i].append(utterance)
        if not overlapping:
            false_triggers += 1
            false_enqueued += utterance.index in entries
    shared = {u.index for i, us in matched.items() for u in us
              if any(u in other for j, other in matched.items() if j != i)}
    found = right = joined = wrong = rejected = split = 0
    latencies = []
    for i, command in enumerate(commands):
        utterances = matched[i]
        found += bool(utterances)
        split += len(utterances) > 1
        read = [entries[u.index] for u in utterances if u.index in entries]
        if not read:
            rejected += bool(utterances)
            continue
        arms = [entry.instruction.arms for entry in read]
        if arms == [command.arms]:
            right += 1
        else:
            wrong += 1
        own = not any(u.index in shared for u in utterances)
        joined += own and sum(arms, ()) == command.arms and len(read) == len(utterances)
        last = [u for u in utterances if u.index in entries][-1]  # the whole command is queued with its last piece
        entry = entries[last.index]
        enqueued_at = entry.metadata["submitted_at"] + entry.metadata["latency_s"]
        end_arrived = (source.started_at + command.end_s if realtime
                       else last.detected_at - (last.detected_s - command.end_s))
        latencies.append(enqueued_at - end_arrived)
    minutes = len(audio) / SAMPLE_RATE / 60
    n = len(commands)
    assert len(events) == len(listener.utterances), "every utterance was submitted and handled"
    return {
        "commands": n, "found %": 100 * found / n, "read right %": 100 * right / n,
        "arms right, pieces joined %": 100 * joined / n,
        "read right, ideal cut %": ideal_cut_right(audio, commands, generator), "split %": 100 * split / n,
        "merged": len(shared),
        "acted on wrongly %": 100 * wrong / n, "found, rejected %": 100 * rejected / n,
        "utterances": len(listener.utterances), "false triggers / min": false_triggers / minutes,
        "false enqueued / min": false_enqueued / minutes,
        "latency median ms": 1e3 * float(np.median(latencies)) if latencies else float("nan"),
        "latency p95 ms": 1e3 * float(np.percentile(latencies, 95)) if latencies else float("nan"),
        "latency max ms": 1e3 * float(np.max(latencies)) if latencies else float("nan"),
        "minutes": minutes, "listen CPU s": listen_cpu, "errors": len(listener.errors) + len(stream.errors),
    }


def main(argv: list[str] | None = None) -> int:
    """Entry point: build the recordings, listen to each, write ``live_listen.csv`` and ``live_listen.md``."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--commands", type=int, default=24, help="commands per recording")
    parser.add_argument("--conditions", nargs="+", choices=list(CONDITIONS), default=list(CONDITIONS))
    parser.add_argument("--min-silence", type=float, nargs="+", default=[0.4, 0.2],
                        help="segmenter minimum silences to measure (s); the first is the default's")
    parser.add_argument("--realtime", action="store_true", help="feed the recordings in real time (wall-clock latency)")
    parser.add_argument("--seed", type=int, default=SEED)
    parser.add_argument("--out", type=Path, default=Path("results/live"))
    parser.add_argument("--name", default="live_listen", help="file name stem of the CSV and markdown table")
    args = parser.parse_args(argv)

    import torch

    from vafn_media import InstructionGenerator

    torch.set_num_threads(1)
    started = time.perf_counter()
    generator = InstructionGenerator.load()
    speech, commands = command_speech(args.commands, np.random.default_rng(args.seed))
    rows = []
    for offset, condition in enumerate(args.conditions):
        audio = condition_audio(speech, commands, condition, np.random.default_rng(args.seed + 1 + offset))
        for silence in args.min_silence:
            row = {"condition": condition, "min silence s": silence,
                   **run_condition(audio, commands, generator, args.realtime, {"min_silence_s": silence})}
            rows.append(row)
            print(", ".join(f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()),
                  flush=True)
    command = "OMP_NUM_THREADS=1 python benchmarks/live_listen.py " + " ".join(sys.argv[1:] if argv is None else argv)
    voices = sorted({c.voice.split("+")[0] for c in commands})
    header = (f"Command: `{command}` (commit {commit()}, {time.perf_counter() - started:.0f} s). {len(commands)} "
              f"commands of {LENGTHS[0]}-{LENGTHS[1]} arm ids by voices never trained on ({', '.join(voices)}), "
              f"{GAP_S[0]}-{GAP_S[1]} s of silence between them and {TAIL_S:.0f} s without commands at the end; "
              f"fed {'in real time' if args.realtime else 'faster than real time'} in 32 ms chunks; segmenter "
              f"defaults (Silero VAD, level gate 9 dB, 0.2 s pre-roll) but the minimum silence of each row. SNR "
              f"relative to the commands' speech.")
    args.out.mkdir(parents=True, exist_ok=True)
    columns = list(rows[0])
    with (args.out / f"{args.name}.csv").open("w", newline="") as handle:
        handle.write(f"# {header}\n")
        writer = csv.DictWriter(handle, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    lines = [header, "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        lines.append("| " + " | ".join(f"{row[c]:.1f}" if isinstance(row[c], float) else str(row[c])
                                       for c in columns) + " |")
    (args.out / f"{args.name}.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out / args.name}.csv and .md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
