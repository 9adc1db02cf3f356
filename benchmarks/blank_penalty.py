"""Choose the audio path's CTC blank penalty: exact % per engine, condition and penalty on selection items.

A reader trained on a few synthesisers swallows a short word of a voice it never heard into the blank (a fluent *two*
between two other digits); lowering the blank logit keeps such words at the price of more insertions on voices it
knows. The penalty is **chosen on the held-out voices of the engines the checkpoint trained on** (espeak-ng, and every
installed engine whose ``--<engine>-probability`` was above 0), never on an engine it has never heard, so those stay an
independent test: the grid value with the best mean over those engines of (clean + mean of the degraded conditions) / 2,
an exact tie going to the smaller penalty. Items come from the selection seed, never the robustness table's.
The same readings choose the **half-heard check** (``blank_probe``): a reading that changes when decoded with a larger
penalty is flagged. The probe is the largest grid penalty above the chosen one whose check flags at most
``PROBE_BUDGET_PERCENT`` of the right readings of those same trained engines' held-out voices (mean over engines, every
condition). ``--write`` stores both in the checkpoint's JSON; recalibrate after it
(``python -m vafn_media.calibration``), since the confidences change with the penalty.

    OMP_NUM_THREADS=1 python benchmarks/blank_penalty.py --items 200 --out results/blank_penalty.md --write
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from vafn_media.evaluation import SELECTION_SEED  # noqa: E402

#: Candidate penalties (logit units; 0 is plain greedy decoding).
PENALTY_GRID: tuple[float, ...] = (0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 3.0)
#: The half-heard check may flag at most this share (%) of the right readings of the trained engines' held-out voices.
PROBE_BUDGET_PERCENT: float = 2.0


def parse_args() -> argparse.Namespace:
    """Command-line options."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--items", type=int, default=200, help="instructions per engine (lengths 1-10)")
    parser.add_argument("--checkpoint", default="packaged", help="checkpoint .pt (its .json beside it) or 'packaged'")
    parser.add_argument("--engines", default=None,
                        help="comma-separated engines to read (espeak and evaluation engines); default: all installed")
    parser.add_argument("--write", action="store_true", help="store the chosen penalty in the checkpoint's JSON")
    parser.add_argument("--out", type=Path, default=None, help="also write the markdown table here")
    return parser.parse_args()


def trained_engines(metadata: dict, engines: list[str]) -> list[str]:
    """The engines of ``engines`` the checkpoint trained on (espeak-ng always; others when their share was above 0)."""
    shares = metadata.get("args", {})
    return [e for e in engines if e == "espeak" or float(shares.get(f"{e}_probability", 0)) > 0]


def engine_score(exact: list[float]) -> float:
    """(clean + mean of the degraded conditions) / 2 of one engine's per-condition exact % (clean first)."""
    return (exact[0] + float(np.mean(exact[1:]))) / 2


def choose_penalty(exact: dict[str, dict[float, list[float]]], engines: list[str]) -> float:
    """The penalty with the best mean :func:`engine_score` over ``engines``; an exact tie goes to the smaller penalty.

    :param exact: engine -> penalty -> exact % per condition (clean first).
    :param engines: the engines the choice may look at.
    """
    if not engines:
        raise ValueError("no engine to choose the blank penalty on")
    penalties = sorted(next(iter(exact.values())))
    return max(penalties, key=lambda p: (round(float(np.mean([engine_score(exact[e][p]) for e in engines])), 6), -p))


def read_log_probs(generator, items: list, condition: str) -> list:
    """Decoder log posteriors of every item's clip under ``condition`` (None where the clip is rejected)."""
    import torch

    from vafn_media.audio import load_audio
    from vafn_media.evaluation import degraded_clip

    out = []
    for index, item in enumerate(items):
        try:
            clip = load_audio(degraded_clip(item, condition, SELECTION_SEED, index))
        except ValueError:
            out.append(None)
            continue
        phi = generator.encode_clip(clip)
        with torch.inference_mode():
            out.append(torch.log_softmax(generator.model.decode(phi), dim=-1))
    return out


def readings(log_probs: list, penalty: float) -> list[tuple[int, ...] | None]:
    """Best-path readings of cached log posteriors under a blank penalty (None where the clip was rejected)."""
    from vafn_media.decoding import best_path_arms

    return [None if frames is None else tuple(best_path_arms(frames, penalty)) for frames in log_probs]


def exact_percent(reads: list, items: list) -> float:
    """Exact-sequence % of readings (a rejected clip is wrong)."""
    return 100.0 * float(np.mean([read == item.arms for read, item in zip(reads, items)]))


def dropped_inserted(reads: list, items: list) -> tuple[int, int]:
    """Digits dropped and inserted over all readings (a rejected clip drops all its digits)."""
    from vafn_media.evaluation import dropped_and_inserted

    changes = [dropped_and_inserted(item.arms, read or ()) for read, item in zip(reads, items)]
    return sum(len(lost) for lost, _ in changes), sum(len(added) for _, added in changes)


def probe_rates(chosen_reads: list, probe_reads: list, items: list) -> tuple[float, float]:
    """(% of right readings the half-heard check flags, % of wrong readings it catches): a reading is flagged when the
    probe penalty reads it differently (rejected clips are left out)."""
    pairs = [(a == item.arms, a != b) for a, b, item in zip(chosen_reads, probe_reads, items) if a is not None]
    right = [changed for ok, changed in pairs if ok]
    wrong = [changed for ok, changed in pairs if not ok]
    return (100.0 * float(np.mean(right)) if right else 0.0, 100.0 * float(np.mean(wrong)) if wrong else 0.0)


def choose_probe(flagged_right: dict[str, dict[float, float]], engines: list[str], chosen: float,
                 budget: float = PROBE_BUDGET_PERCENT) -> float | None:
    """The largest penalty above ``chosen`` whose check flags at most ``budget`` % of right readings (mean over
    ``engines``); None when even the smallest one flags more.

    :param flagged_right: engine -> probe penalty -> % of right readings flagged.
    :param engines: the engines the choice may look at.
    :param chosen: the decoding penalty.
    :param budget: the largest acceptable mean share (%).
    """
    candidates = [p for p in sorted(next(iter(flagged_right.values()))) if p > chosen
                  and float(np.mean([flagged_right[e][p] for e in engines])) <= budget]
    return max(candidates) if candidates else None


def main() -> None:
    """Sweep the grid on every engine, choose on the trained engines' held-out voices, print (and write) the table."""
    import torch
    from tqdm import tqdm

    from vafn_media.augment import CONDITIONS
    from vafn_media.engines import available_engines
    from vafn_media.evaluation import checkpoint_by_name, speech_items

    args = parse_args()
    torch.set_num_threads(1)
    generator, name = checkpoint_by_name(args.checkpoint)
    engines = args.engines.split(",") if args.engines else ["espeak"] + available_engines()
    exact: dict[str, dict[float, list[float]]] = {}
    clean_changes: dict[str, dict[float, tuple[int, int]]] = {}
    reads: dict[str, dict[float, list]] = {}  # engine -> penalty -> readings of every condition's items in turn
    items_by_engine: dict[str, list] = {}
    for engine in tqdm(engines, desc="engines", unit="engine"):
        items = speech_items(engine, args.items, SELECTION_SEED)
        log_probs = {condition: read_log_probs(generator, items, condition) for condition in CONDITIONS}
        by_condition = {(c, p): readings(log_probs[c], p) for c in CONDITIONS for p in PENALTY_GRID}
        exact[engine] = {p: [exact_percent(by_condition[c, p], items) for c in CONDITIONS] for p in PENALTY_GRID}
        clean_changes[engine] = {p: dropped_inserted(by_condition["clean", p], items) for p in PENALTY_GRID}
        reads[engine] = {p: [r for c in CONDITIONS for r in by_condition[c, p]] for p in PENALTY_GRID}
        items_by_engine[engine] = items * len(CONDITIONS)
    chosen_on = trained_engines(generator.metadata, engines)
    chosen = choose_penalty(exact, chosen_on)
    never = [e for e in engines if e not in chosen_on]
    probes = [p for p in PENALTY_GRID if p > chosen]
    rates = {e: {p: probe_rates(reads[e][chosen], reads[e][p], items_by_engine[e]) for p in probes} for e in engines}
    probe = choose_probe({e: {p: rates[e][p][0] for p in probes} for e in engines}, chosen_on, chosen)
    lines = [f"Audio alone, exact sequence (%) by CTC blank penalty, checkpoint {name}, {args.items} instructions of "
             f"lengths 1-10 per engine (selection seed {SELECTION_SEED}). Chosen on the held-out voices of "
             f"{', '.join(chosen_on)}: **{chosen}** (score = (clean + mean of degraded) / 2).", "",
             "| Penalty | " + " | ".join(f"{e} clean / degraded" for e in engines)
             + " | trained engines' score | never-trained engines' score |",
             "|---|" + "---|" * (len(engines) + 2)]
    for p in PENALTY_GRID:
        cells = " | ".join(f"{exact[e][p][0]:.1f} / {np.mean(exact[e][p][1:]):.1f}" for e in engines)
        scores = [f"{np.mean([engine_score(exact[e][p]) for e in group]):.2f}" if group else "-"
                  for group in (chosen_on, never)]
        lines.append(f"| {'**' + str(p) + '**' if p == chosen else p} | {cells} | {' | '.join(scores)} |")
    lines += ["", "Per condition (" + ", ".join(CONDITIONS) + "), plain greedy (0) -> chosen penalty:", ""]
    lines += [f"- {e}: " + ", ".join(f"{a:.1f} -> {b:.1f}" for a, b in zip(exact[e][0.0], exact[e][chosen]))
              + "; clean digits dropped / inserted {} / {} -> {} / {}".format(*clean_changes[e][0.0],
                                                                            *clean_changes[e][chosen])
              for e in engines]
    lines += ["", f"Half-heard check: % of right readings flagged / % of wrong readings caught (every condition) when "
              f"the reading at penalty {chosen} changes at the probe penalty. Chosen on the held-out voices of "
              f"{', '.join(chosen_on)} (the largest probe flagging at most {PROBE_BUDGET_PERCENT} % of their right "
              f"readings on average): **{probe}**.", "",
              "| Probe | " + " | ".join(engines) + " | trained engines' mean right flagged |",
              "|---|" + "---|" * (len(engines) + 1)]
    for p in probes:
        cells = " | ".join(f"{rates[e][p][0]:.1f} / {rates[e][p][1]:.0f}" for e in engines)
        mean = np.mean([rates[e][p][0] for e in chosen_on])
        lines.append(f"| {'**' + str(p) + '**' if p == probe else p} | {cells} | {mean:.2f} |")
    print("\n".join(lines))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")
    if args.write:
        from vafn_media.generator import DEFAULT_CHECKPOINT

        path = Path(DEFAULT_CHECKPOINT if args.checkpoint == "packaged" else args.checkpoint).with_suffix(".json")
        metadata = json.loads(path.read_text())
        metadata["blank_penalty"] = {**metadata.get("blank_penalty", {}), "audio": chosen}
        probes_written = {k: v for k, v in metadata.get("blank_probe", {}).items() if k != "audio"}
        metadata["blank_probe"] = {**probes_written, **({"audio": probe} if probe is not None else {})}
        path.write_text(json.dumps(metadata, indent=2))
        print(f"wrote blank_penalty.audio = {chosen} and blank_probe.audio = {probe} to {path}; now run "
              "python -m vafn_media.calibration")


if __name__ == "__main__":
    main()
