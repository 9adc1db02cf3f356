"""``vafn-instruct``: read an instruction from a speech file, an image and/or machine code,
print it with confidences."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from typing import NoReturn


def error_line(prog: str, message: object) -> str:
    """``<prog>: error: <message>`` as one line (its newlines folded), ending in a newline."""
    return f"{prog}: error: {' '.join(str(message).split())}\n"


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line on stderr and exit code 2 (every vafn command line)."""

    def error(self, message: str) -> NoReturn:
        """A usage error: print ``<prog>: error: <message> (see --help)`` on one line and exit 2."""
        self.exit(2, error_line(self.prog, f"{message} (see --help)"))

    def fail(self, message: object) -> NoReturn:
        """Bad input found after parsing (a file, a value): print ``<prog>: error: <message>`` and exit 2."""
        self.exit(2, error_line(self.prog, message))


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    parser = OneLineParser(prog="vafn-instruct", description=__doc__)
    parser.add_argument("--audio", help="speech file (WAV/FLAC/OGG, any sample rate from 8 to 192 kHz)")
    parser.add_argument("--image", help="image of digits 1-3 in a left-to-right row (PNG/JPG/...)")
    parser.add_argument("--code", help='machine code, e.g. "2,3,1" or "[2, 3, 1]"; "" is the empty instruction')
    parser.add_argument("--checkpoint", help="model checkpoint (.pt); default: the packaged one")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    return parser


def _fail(message: str) -> int:
    """Print one error line (newlines folded) and return exit code 2."""
    print(error_line("vafn-instruct", message), end="", file=sys.stderr)
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code (0 ok, 2 bad input, one line on stderr)."""
    args = build_parser().parse_args(argv)
    if args.audio is None and args.image is None and args.code is None:
        return _fail("give at least one of --audio, --image, --code (see --help)")
    for option in ("audio", "image", "checkpoint"):  # path errors before the slow imports (torch, OpenCV)
        path = getattr(args, option)
        if path is not None and not os.path.isfile(path):
            what = "does not exist" if not os.path.exists(path) else "is not a file"
            return _fail(f"--{option} {path!r} {what}")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        import torch

        from vafn_media.generator import InstructionGenerator

        torch.set_num_threads(1)
        generator = InstructionGenerator.load(args.checkpoint)
        result = generator.transcribe(audio=args.audio, image=args.image, code=args.code)
    except (ValueError, OSError, RuntimeError, ImportError) as error:
        return _fail(str(error))
    if args.json:
        print(json.dumps({
            "instruction": list(result.arms), "code": result.instruction.to_code(),
            "confidences": [round(c, 4) for c in result.confidences], "confidence": round(result.confidence, 4),
            "low_confidence": result.low_confidence, "modalities": list(result.modalities), "method": result.method,
            "readings": {k: list(v) for k, v in result.readings.items()}, "warnings": list(result.warnings),
            "latency_ms": round(1000 * result.latency_s, 3),
        }))
    else:
        print(f"instruction: {result.instruction}")
        print("confidences: " + " ".join(f"{arm}:{c:.3f}" for arm, c in zip(result.arms, result.confidences)))
        flag = "  (LOW CONFIDENCE)" if result.low_confidence else ""
        print(f"confidence:  {result.confidence:.3f}{flag}")
        print(f"modalities:  {'+'.join(result.modalities)} ({result.method})")
        for warning in result.warnings:
            print(f"warning:     {warning}")
        print(f"latency:     {1000 * result.latency_s:.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
