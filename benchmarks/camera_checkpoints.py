"""Compare image checkpoints on phone-camera photos of cards, per glyph set and condition (image alone, exact %).

For choosing between training runs: the cards come from a seed of their own (777), never the one of
``instruction_table.py``'s camera table, so that table stays an independent check of the chosen checkpoint. Rows are
the glyph sets and conditions of the camera table (``evaluation.CAMERA_SETS`` x ``camera.CAMERA_CONDITIONS``), one
column per checkpoint; then, per checkpoint, the mean over the unseen sets' cells, over their "all" cells, and the
largest drop of an unseen cell against the first checkpoint.

    OMP_NUM_THREADS=1 python benchmarks/camera_checkpoints.py --items 300 --checkpoints packaged a.pt b.pt \
        --out results/camera_checkpoints.md
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from vafn_media.evaluation import CAMERA_SELECTION_SEED  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--items", type=int, default=300, help="cards per glyph set (lengths 1-10)")
    parser.add_argument("--checkpoints", nargs="+", default=["packaged"],
                        help="checkpoint files (.pt with its .json beside it; named by their folder), or 'packaged'")
    parser.add_argument("--out", type=Path, default=None, help="also write the markdown table here")
    return parser.parse_args(argv)


def summary(scores: dict[str, dict[tuple[str, str], float]]) -> list[str]:
    """Markdown lines, per checkpoint: mean exact over the unseen sets' cells and their "all" cells, and the largest
    drop of an unseen cell against the first checkpoint (0 for the first itself).

    :param scores: checkpoint name -> {(glyph set, condition): exact %}, in the table's column order.
    """
    first = next(iter(scores.values()))
    lines = []
    for name, cells in scores.items():
        unseen = {key: value for key, value in cells.items() if key[0].startswith("unseen")}
        every = [value for (_, condition), value in unseen.items() if condition == "all"]
        drop = min(value - first[key] for key, value in unseen.items())
        lines.append(f"- {name}: unseen sets, mean of every cell {np.mean(list(unseen.values())):.2f}, of the \"all\" "
                     f"cells {np.mean(every):.2f}; largest drop of an unseen cell vs the first column {drop:+.1f}")
    return lines


def main(argv: list[str] | None = None) -> None:
    """Score every checkpoint on the same cards; print (and write) the table and the summary."""
    import torch
    from tqdm import tqdm

    from vafn_media.camera import CAMERA_CONDITIONS
    from vafn_media.evaluation import CAMERA_SETS, camera_cell, camera_items, checkpoint_by_name

    args = parse_args(argv)
    torch.set_num_threads(1)
    cards = {glyph_set: camera_items(glyph_set, args.items, CAMERA_SELECTION_SEED) for glyph_set in CAMERA_SETS}
    scores: dict[str, dict[tuple[str, str], float]] = {}
    for checkpoint in args.checkpoints:
        generator, name = checkpoint_by_name(checkpoint)
        scores[name] = {(glyph_set, condition): camera_cell(generator.transcribe, items, condition,
                                                            CAMERA_SELECTION_SEED)["exact"]
                        for glyph_set, items in tqdm(cards.items(), desc=name, unit="glyph set")
                        for condition in CAMERA_CONDITIONS}
    lines = [f"Image alone, exact sequence (%), {args.items} cards of lengths 1-10 per glyph set (selection seed "
             f"{CAMERA_SELECTION_SEED}); conditions as in the camera table.", "",
             "| Glyphs | Condition | " + " | ".join(scores) + " |", "|---|---|" + "---|" * len(scores)]
    for glyph_set in CAMERA_SETS:
        for condition in CAMERA_CONDITIONS:
            lines.append(f"| {glyph_set} | {condition} | "
                         + " | ".join(f"{cells[glyph_set, condition]:.1f}" for cells in scores.values()) + " |")
    lines += [""] + summary(scores)
    print("\n".join(lines))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
