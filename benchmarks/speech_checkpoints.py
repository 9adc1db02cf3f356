"""Compare audio checkpoints on spoken instructions from every speech engine, per condition (audio alone, exact %).

For choosing between training runs: the items come from a seed of their own (12345), never the one of
``instruction_table.py``'s robustness section, so the table stays an independent check of the chosen checkpoint.
Engines: espeak-ng's held-out voices, and every evaluation engine installed (``engines.available_engines``:
flite, Festival, the held-out voices of MBROLA, Pico, RHVoice and DECtalk, Piper's neural voice, a person's recorded
words), or those named by ``--engines``; none is trained on.
``--errors`` adds, per checkpoint and engine, where clean speech is misread: exact % per phrasing and per voice, and
which digits are dropped and inserted.

    OMP_NUM_THREADS=1 python benchmarks/speech_checkpoints.py --items 200 --checkpoints packaged a.pt b.pt \
        --out results/speech_checkpoints.md
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from vafn_media.evaluation import SELECTION_SEED  # noqa: E402


def parse_args() -> argparse.Namespace:
    """Command-line options."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--items", type=int, default=200, help="instructions per engine (lengths 1-10)")
    parser.add_argument("--checkpoints", nargs="+", default=["packaged"],
                        help="checkpoint files (.pt with its .json beside it; named by their folder), or 'packaged'")
    parser.add_argument("--engines", default=None,
                        help="comma-separated engines to read (espeak and evaluation engines); default: all installed")
    parser.add_argument("--errors", action="store_true", help="also break clean-speech errors down (see above)")
    parser.add_argument("--out", type=Path, default=None, help="also write the markdown table here")
    return parser.parse_args()


def error_lines(transcribe: Callable[..., object], items: list, engine: str) -> list[str]:
    """Markdown lines: clean-speech exact % per phrasing and per voice, and the digits dropped / inserted."""
    from collections import Counter, defaultdict

    from vafn_media.evaluation import degraded_clip, dropped_and_inserted
    from vafn_media.speech import phrase

    by_phrasing, by_voice = defaultdict(list), defaultdict(list)
    dropped, inserted = Counter(), Counter()
    for index, item in enumerate(items):
        try:
            read = tuple(transcribe(audio=degraded_clip(item, "clean", SELECTION_SEED, index)).instruction.arms)
        except ValueError:
            read = ()
        by_phrasing[item.template].append(read == item.arms)
        by_voice[item.voice.split("+")[0]].append(read == item.arms)
        lost, added = dropped_and_inserted(item.arms, read)
        dropped.update(lost)
        inserted.update(added)

    def cells(groups: dict) -> str:
        return "; ".join(f"{name}: {100 * np.mean(hits):.0f} % of {len(hits)}" for name, hits in sorted(groups.items()))

    return [f"- {engine}, clean, per phrasing (shown for [1, 2]): "
            + cells({repr(phrase([1, 2], t)): hits for t, hits in by_phrasing.items()}),
            f"- {engine}, clean, per voice: " + cells(by_voice),
            f"- {engine}, clean, digits dropped: {dict(sorted(dropped.items()))}, inserted: "
            f"{dict(sorted(inserted.items()))}"]


def main() -> None:
    """Score every checkpoint on the same items; print (and write) one markdown row per checkpoint and engine."""
    import torch
    from tqdm import tqdm

    from vafn_media.augment import CONDITIONS
    from vafn_media.engines import available_engines
    from vafn_media.evaluation import checkpoint_by_name, robust_cell, speech_items

    args = parse_args()
    torch.set_num_threads(1)
    engines = args.engines.split(",") if args.engines else ["espeak"] + available_engines()
    items = {engine: speech_items(engine, args.items, SELECTION_SEED) for engine in engines}
    lines = [f"Audio alone, exact sequence (%), {args.items} instructions of lengths 1-10 per engine "
             f"(selection seed {SELECTION_SEED}).", "",
             "| Checkpoint | Engine | " + " | ".join(CONDITIONS) + " | mean of degraded |",
             "|---|---|" + "---|" * (len(CONDITIONS) + 1)]
    errors: list[str] = []
    for checkpoint in args.checkpoints:
        generator, name = checkpoint_by_name(checkpoint)
        if args.errors:
            errors.append(f"{name}:")
        for engine in engines:
            exact = [robust_cell(generator.transcribe, items[engine], condition, SELECTION_SEED)["exact"]
                     for condition in tqdm(CONDITIONS, desc=f"{name}: {engine}",
                                           unit="condition", leave=False)]
            cells = " | ".join(f"{value:.1f}" for value in exact)
            lines.append(f"| {name} | {engine} | {cells} | {np.mean(exact[1:]):.1f} |")
            print(lines[-1], flush=True)
            if args.errors:
                errors += error_lines(generator.transcribe, items[engine], engine)
    if errors:
        lines += ["", "Where clean speech is misread:", ""] + errors
        print("\n".join(errors))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
