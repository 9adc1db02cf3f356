"""vafn-demo: spoken, written or typed instructions move three arms, end to end (the paper's Fig. 1).

Each input (``--audio``, ``--image``, ``--code``, in command-line order) is submitted to a
:class:`vafn_media.MultimediaStream`, which transcribes it on a background thread into the Dynamic Instruction Queue of
``VAFN/ThreeArmStream-v1`` while :class:`vafn_sb3.OnlineController` runs the packaged pretrained policy on the arms.
Writes a labelled video (MP4, or GIF without imageio-ffmpeg) and a PNG timeline into ``--out`` and prints each
instruction's outcome and latency. ``--listen`` takes spoken commands live instead (a microphone, a recording replayed
in real time, or 16-bit PCM on stdin), each utterance found by :mod:`vafn_media.listen` as it ends. Without inputs it
runs a built-in example. Exit status: 0 every instruction succeeded, 1 some were rejected or failed (or none was
heard), 2 bad input.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

AUDIO_SUFFIXES = (".wav", ".flac", ".ogg")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
CODE_SUFFIXES = (".txt",)
ENV_ID = "VAFN/ThreeArmStream-v1"
#: Built-in example: (kind, arm ids) in arrival order; speech is used where espeak-ng is installed.
EXAMPLE_SPEECH = ("audio", (2, 3, 1))
EXAMPLE_REST = (("image", (1, 3)), ("code", (3, 2)))
EXAMPLE_NO_SPEECH = (("code", (2, 3, 1)), ("image", (1, 3)), ("image", (3, 2)))
#: Steps the video keeps running after the last instruction settled (so its final state is visible).
TAIL_STEPS = 24
#: Video frame sides (pixels) --size accepts.
MIN_FRAME_SIDE = 16
MAX_FRAME_SIDE = 1920
#: While the arms are idle and an input is still being read, wait (poll period, s) instead of spending control steps
#: (the simulation runs faster than real time, so a slow first transcription would otherwise use up --max-steps),
#: at most this long (s) per input.
READER_POLL_S = 0.01
READER_WAIT_S = 60.0


class DemoInputError(ValueError):
    """A command-line input that cannot be used (missing file, unknown file type, malformed code)."""


@dataclass
class DemoInput:
    """One instruction source, in arrival order.

    :param kind: "audio", "image" or "code".
    :param value: a file path, an in-memory array or a code string (what ``transcribe`` takes).
    :param label: how reports name it (file name or code).
    """

    kind: str
    value: Any
    label: str


@dataclass
class Outcome:
    """What happened to one input: transcription, queueing, execution and latencies (seconds; NaN if not reached)."""

    index: int
    kind: str
    label: str
    status: str = "pending"
    instruction: str = ""
    confidence: float = float("nan")
    message: str = ""
    submit_step: int = -1
    arrival_step: int = -1
    start_step: int = -1
    end_step: int = -1
    transcribe_s: float = float("nan")
    arrival_to_first_action_s: float = float("nan")
    dequeue_to_first_action_s: float = float("nan")
    submit_to_first_action_s: float = float("nan")
    completion_wall_s: float = float("nan")
    waypoints_reached: int = 0
    collisions: int = 0

    @property
    def executed(self) -> bool:
        """Whether the instruction reached the arms."""
        return self.start_step >= 0


@dataclass
class DemoResult:
    """Outcomes in input order, the written files and the wall time of the run."""

    outcomes: list[Outcome]
    video: Path | None
    timeline: Path
    steps: int
    wall_s: float
    frames: int = 0
    errors: list[str] = field(default_factory=list)

    @property
    def all_succeeded(self) -> bool:
        """Whether every input was executed and completed without contact."""
        return all(o.status == "completed" for o in self.outcomes)


class _Ordered(argparse.Action):
    """Appends ``(kind, value)`` to ``namespace.inputs`` so --audio/--image/--code keep their command-line order."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        items = list(getattr(namespace, "inputs", None) or [])
        items.append((self.dest, values))
        namespace.inputs = items


def expand_inputs(pairs: Sequence[tuple[str, str]]) -> list[DemoInput]:
    """Command-line ``(kind, value)`` pairs -> inputs; folders expand to their files sorted by name.

    ``kind`` is "audio", "image", "code" or "folder" (a folder of mixed files: the suffix gives the kind, ``.txt``
    files hold machine code). Raises :class:`DemoInputError` naming the first unusable input.
    """
    from vafn_gym.instructions import Instruction

    suffixes = {"audio": AUDIO_SUFFIXES, "image": IMAGE_SUFFIXES, "code": CODE_SUFFIXES}
    inputs: list[DemoInput] = []
    for kind, value in pairs:
        if kind == "code":
            inputs.append(DemoInput("code", _check_code(value, Instruction), value))
            continue
        path = Path(value)
        if not path.exists():
            raise DemoInputError(f"--{kind} {value}: no such file or folder")
        if path.is_dir():
            wanted = {k: v for k, v in suffixes.items() if kind == "folder" or k == kind}
            known = {suffix for group in wanted.values() for suffix in group}
            files = sorted(f for f in path.iterdir() if f.is_file() and f.suffix.lower() in known)
            if not files:
                names = ", ".join(s for group in wanted.values() for s in group)
                raise DemoInputError(f"--{kind} {value}: the folder holds no {names} file")
            for file in files:
                file_kind = next(k for k, s in wanted.items() if file.suffix.lower() in s)
                if file_kind == "code":
                    inputs.append(DemoInput("code", _check_code(file.read_text().strip(), Instruction), file.name))
                else:
                    inputs.append(DemoInput(file_kind, str(file), file.name))
        elif kind == "folder":
            raise DemoInputError(f"--inputs {value}: not a folder")
        elif path.suffix.lower() not in suffixes[kind]:
            raise DemoInputError(f"--{kind} {value}: expected a {'/'.join(suffixes[kind])} file")
        else:
            inputs.append(DemoInput(kind, str(path), path.name))
    return inputs


def _check_code(code: str, instruction_class: Any) -> str:
    """``code`` if it parses as a three-arm instruction, else :class:`DemoInputError` saying why."""
    try:
        instruction_class.coerce(code, n_arms=3)
    except (ValueError, TypeError) as error:
        raise DemoInputError(f"--code {code!r}: {error}") from error
    return code


def speech_available() -> bool:
    """Whether espeak-ng can synthesise speech here (the optional espeakng-loader package)."""
    try:
        from vafn_media.speech import EspeakSynthesizer

        EspeakSynthesizer.shared()
    except (ImportError, OSError, RuntimeError):
        return False
    return True


def builtin_example(folder: Path, speech: bool | None = None) -> list[DemoInput]:
    """Write the built-in example's input files into ``folder`` and return them as inputs.

    With espeak-ng: a spoken "arm two, then three, then one", a card image of 1 3 and the code "3,2"; without it:
    the code "2,3,1" and card images of 1 3 and 3 2 (drawn by the package's own strip renderer).
    """
    from PIL import Image

    from vafn_media.strips import render_strip

    speech = speech_available() if speech is None else speech
    folder.mkdir(parents=True, exist_ok=True)
    plan = ((EXAMPLE_SPEECH,) + EXAMPLE_REST) if speech else EXAMPLE_NO_SPEECH
    inputs = []
    for index, (kind, arms) in enumerate(plan, start=1):
        stem = f"{index}_{kind}_{''.join(map(str, arms))}"
        if kind == "audio":
            import soundfile

            from vafn_media.speech import ESPEAK_SAMPLE_RATE, phrase, speak

            path = folder / f"{stem}.wav"
            silence = np.zeros(int(0.3 * ESPEAK_SAMPLE_RATE), np.float32)  # a recording starts and ends quiet
            soundfile.write(path, np.concatenate([silence, speak(arms, template=2), silence]), ESPEAK_SAMPLE_RATE)
            inputs.append(DemoInput("audio", str(path), f"{path.name} (\"{phrase(arms, 2)}\")"))
        elif kind == "image":
            path = folder / f"{stem}.png"
            Image.fromarray(render_strip(arms, np.random.default_rng(index + 2))).save(path)
            inputs.append(DemoInput("image", str(path), path.name))
        else:
            code = ",".join(map(str, arms))
            inputs.append(DemoInput("code", code, code))
    return inputs


def load_policy(policy: str = "sac", model_path: str | None = None, trust_remote_code: bool = False) -> Any:
    """The packaged policy of algorithm ``policy``, or the saved model at ``model_path`` (a weights-only file, or an
    SB3 zip rebuilt without unpickling; SB3's own load with ``trust_remote_code``: see
    :func:`vafn_sb3.loading.load_model`)."""
    if model_path is not None:
        from vafn_sb3.loading import load_model

        return load_model(model_path, trust_remote_code=trust_remote_code)[0]
    from vafn_sb3 import load_pretrained

    return load_pretrained(policy)


def run_demo(
    inputs: Sequence[DemoInput], out: Path, model: Any = None, generator: Any = None, interval: int = 60,
    max_steps: int = 3000, width: int = 400, height: int = 300, frame_skip: int = 4, video: str = "auto",
    min_confidence: float | None = None, seed: int = 0, progress: bool = True, listener: Any = None,
) -> DemoResult:
    """Feed ``inputs`` through the multimedia stream into the queue while the controller moves the arms.

    :param inputs: the instruction sources, submitted one every ``interval`` steps from step 0.
    :param out: folder for ``demo.mp4`` / ``demo.gif``, ``timeline.png`` and ``outcomes.csv``.
    :param model: policy with SB3's ``predict`` (default: the packaged SAC).
    :param generator: an ``InstructionGenerator`` (default: the packaged one).
    :param interval: control steps between two submissions.
    :param max_steps: stop after this many control steps even if instructions are still running.
    :param width: video frame width.
    :param height: video frame height.
    :param frame_skip: keep every N-th control step as a video frame.
    :param video: "mp4", "gif", "auto" (MP4 where imageio-ffmpeg is installed) or "none".
    :param min_confidence: transcriptions below it are rejected (default: the stream's threshold).
    :param seed: seed of the stream env.
    :param progress: show a progress bar.
    :param listener: a :class:`vafn_media.listen.Listener`, not started: each utterance it hears is submitted as an
        audio input at once (``inputs`` may be empty); the run ends when its source ends (Ctrl-C for a microphone).
    """
    import gymnasium as gym
    from tqdm import tqdm

    import vafn_gym  # noqa: F401  (registers the env IDs)
    from vafn_gym.overlay import FrameOverlay, VideoWriter, frame_rate, mp4_available
    from vafn_media import MultimediaStream
    from vafn_sb3.online import OnlineController

    if not inputs and listener is None:
        raise DemoInputError("no inputs to run")
    inputs = list(inputs)
    if interval < 0 or max_steps < 1 or frame_skip < 1:
        raise ValueError(f"need interval >= 0, max_steps >= 1, frame_skip >= 1; got {interval}, {max_steps}, "
                         f"{frame_skip}")
    out.mkdir(parents=True, exist_ok=True)
    model = load_policy() if model is None else model
    env = gym.make(ENV_ID, arrivals=None, auto_dequeue=False, horizon=max_steps + 1, render_mode="rgb_array",
                   render_width=width, render_height=height)
    stream_env = env.unwrapped
    controller = OnlineController(model, env, seed=seed)
    outcomes = [Outcome(i + 1, item.kind, item.label) for i, item in enumerate(inputs)]
    by_ticket: dict[int, Outcome] = {}
    enqueued: list[Outcome] = []  # the k-th enqueued event is queue sequence k: one worker, nothing else enqueues

    def on_event(event: Any) -> None:
        outcome = by_ticket[event.ticket]
        result = event.transcription
        if result is not None:
            outcome.instruction = result.instruction.to_code()
            outcome.confidence = float(result.confidence)
        outcome.transcribe_s = event.latency_s
        outcome.message = event.message
        if event.status == "enqueued":
            outcome.status = "queued"
            outcome.arrival_step = stream_env.total_steps
            enqueued.append(outcome)
        else:
            outcome.status = event.status  # "rejected" (low confidence) or "error" (bad input)

    kwargs = {} if min_confidence is None else {"min_confidence": float(min_confidence)}
    if generator is None:
        from vafn_media import InstructionGenerator

        generator = InstructionGenerator.load()
    media = MultimediaStream(stream_env.queue, generator, on_event=on_event, **kwargs).start()
    suffix = {"auto": ".mp4" if mp4_available() else ".gif", "mp4": ".mp4", "gif": ".gif"}.get(video)
    writer = VideoWriter(out / f"demo{suffix}", frame_rate(env, frame_skip)) if suffix else None
    overlay = FrameOverlay(env)
    submitted_at: dict[int, float] = {}
    started = time.perf_counter()
    step, tail, next_input, heard = 0, None, 0, 0
    bar = tqdm(total=len(inputs) or None, desc="vafn-demo", unit="instruction", disable=not progress)
    if listener is not None:
        listener.start()
    try:
        while step < max_steps:
            listening = listener is not None and not listener.finished  # before taking: no utterance is missed
            if listener is not None:
                heard = _take_utterances(listener, heard, inputs, outcomes)
            while next_input < len(inputs) and (listener is not None or step >= next_input * interval):
                item = inputs[next_input]
                outcome = outcomes[next_input]
                ticket = media.submit(**{item.kind: item.value}, metadata={"input": next_input + 1})
                by_ticket[ticket] = outcome
                outcome.submit_step, outcome.status = step, "transcribing"
                submitted_at[next_input] = time.perf_counter()
                next_input += 1
            idle = not any(o.status in ("queued", "running") for o in outcomes)
            if _arms_wait_for_reader(outcomes, submitted_at) or (listening and idle):
                time.sleep(READER_POLL_S)
                continue
            info = controller.step()
            step += 1
            _update_from_log(controller.log, enqueued, submitted_at, started)
            if writer is not None and step % frame_skip == 0:
                writer.append(overlay(env.render(), info, notes=_notes(stream_env, enqueued, outcomes)))
            settled = sum(o.status not in ("pending", "transcribing", "queued", "running") for o in outcomes)
            if settled != bar.n:
                bar.update(settled - bar.n)
            if tail is None and next_input == len(inputs) and settled == len(outcomes) and not listening:
                tail = step + TAIL_STEPS
            if tail is not None and step >= tail:
                break
    except KeyboardInterrupt:  # Ctrl-C ends listening to a microphone; the report follows
        if listener is None:
            raise
    finally:
        if listener is not None:
            listener.stop()
        bar.close()
        media.stop(drain=False, timeout=5.0)
        frames = writer.n_frames if writer is not None else 0
        video_path = writer.close() if writer is not None and frames else None
        controller.close()
        env.close()
    for outcome in outcomes:
        if outcome.status in ("pending", "transcribing", "queued", "running"):
            outcome.status = "not finished" if outcome.status == "running" else "not started"
            outcome.message = outcome.message or f"still {outcome.status} after {max_steps} steps (raise --max-steps)"
    timeline = plot_timeline(controller, outcomes, out / "timeline.png", step)
    write_outcomes(outcomes, out / "outcomes.csv")
    errors = list(controller.errors) + list(media.errors)
    return DemoResult(outcomes, video_path, timeline, step, time.perf_counter() - started, frames, errors)


def _take_utterances(listener: Any, taken: int, inputs: list[DemoInput], outcomes: list[Outcome]) -> int:
    """Append the utterances the listener heard after the first ``taken`` as audio inputs; returns how many it heard."""
    utterances = list(listener.utterances)
    for utterance in utterances[taken:]:
        label = f"heard {utterance.start_s:.1f}-{utterance.end_s:.1f} s"
        inputs.append(DemoInput("audio", (utterance.waveform, utterance.rate), label))
        outcomes.append(Outcome(len(outcomes) + 1, "audio", label))
    return len(utterances)


def _update_from_log(log: Sequence[Any], enqueued: Sequence[Outcome], submitted_at: dict[int, float],
                     started: float) -> None:
    """Copy the controller's per-instruction log (start, first action, end) into the outcomes."""
    for entry in log:
        if entry.sequence >= len(enqueued):
            continue
        outcome = enqueued[entry.sequence]
        if outcome.start_step < 0:
            outcome.start_step = entry.start_step
            outcome.status = "running"
        if np.isfinite(entry.first_action_time):
            outcome.arrival_to_first_action_s = entry.latency_s
            outcome.dequeue_to_first_action_s = entry.service_latency_s
            outcome.submit_to_first_action_s = entry.first_action_time - submitted_at[outcome.index - 1]
        outcome.collisions = entry.collisions
        if entry.outcome != "running" and outcome.status == "running":
            outcome.end_step = entry.completion_step
            outcome.waypoints_reached = entry.waypoints_reached
            outcome.completion_wall_s = time.perf_counter() - submitted_at[outcome.index - 1]
            if entry.outcome == "completed":
                outcome.status = "completed" if entry.success else "completed with contact"
            else:
                outcome.status = entry.outcome


def _notes(stream_env: Any, enqueued: Sequence[Outcome], outcomes: Sequence[Outcome]) -> list[str]:
    """The video's extra line: where the running instruction came from, and how many wait in the queue."""
    current = stream_env.current
    waiting = len(stream_env.queue)
    if current is not None and current.sequence < len(enqueued):
        source = enqueued[current.sequence]
        line = f"#{source.index} from {source.kind}: {source.label}"[:60]
    else:
        line = "queue empty: holding" if not waiting else "starting next instruction"
    done = sum(o.status == "completed" for o in outcomes)
    return [f"{line} | queued {waiting} | done {done}/{len(outcomes)}"]


def _arms_wait_for_reader(outcomes: Sequence[Outcome], submitted_at: dict[int, float]) -> bool:
    """True while nothing is queued or running and an input submitted under ``READER_WAIT_S`` ago is being read."""
    if any(o.status in ("queued", "running") for o in outcomes):
        return False
    now = time.perf_counter()
    return any(
        o.status == "transcribing" and now - submitted_at.get(i, now) < READER_WAIT_S for i, o in enumerate(outcomes)
    )


def plot_timeline(controller: Any, outcomes: Sequence[Outcome], path: Path, n_steps: int) -> Path:
    """PNG: each arm's distance to its target (top) and one row per input: queued, executing, outcome (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vafn_gym.constants import SUCCESS_TOLERANCE

    layout = controller.stream.layout
    steps = np.asarray(controller.trace["step"])
    distances = np.asarray(controller.trace["distances"]).reshape(len(steps), -1) if len(steps) else np.zeros((0, 3))
    fig, (top, bottom) = plt.subplots(
        2, 1, figsize=(11, 3.2 + 0.45 * len(outcomes)), sharex=True,
        gridspec_kw={"height_ratios": [2.2, 0.6 + 0.35 * len(outcomes)]},
    )
    for column, arm in enumerate(layout.arm_ids[: distances.shape[1]]):
        top.plot(steps, distances[:, column], lw=1.2, color=layout.colour(arm, 1.0), label=f"arm {arm}")
    top.axhline(SUCCESS_TOLERANCE, color="k", ls="--", lw=0.8, label=f"tolerance {SUCCESS_TOLERANCE} m")
    top.set_ylabel("distance to target (m)")
    top.legend(fontsize=8, loc="upper right", ncol=4)
    top.set_title("vafn-demo: instructions through the multimedia stream, executed by the online controller",
                  fontsize=10)
    for row, outcome in enumerate(outcomes):
        y = len(outcomes) - 1 - row
        if outcome.arrival_step >= 0:
            start = outcome.start_step if outcome.start_step >= 0 else n_steps
            bottom.broken_barh([(outcome.arrival_step, max(start - outcome.arrival_step, 0.5))], (y - 0.3, 0.6),
                               color="lightgrey")
        if outcome.start_step >= 0:
            end = outcome.end_step if outcome.end_step >= 0 else n_steps
            colour = "tab:green" if outcome.status == "completed" else "tab:red"
            bottom.broken_barh([(outcome.start_step, max(end - outcome.start_step, 0.5))], (y - 0.3, 0.6), color=colour)
        if outcome.submit_step >= 0:
            bottom.plot([outcome.submit_step], [y], marker="v", color="k", ms=5)
        what = f"[{outcome.instruction}]" if outcome.instruction else ""
        text = f"#{outcome.index} {outcome.kind} {outcome.label[:28]} {what}: {outcome.status}"
        bottom.text(max(outcome.submit_step, 0) + 3, y + 0.33, text, fontsize=7, va="bottom")
    bottom.set_yticks([])
    bottom.set_ylim(-0.6, len(outcomes) - 0.1 + 0.3)
    bottom.set_xlabel("control step (▼ submitted, grey: queued, green: executed and completed, red: failed)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_outcomes(outcomes: Sequence[Outcome], path: Path) -> Path:
    """The outcomes as CSV, one row per input."""
    import csv
    from dataclasses import asdict, fields

    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=[f.name for f in fields(Outcome)])
        writer.writeheader()
        for outcome in outcomes:
            writer.writerow(asdict(outcome))
    return path


def format_outcome(outcome: Outcome, fps: float) -> str:
    """One report line: source, transcription, outcome and latencies."""
    head = f"#{outcome.index} {outcome.kind:<5} {outcome.label}"
    if outcome.status in ("rejected", "error"):
        reason = "low confidence, not executed" if outcome.status == "rejected" else "not executed"
        read = f" read [{outcome.instruction}]" if outcome.instruction else ""
        return f"{head}:{read} {outcome.status.upper()} ({reason}): {outcome.message}"
    parts = [f"{head} -> [{outcome.instruction}] (confidence {outcome.confidence:.2f}): {outcome.status}"]
    if outcome.executed:
        parts.append(f"transcribed in {1e3 * outcome.transcribe_s:.0f} ms, queue arrival -> first action "
                     f"{1e3 * outcome.arrival_to_first_action_s:.0f} ms (of which dequeue -> first action "
                     f"{1e3 * outcome.dequeue_to_first_action_s:.1f} ms)")
    if outcome.end_step >= 0:
        steps = outcome.end_step - outcome.start_step
        parts.append(f"done after {steps} steps ({steps / fps:.1f} s simulated, {outcome.completion_wall_s:.1f} s "
                     f"wall from submission), {outcome.collisions} contact steps")
    elif outcome.message:
        parts.append(outcome.message)
    return "; ".join(parts)


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface (defaults shown in --help)."""
    from vafn_media.cli import OneLineParser
    from vafn_sb3.loading import add_trust_flag

    parser = OneLineParser(
        prog="vafn-demo", description=__doc__.split("\n\n")[0],
        epilog="Example: vafn-demo --audio cmd.wav --image card.png --code 3,2 --out runs/demo",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.set_defaults(inputs=[])
    parser.add_argument("--audio", action=_Ordered, metavar="FILE|DIR",
                        help="spoken instruction (WAV/FLAC/OGG), or a folder of them; repeatable")
    parser.add_argument("--image", action=_Ordered, metavar="FILE|DIR",
                        help="image of digits 1-3 in a row (PNG/JPG/...), or a folder of them; repeatable")
    parser.add_argument("--code", action=_Ordered, metavar="CODE", help='machine code, e.g. "2,3,1"; repeatable')
    parser.add_argument("--inputs", action=_Ordered, dest="folder", metavar="DIR",
                        help="a folder of mixed inputs, run in file-name order (.txt files hold machine code)")
    parser.add_argument("--out", type=Path, default=Path("runs/demo"), help="folder for the video, timeline, CSV")
    parser.add_argument("--policy", default="sac", help="packaged pretrained policy (algorithm key)")
    parser.add_argument("--model", default=None,
                        help="a saved model to run instead of the packaged one: a weights-only file "
                             "(vafn_sb3.save_weights), or an SB3 .zip with --trust-remote-code")
    add_trust_flag(parser)
    parser.add_argument("--checkpoint", default=None, help="instruction model (.pt); default: the packaged one")
    parser.add_argument("--interval", type=int, default=60, help="control steps between two submissions")
    parser.add_argument("--max-steps", type=int, default=3000, help="stop after this many control steps")
    parser.add_argument("--video", choices=["auto", "mp4", "gif", "none"], default="auto",
                        help="video format (auto: MP4 where imageio-ffmpeg is installed, else GIF)")
    parser.add_argument("--size", type=int, nargs=2, default=(400, 300), metavar=("W", "H"), help="video frame size")
    parser.add_argument("--frame-skip", type=int, default=4, help="keep every N-th control step as a frame")
    parser.add_argument("--min-confidence", type=float, default=None,
                        help="reject transcriptions below this confidence (default: the stream's 0.5)")
    parser.add_argument("--listen", nargs="?", const="mic", default=None, metavar="FILE",
                        help="spoken commands live: from the microphone (needs sounddevice), a recording replayed in "
                             "real time, or '-' for 16-bit 16 kHz mono PCM on stdin; each utterance is read as it ends")
    parser.add_argument("--no-speech", action="store_true", help="built-in example without synthesised speech")
    parser.add_argument("--seed", type=int, default=0, help="seed of the stream env")
    return parser


def _fail(message: str) -> int:
    """Print one error line (newlines folded) and return exit status 2."""
    from vafn_media.cli import error_line

    print(error_line("vafn-demo", message), end="", file=sys.stderr)
    return 2


def _writable_folder(out: Path) -> None:
    """Create ``out`` (--out) or raise :class:`DemoInputError` saying why it cannot hold the outputs."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise DemoInputError(f"--out {out}: cannot create the folder ({error.strerror or error})") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise DemoInputError(f"--out {out}: the folder is not writable")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``vafn-demo``; returns the exit status (0 all succeeded, 1 some did not, 2 bad input)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.interval < 0 or args.max_steps < 1 or args.frame_skip < 1:
        parser.error("need --interval >= 0, --max-steps >= 1 and --frame-skip >= 1")
    if not all(MIN_FRAME_SIDE <= side <= MAX_FRAME_SIDE for side in args.size):
        parser.error(f"--size {args.size[0]} {args.size[1]}: each side must be {MIN_FRAME_SIDE} to {MAX_FRAME_SIDE}")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        _writable_folder(args.out)
        inputs = expand_inputs(args.inputs)
    except DemoInputError as error:
        return _fail(str(error))
    listener = None
    if args.listen is not None:
        from vafn_media.listen import Listener, LiveInputError, open_source

        try:
            listener = Listener(open_source(None if args.listen == "mic" else args.listen))
        except LiveInputError as error:
            return _fail(str(error))
    import torch

    torch.set_num_threads(1)
    started = time.perf_counter()
    if not inputs and listener is None:
        inputs = builtin_example(args.out / "inputs", speech=False if args.no_speech else None)
        print(f"no inputs given: running the built-in example ({', '.join(i.kind for i in inputs)}) "
              f"from {args.out / 'inputs'}")
    try:
        from vafn_media import InstructionGenerator

        generator = InstructionGenerator.load(args.checkpoint)
        model = load_policy(args.policy, args.model, args.trust_remote_code)
    except (ValueError, OSError) as error:
        return _fail(str(error))
    except MemoryError:
        return _fail(f"loading {args.model or args.policy} needs more memory than this machine has")
    result = run_demo(inputs, args.out, model=model, generator=generator, interval=args.interval,
                      max_steps=args.max_steps, width=args.size[0], height=args.size[1], frame_skip=args.frame_skip,
                      video=args.video, min_confidence=args.min_confidence, seed=args.seed, listener=listener)
    from vafn_gym.constants import N_SUBSTEPS, PHYSICS_DT

    for outcome in result.outcomes:
        print(format_outcome(outcome, 1.0 / (PHYSICS_DT * N_SUBSTEPS)))
    for error in result.errors + (listener.errors if listener is not None else []):
        print("error:", error)
    video = f"{result.video} ({result.frames} frames), " if result.video else ""
    print(f"wrote {video}{result.timeline} and {args.out / 'outcomes.csv'}")
    succeeded = sum(o.status == "completed" for o in result.outcomes)
    print(f"{succeeded}/{len(result.outcomes)} instructions completed without contact in {result.steps} control "
          f"steps; {time.perf_counter() - started:.1f} s in all (models loaded, video written)")
    return 0 if result.all_succeeded and result.outcomes else 1


if __name__ == "__main__":
    sys.exit(main())
