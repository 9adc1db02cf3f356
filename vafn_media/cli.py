"""``vafn-instruct``: read an instruction from a speech file, an image and/or machine code,
print it with confidences."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    parser = argparse.ArgumentParser(prog="vafn-instruct", description=__doc__)
    parser.add_argument("--audio", help="speech file (WAV/FLAC/OGG, any sample rate >= 16 kHz)")
    parser.add_argument("--image", help="image of digits 1-3 in a left-to-right row (PNG/JPG/...)")
    parser.add_argument("--code", help='machine code, e.g. "2,3,1" or "[2, 3, 1]"')
    parser.add_argument("--checkpoint", help="model checkpoint (.pt); default: the packaged one")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code (0 ok, 2 bad input)."""
    args = build_parser().parse_args(argv)
    if not (args.audio or args.image or args.code):
        build_parser().error("give at least one of --audio, --image, --code")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    from vafn_media.generator import InstructionGenerator

    torch.set_num_threads(1)
    try:
        generator = InstructionGenerator.load(args.checkpoint)
        result = generator.transcribe(audio=args.audio, image=args.image, code=args.code)
    except (ValueError, FileNotFoundError) as error:
        print(f"vafn-instruct: error: {error}", file=sys.stderr)
        return 2
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
