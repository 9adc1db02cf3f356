"""Does the reader still need its test-time corrections? The packaged reader with and without each, on the selection
items of ``speech_checkpoints.py`` (audio alone, exact %).

The corrections are the 200 Hz low cut (``features.low_cut``), reading every clip at one peak (``features.at_peak``),
taking each mel band's noise floor away (``features.subtract_noise_floor``) and, for a clip that starts or ends in a
sound, adding silence there (``audio.with_quiet_edges``, measured on the clean clips trimmed at their words); they were
added for an audio path trained without them, so each fine-tune of that path should be checked against them.

    OMP_NUM_THREADS=1 python benchmarks/speech_corrections.py --items 200 --out results/speech_corrections.md
"""

from __future__ import annotations

import argparse
import os
import time
from contextlib import nullcontext
from pathlib import Path
from unittest.mock import patch

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from vafn_media.evaluation import SELECTION_SEED  # noqa: E402  (the items of benchmarks/speech_checkpoints.py)


def _reads(generator, waveform: np.ndarray, rate: int, arms: tuple[int, ...]) -> bool:
    """Whether the reader reads ``arms`` from the clip (a rejected clip counts as wrong)."""
    try:
        return tuple(generator.transcribe(audio=(waveform, rate)).arms) == tuple(arms)
    except ValueError:
        return False


def main() -> None:
    """Read every engine's items with the corrections on and without each of them in turn."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--items", type=int, default=200, help="instructions per engine (lengths 1-10)")
    parser.add_argument("--engines", default="recorded,flite,festival,pico,piper,rhvoice,espeak",
                        help="comma-separated")
    parser.add_argument("--checkpoint", default=None, help="a .pt file with its .json beside it (default: packaged)")
    parser.add_argument("--out", type=Path, default=None, help="also write the markdown table here")
    args = parser.parse_args()
    import torch

    import vafn_media.features as features
    import vafn_media.generator as generator_module
    from vafn_media import InstructionGenerator
    from vafn_media.augment import CONDITIONS
    from vafn_media.evaluation import robust_cell, speech_items
    from vafn_media.speech import trim_silence

    torch.set_num_threads(1)
    started = time.time()
    generator = InstructionGenerator.load(args.checkpoint)
    engines = args.engines.split(",")
    items = {engine: speech_items(engine, args.items, SELECTION_SEED) for engine in engines}
    # each variant is the reader with one correction replaced by the identity (None: as shipped)
    variants = {"as shipped": None,
                "without the low cut": (features, "low_cut", lambda waveform, rate: np.asarray(waveform, np.float32)),
                "without reading at one level": (features, "at_peak", lambda waveform: waveform),
                "without the noise-floor subtraction": (features, "subtract_noise_floor", lambda power: power)}
    lines = [f"Audio alone, exact sequence (%), {args.items} instructions per engine (selection seed "
             f"{SELECTION_SEED}), the reader with and without its test-time corrections; the last column is the share "
             "read wrong without a low-confidence flag, mean of the five conditions.", "",
             "| Reader | Engine | " + " | ".join(CONDITIONS) + " | mean of degraded | wrong & unflagged |",
             "|---|---|" + "---|" * (len(CONDITIONS) + 2)]
    for name, replaced in variants.items():
        with patch.object(*replaced) if replaced else nullcontext():
            for engine in engines:
                cells = [robust_cell(generator.transcribe, items[engine], condition, SELECTION_SEED)
                         for condition in CONDITIONS]
                exact = [cell["exact"] for cell in cells]
                unflagged = np.mean([cell["wrong_unflagged"] for cell in cells])
                lines.append(f"| {name} | {engine} | " + " | ".join(f"{v:.1f}" for v in exact)
                             + f" | {np.mean(exact[1:]):.1f} | {unflagged:.1f} |")
                print(lines[-1], flush=True)
    lines += ["", "Clean clips trimmed at their words (`speech.trim_silence`, as a voice-activity detector leaves "
              "them), exact %, with and without the silence the reader adds at an end that is in a sound:", "",
              "| Reader | " + " | ".join(engines) + " |", "|---|" + "---|" * len(engines)]
    without_edges = patch.object(generator_module, "with_quiet_edges", lambda clip: clip.waveform)
    for name, context in (("as shipped", nullcontext()), ("without the added silence", without_edges)):
        with context:
            exact = [100.0 * np.mean([_reads(generator, trim_silence(item.waveform), item.sample_rate, item.arms)
                                      for item in items[engine]]) for engine in engines]
        lines.append(f"| {name} | " + " | ".join(f"{v:.1f}" for v in exact) + " |")
        print(lines[-1], flush=True)
    lines += ["", f"Generated by `OMP_NUM_THREADS=1 python benchmarks/speech_corrections.py --items {args.items}` in "
              f"{time.time() - started:.0f} s (checkpoint: {args.checkpoint or 'packaged'}, trained by "
              f"{generator.metadata.get('command', 'unknown')})."]
    if args.out is not None:
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
