"""Table 1 of the paper for the multimedia instruction generator (prints and writes markdown + CSV).

Rows Audio / Audio (noise) / Audio-Visual / Audio-Visual (noise) / Visual / Visual (Cutout) / Machine code, for
Easy (0-3) / Medium (4-6) / Hard (7-10) instructions; 5 seeds x 100 fresh items per cell. Accuracy is the exact
match of the whole sequence (mean ± std over seeds); time is the per-instruction wall time of ``transcribe`` on one
CPU thread, features included (mean ± std over all items). Noise: white Gaussian noise at 20 dB SNR; Cutout:
one rectangle covering 10-20 % of the image. The main table uses the held-out split (voices, variants,
handwriting and fonts never seen in training); a second table compares it with in-distribution items. A third
section tests cross-modal alignment: a fresh decoder trained on one modality's Φ reads the other's.

A robustness section (``results/instruction_table_robust.{md,csv}``) reads spoken instructions of lengths 1-10 from
espeak-ng's held-out voices and from every *other* speech engine installed (flite, Festival, the held-out voices of
MBROLA, Pico and RHVoice, a person's recorded words; one that is absent is skipped, never faked) under five
conditions: clean 16 kHz, 8 kHz telephone band, reverberation (RT60 0.6 s), white noise at 10 dB SNR, and fast speech
(the engine's own rate control). Per cell: exact sequence and per-digit accuracy for audio alone and audio + image,
the image alone, and how often a wrong result is unflagged.

    OMP_NUM_THREADS=1 python benchmarks/instruction_table.py            # full: 5 seeds x 100 per cell
    OMP_NUM_THREADS=1 python benchmarks/instruction_table.py --items 20 --seeds 1   # quick look
A camera section (``results/instruction_table_camera.{md,csv}``) reads images of cards as a phone camera sees them
(``vafn_media.camera``): glyphs from TrueType fonts, Hershey fonts and scikit-learn handwriting that were never used
for training (plus the training TrueType fonts as a reference), each under seven conditions: flat, perspective,
uneven light, tinted paper + coloured ink, blur (Gaussian + motion), JPEG quality 20, and all of them together.

    OMP_NUM_THREADS=1 python benchmarks/instruction_table.py --robust-only --checkpoint X.pt --out /tmp/x
    OMP_NUM_THREADS=1 python benchmarks/instruction_table.py --camera-only --camera-items 100

A real-people section (``results/real_people/``, ``--people-speech`` and ``--people-handwriting``) reads commands said
by real speakers and written by real hands that never trained, validated or calibrated the reader
(``benchmarks/real_people.py``), with the robot's two rates: acted on correctly and acted on wrongly.
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from vafn_gym.constants import DIFFICULTY_LENGTHS  # noqa: E402
from vafn_media.evaluation import PAPER_ACCURACY, PAPER_LATENCY_S, ROWS, run_cell  # noqa: E402

RESULTS = Path(__file__).resolve().parents[1] / "results"
#: Seeds of the evaluation items are offset from the training seed range.
EVAL_SEED_BASE = 1000


def parse_args() -> argparse.Namespace:
    """Command-line options; ``--help`` shows the module docstring without markup and every option's default."""

    class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
        pass

    parser = argparse.ArgumentParser(description=__doc__.replace("``", ""), formatter_class=HelpFormatter)
    parser.add_argument("--seeds", type=int, default=5, help="evaluation seeds per cell (fresh items each)")
    parser.add_argument("--items", type=int, default=100, help="items per seed and difficulty")
    parser.add_argument("--checkpoint", default=None, help="model checkpoint (.pt; None: the packaged one)")
    parser.add_argument("--workers", type=int, default=2, help="data-generation processes")
    parser.add_argument(
        "--in-distribution", type=int, default=1, help="seeds of the in-distribution comparison (0: skip)"
    )
    parser.add_argument(
        "--transfer-items", type=int, default=1000, help="training items for the cross-modal probe (0: skip)"
    )
    parser.add_argument("--robust-items", type=int, default=100, help="items per engine of the robustness section")
    parser.add_argument("--robust-only", action="store_true", help="skip Table 1; run only the robustness section")
    parser.add_argument("--robust-engines", default=None,
                        help="comma-separated engines of the robustness section (default: espeak and every evaluation "
                             "engine installed)")
    parser.add_argument("--camera-items", type=int, default=300,
                        help="cards per glyph set of the camera section (0: skip)")
    parser.add_argument("--camera-only", action="store_true",
                        help="skip Table 1 and the speech robustness; run only the camera section")
    parser.add_argument("--people-speech", type=Path, nargs="+", default=None,
                        help="real people's recorded words (vafn_media.people): adds the real-people section "
                             "(benchmarks/real_people.py: test speakers and glyphs, acted on correctly / wrongly, "
                             "pocketsphinx as a reference) to results/real_people/")
    parser.add_argument("--people-handwriting", type=Path, default=None,
                        help="folder with MNIST's training files, for the real-people section")
    parser.add_argument("--csv", action="store_true", help="also write each table's rows as CSV beside its markdown")
    parser.add_argument("--out", type=Path, default=RESULTS / "instruction_table",
                        help="output prefix: writes <out>.md and <out>.csv")
    return parser.parse_args()


def evaluate_split(generator, split: str, seeds: int, items: int, workers: int, rows) -> dict:
    """Run every row x difficulty cell of one split; returns {(row, difficulty): [CellResult per seed]}."""
    from tqdm import tqdm

    from vafn_media.dataset import generate_raw

    cells: dict = {}
    jobs = [(s, d) for s in range(seeds) for d in DIFFICULTY_LENGTHS]
    for seed_index, difficulty in tqdm(jobs, desc=f"{split} cells", unit="seed x difficulty"):
        eval_seed = EVAL_SEED_BASE + seed_index
        data = generate_raw(eval_seed, split, items, difficulty, workers=workers)
        for row in rows:
            cells.setdefault((row, difficulty), []).append(run_cell(generator.transcribe, data, eval_seed, row))
    return cells


def summarise(cells: dict, row: str, difficulty: str) -> tuple[float, ...]:
    """(wall mean, wall std, CPU mean, CPU std, accuracy mean %, accuracy std %, per-digit accuracy %) of one cell."""
    results = cells[(row, difficulty)]
    seconds = np.concatenate([r.seconds for r in results])
    cpu = np.concatenate([r.cpu_seconds for r in results])
    accuracy = np.array([100.0 * r.correct.mean() for r in results])
    errors = sum(int(r.digit_errors.sum()) for r in results)
    digits = sum(int(r.digits.sum()) for r in results)
    digit = 100.0 * (1.0 - errors / digits) if digits else 100.0
    return (float(seconds.mean()), float(seconds.std()), float(cpu.mean()), float(cpu.std()),
            float(accuracy.mean()), float(accuracy.std()), digit)


def cross_modal_probe(generator, items: int, heldout_items) -> dict:
    """Train a fresh decoder on one modality's Φ (frozen encoders) and read the other modality with it."""
    import torch
    import torch.nn.functional as F

    from vafn_media.batching import make_batch
    from vafn_media.constants import BLANK, VOCAB_SIZE
    from vafn_media.dataset import build_cache
    from vafn_media.decoding import greedy_decode
    from vafn_media.images import canonical_strip

    model = generator.model
    train = build_cache(0, "train", items, progress=False)
    latents = {"audio": [], "image": []}
    with torch.inference_mode():
        for start in range(0, len(train), 64):
            batch = make_batch(train, np.arange(start, min(len(train), start + 64)), None)
            for modality in latents:
                phi, lengths = model.encode(modality, batch[modality], batch[f"{modality}_lengths"])
                latents[modality] += [phi[b, : int(lengths[b])].clone() for b in range(len(lengths))]
    labels = [train.arms[i, : train.lengths[i]].tolist() for i in range(len(train))]
    test_phi = {"audio": [], "image": []}
    for waveform, image in zip(heldout_items.waveforms, heldout_items.images):
        test_phi["audio"].append(generator.encode_audio(waveform, heldout_items.sample_rate))
        test_phi["image"].append(generator.encode_strip(canonical_strip(image)))
    results = {}
    torch.manual_seed(0)
    for source in ("audio", "image"):
        head = torch.nn.Sequential(torch.nn.Linear(model.config.latent_dim, model.config.decoder_hidden),
                                   torch.nn.ReLU(),
                                   torch.nn.Linear(model.config.decoder_hidden, VOCAB_SIZE))
        optimizer = torch.optim.Adam(head.parameters(), lr=3e-3)
        rng = np.random.default_rng(0)
        for _ in range(400):
            idx = rng.integers(0, len(labels), 64)
            phis = torch.nn.utils.rnn.pad_sequence([latents[source][i] for i in idx], batch_first=True)
            lengths = torch.tensor([len(latents[source][i]) for i in idx])
            targets = torch.tensor([a for i in idx for a in labels[i]], dtype=torch.long)
            target_lengths = torch.tensor([len(labels[i]) for i in idx])
            loss = F.ctc_loss(head(phis).log_softmax(-1).transpose(0, 1), targets, lengths, target_lengths,
                              blank=BLANK, zero_infinity=True)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        with torch.inference_mode():
            for target in ("audio", "image"):
                hits = [tuple(greedy_decode(phi, head(phi)).arms) == tuple(arms)
                        for phi, arms in zip(test_phi[target], heldout_items.arms)]
                results[(source, target)] = 100.0 * float(np.mean(hits))
    return results


def provenance(generator) -> str:
    """The checkpoint's training command and how it decodes (its blank penalties and half-heard probes)."""
    return (f"{generator.metadata.get('command', 'unknown')}; CTC blank penalty "
            f"{dict(generator.blank_penalty) or 'none'}, half-heard probe {dict(generator.blank_probe) or 'none'}")


def engine_note(engine: str, voice: str, share: float) -> str:
    """How the robustness header describes an evaluation engine that can also be trained on (``share`` > 0)."""
    if share > 0:
        return f"{engine} = {voice}, held out (this checkpoint trained on its other voices, {share:.0%} of utterances)"
    return f"{engine} = {voice}, an engine this checkpoint never trained on"


def robust_section(generator, items_per_engine: int, seed: int = EVAL_SEED_BASE + 500,
                   engines: list[str] | None = None) -> tuple[list, list]:
    """Per engine x condition: audio and audio+image accuracy (exact, per digit), image alone; markdown + CSV rows.

    :param engines: "espeak" and evaluation engines to read; None: espeak and every one installed.
    """
    from tqdm import tqdm

    from vafn_media.augment import CONDITIONS
    from vafn_media.engines import available_engines
    from vafn_media.evaluation import robust_cell, speech_items

    engines = engines or ["espeak"] + available_engines()
    lines = ["| Engine | Condition | Audio exact (%) | Audio per digit (%) | AV exact (%) | AV per digit (%) | "
             "Image exact (%) | Audio flagged (%) | Audio rejected (%) | Audio wrong & unflagged (%) | "
             "Audio right but flagged (%) | AV wrong & unflagged (%) | Audio CPU (ms) | AV CPU (ms) |",
             "|" + "---|" * 14]
    rows = [["engine", "condition", "audio_exact", "audio_digit", "av_exact", "av_digit", "image_exact",
             "audio_flagged", "audio_rejected", "audio_wrong_unflagged", "audio_right_flagged", "av_wrong_unflagged",
             "audio_cpu_ms", "av_cpu_ms", "items"]]
    summary = {}
    for engine in engines:
        items = speech_items(engine, items_per_engine, seed)
        image_exact = 100.0 * float(np.mean([
            tuple(generator.transcribe(image=item.image).instruction.arms) == item.arms for item in items
        ]))
        for condition in tqdm(CONDITIONS, desc=f"robustness: {engine}", unit="condition"):
            audio = robust_cell(generator.transcribe, items, condition, seed)
            av = robust_cell(generator.transcribe, items, condition, seed, with_image=True)
            summary[(engine, condition)] = (audio, av, image_exact)
            lines.append(f"| {engine} | {condition} | {audio['exact']:.1f} | {audio['digit']:.1f} | {av['exact']:.1f} "
                         f"| {av['digit']:.1f} | {image_exact:.1f} | {audio['flagged']:.1f} | {audio['rejected']:.1f} "
                         f"| {audio['wrong_unflagged']:.1f} | {audio['right_flagged']:.1f} "
                         f"| {av['wrong_unflagged']:.1f} | {audio['cpu_ms']:.2f} | {av['cpu_ms']:.2f} |")
            rows.append([engine, condition] + [f"{v:.2f}" for v in (
                audio["exact"], audio["digit"], av["exact"], av["digit"], image_exact, audio["flagged"],
                audio["rejected"], audio["wrong_unflagged"], audio["right_flagged"], av["wrong_unflagged"],
                audio["cpu_ms"], av["cpu_ms"])]
                + [len(items)])
        degraded = [summary[(engine, c)][0]["exact"] for c in CONDITIONS if c != "clean"]
        lines.append(f"| {engine} | **mean of degraded** | {np.mean(degraded):.1f} | | "
                     f"{np.mean([summary[(engine, c)][1]['exact'] for c in CONDITIONS if c != 'clean']):.1f} "
                     "| | | | | | | | | |")
    return lines, rows


def camera_section(generator, items_per_set: int, seed: int = EVAL_SEED_BASE + 600) -> tuple[list, list]:
    """Per glyph set x camera condition: image exact / per-digit accuracy, flags, rejections; then per unseen font."""
    from tqdm import tqdm

    from vafn_media.camera import CAMERA_CONDITIONS
    from vafn_media.evaluation import CAMERA_SETS, camera_cell, camera_items

    lines = ["| Glyphs | Condition | Image exact (%) | Image per digit (%) | Flagged (%) | Rejected (%) | "
             "Wrong & unflagged (%) | Right but flagged (%) |", "|" + "---|" * 8]
    rows = [["glyphs", "condition", "exact", "digit", "flagged", "rejected", "wrong_unflagged", "right_flagged",
             "items"]]
    per_font: dict[str, dict[str, list[int]]] = {}
    per_size: dict[tuple[str, tuple[int, int]], dict[str, list[int]]] = {}
    for glyph_set in CAMERA_SETS:
        items = camera_items(glyph_set, items_per_set, seed)
        exact = []
        for condition in tqdm(CAMERA_CONDITIONS, desc=f"camera: {glyph_set}", unit="condition"):
            cell = camera_cell(generator.transcribe, items, condition, seed)
            exact.append(cell["exact"])
            lines.append(f"| {glyph_set} | {condition} | {cell['exact']:.1f} | {cell['digit']:.1f} | "
                         f"{cell['flagged']:.1f} | {cell['rejected']:.1f} | {cell['wrong_unflagged']:.1f} | "
                         f"{cell['right_flagged']:.1f} |")
            rows.append([glyph_set, condition] + [f"{cell[k]:.2f}" for k in (
                "exact", "digit", "flagged", "rejected", "wrong_unflagged", "right_flagged")] + [len(items)])
            for size, counts in cell["per_size"].items():
                per_size.setdefault((glyph_set, size), {})[condition] = counts
            if glyph_set.startswith("unseen"):
                for font, (hits, count) in cell["per_font"].items():
                    per_font.setdefault(font, {})[condition] = [hits, count]
        lines.append(f"| {glyph_set} | **mean of the 6 camera conditions** | **{np.mean(exact[1:]):.1f}** | | | | | |")
        rows.append([glyph_set, "mean of camera conditions", f"{np.mean(exact[1:]):.2f}", "", "", "", "", "",
                     len(items)])
    def breakdown(groups: list[tuple[str, str, dict[str, list[int]]]]) -> None:
        """Per (markdown label cells, CSV name, {condition: [hits, cards]}): one markdown row of exact % per
        condition, and one CSV row per condition."""
        for label, name, cells in groups:
            lines.append(f"| {label} | " + " | ".join(
                f"{100.0 * cells[c][0] / max(1, cells[c][1]):.1f}" for c in CAMERA_CONDITIONS) + " |")
            for condition in CAMERA_CONDITIONS:
                hits, count = cells[condition]
                rows.append([name, condition, f"{100.0 * hits / max(1, count):.2f}", "", "", "", "", "", count])

    lines += ["", "Unseen TrueType fonts, one row per font (exact %, each font has 1/"
              f"{max(1, len(per_font))} of the cards):", "",
              "| Font | " + " | ".join(CAMERA_CONDITIONS) + " |", "|" + "---|" * (1 + len(CAMERA_CONDITIONS))]
    breakdown([(font, f"font:{font}", cells) for font, cells in per_font.items()])
    lines += ["", "By digit size: exact % per side of a digit's cell on the card (pixels; blur and JPEG blocks are in "
              "pixels, so they take more of a small digit), cards in brackets:", "",
              "| Glyphs | Digit cell (px) | " + " | ".join(CAMERA_CONDITIONS) + " |",
              "|" + "---|" * (2 + len(CAMERA_CONDITIONS))]
    breakdown([(f"{glyph_set} | {low}-{high} ({cells[CAMERA_CONDITIONS[0]][1]})", f"{glyph_set}:cell {low}-{high}px",
                cells) for (glyph_set, (low, high)), cells in per_size.items()])
    return lines, rows


def write_tables(out: Path, text: str, rows: list, with_csv: bool) -> None:
    """Print ``text`` and write it to ``<out>.md`` and, with ``with_csv``, ``rows`` to ``<out>.csv``."""
    print(text)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(text + "\n")
    if with_csv:
        with open(out.with_suffix(".csv"), "w", newline="") as handle:
            csv.writer(handle).writerows(rows)


def write_camera(args: argparse.Namespace, generator) -> None:
    """Run the camera section and write ``<out>_camera.{md,csv}``."""
    from vafn_media.camera import (EVAL_BLUR_SIGMA, EVAL_JPEG_QUALITY, EVAL_LIGHT_DEPTH, EVAL_MOTION_LENGTH,
                                   EVAL_WARP, HELDOUT_TTF_FONTS)

    started = time.time()
    lines, rows = camera_section(generator, args.camera_items)
    load = os.getloadavg()
    text = "\n".join([
        f"Cards as a phone camera sees them: {args.camera_items} cards (lengths 1-10) per glyph set, image alone. "
        f"Unseen TrueType fonts = {', '.join(HELDOUT_TTF_FONTS)} (matplotlib's bundled fonts, never used for "
        "training); unseen Hershey fonts = DUPLEX and SCRIPT_COMPLEX (a script, handwriting-like face); unseen "
        "handwriting = the last 30 % of each digit's scikit-learn samples (8x8 px, upscaled); training TrueType "
        "fonts are the in-distribution reference. Conditions: flat = black ink on white paper; perspective = "
        f"corners moved by up to {EVAL_WARP:.0%} of the side; uneven light = light falling to "
        f"{1 - EVAL_LIGHT_DEPTH:.0%} across the card; tinted paper + coloured ink = yellow/pink/blue-grey/green "
        f"paper with blue/red/green/pencil ink; blur = Gaussian sigma {EVAL_BLUR_SIGMA} px then {EVAL_MOTION_LENGTH} "
        f"px motion blur; JPEG = quality {EVAL_JPEG_QUALITY}; all = every one of them. Every photo has sensor "
        "noise (sigma 3). A rejected image (ValueError) counts as wrong.", "", *lines, "",
        f"Generated by `OMP_NUM_THREADS=1 python benchmarks/instruction_table.py --camera-only --camera-items "
        f"{args.camera_items}` in {time.time() - started:.0f} s (1-min load average {load[0]:.1f} on "
        f"{os.cpu_count()} cores; checkpoint: {provenance(generator)})."])
    write_tables(args.out.with_name(args.out.name + "_camera"), text, rows, args.csv)


def main() -> None:
    """Run the benchmark, print the tables, write markdown and CSV."""
    import torch

    from vafn_media.engines import RECORDED_PAUSES_S, recorded_templates
    from vafn_media.generator import InstructionGenerator

    args = parse_args()
    torch.set_num_threads(1)
    started = time.time()
    generator = InstructionGenerator.load(args.checkpoint)
    if args.people_speech is not None:
        import real_people

        real_people.main(["--speech", *map(str, args.people_speech), "--handwriting", str(args.people_handwriting),
                          "--pocketsphinx"] + (["--checkpoint", args.checkpoint] if args.checkpoint else []))
    if not (args.robust_only or args.camera_only):
        table1(args, generator, started)
    if args.camera_items:
        write_camera(args, generator)
    if args.robust_items and not args.camera_only:
        robust_started = time.time()
        lines, rows = robust_section(generator, args.robust_items,
                                     engines=args.robust_engines.split(",") if args.robust_engines else None)
        load = os.getloadavg()
        shares = generator.metadata.get("args", {})
        engines = "; ".join(engine_note(name, voice, float(shares.get(f"{name}_probability", 0)))
                            for name, voice in (("mbrola", "MBROLA's voice us2"), ("pico", "SVOX Pico's voice en-GB"),
                                                ("rhvoice", "RHVoice's voices slt and lyubov"),
                                                ("dectalk", "DECtalk's speakers Rita and Wendy")))
        pause, comma, stop = (RECORDED_PAUSES_S[mark] for mark in ("", ",", "."))
        text = "\n".join([
            f"Robustness of the speech reader: {args.robust_items} held-out instructions (lengths 1-10, random "
            f"phrasings) per engine; espeak = held-out voices and variants of the training engine; {engines}; "
            "flite and festival (Festival's diphone voices rab, ked and don) were never used for training; "
            "piper = Piper's neural voice joe (a person's voice learnt by a neural network; its text front end is "
            "espeak-ng's phonemiser), never used for training; "
            "recorded = a person's voice, never used for training (Allison "
            f"Smith's Asterisk prompts: 8 kHz recordings of single words, joined with pauses of {pause} s, {comma} s "
            f"after a comma and {stop} s after a full stop, in the {len(recorded_templates())} phrasings they can "
            "say; its fast rendition is the recording time-compressed by a phase vocoder, not a person speaking "
            "fast). "
            "Conditions: clean 16 kHz; 8 kHz = 300-3400 Hz band sampled at 8 kHz; "
            "reverb = simulated room, RT60 0.6 s; 10 dB noise = white noise at 10 dB SNR; fast = the engine's own "
            "rate control (espeak 1.4x, others duration x0.7). 0.25 s of silence surrounds every clip. AV = the same "
            "audio plus the item's clean held-out image. Per digit = 1 - edit distance / reference digits. "
            "A rejected input (ValueError) counts as wrong.", "", *lines, "",
            f"Generated by `OMP_NUM_THREADS=1 python benchmarks/instruction_table.py --robust-items "
            f"{args.robust_items}` in {time.time() - robust_started:.0f} s (1-min load average {load[0]:.1f} on "
            f"{os.cpu_count()} cores; checkpoint: {provenance(generator)})."])
        write_tables(args.out.with_name(args.out.name + "_robust"), text, rows, args.csv)


def table1(args: argparse.Namespace, generator, started: float) -> None:
    """Table 1 (held-out split, every row and difficulty), the in-distribution comparison and the alignment probe."""
    from vafn_media.dataset import generate_raw

    load = os.getloadavg()
    rows = list(ROWS)
    heldout = evaluate_split(generator, "heldout", args.seeds, args.items, args.workers, rows)
    weights = generator.fusion_weights or {"audio": 1.0, "image": 1.0}
    lines = [f"Held-out split (unseen voices/variants, handwriting and fonts); {args.seeds} seeds x {args.items} items "
             f"per cell; accuracy = exact sequence match (mean ± std over seeds); "
             f"time per instruction on 1 CPU thread, "
             f"features included (mean ± std over items). Fusion reliability weights (calibrated by "
             f"vafn_media.calibration on training voices and glyph sets, never on these items): {weights}.",
             f"Wall time depends on machine load "
             f"(1-min load average at start: {load[0]:.1f} on {os.cpu_count()} cores); "
             "CPU time is the thread CPU time of the call, which other processes affect much less.", "",
             "Acted on correctly / wrongly: read right / wrong and not flagged low_confidence (a rejected input is "
             "neither), what a robot executes.", "",
             "| Input | Difficulty | Time (s) | CPU time (s) | Accuracy (%) | Per digit (%) | Acted on correctly (%) "
             "| Acted on wrongly (%) | Paper accuracy (%) | Paper time (s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    csv_rows = [["split", "input", "difficulty", "time_mean_s", "time_std_s", "cpu_mean_s", "cpu_std_s",
                 "accuracy_mean", "accuracy_std", "paper_accuracy", "seeds", "items_per_seed", "digit_accuracy",
                 "acted_right", "acted_wrong"]]
    for row in rows:
        for k, difficulty in enumerate(DIFFICULTY_LENGTHS):
            t_mean, t_std, c_mean, c_std, a_mean, a_std, digit = summarise(heldout, row, difficulty)
            paper = PAPER_ACCURACY.get(row)
            paper_text = f"{paper[k]:.1f}" if paper else "-"
            paper_time = PAPER_LATENCY_S.get(row.replace(" (noise)", ""), "-")
            low, high = DIFFICULTY_LENGTHS[difficulty]
            right = np.mean([r.acted_right for r in heldout[(row, difficulty)]])
            wrong = np.mean([r.acted_wrong for r in heldout[(row, difficulty)]])
            lines.append(f"| {row} | {difficulty.capitalize()} ({low}-{high}) | {t_mean:.4f} ± {t_std:.4f} | "
                         f"{c_mean:.4f} ± {c_std:.4f} | {a_mean:.1f} ± {a_std:.1f} | {digit:.1f} | {right:.1f} | "
                         f"{wrong:.1f} | {paper_text} | {paper_time} |")
            csv_rows.append(["heldout", row, difficulty, f"{t_mean:.6f}", f"{t_std:.6f}", f"{c_mean:.6f}",
                             f"{c_std:.6f}", f"{a_mean:.2f}", f"{a_std:.2f}", paper[k] if paper else "", args.seeds,
                             args.items, f"{digit:.2f}", f"{right:.2f}", f"{wrong:.2f}"])
    if args.in_distribution:
        compare_rows = ["Audio", "Visual", "Audio-Visual"]
        inside = evaluate_split(generator, "test", args.in_distribution, args.items, args.workers, compare_rows)
        lines += ["", f"In-distribution (training voices/glyph sets, fresh items; {args.in_distribution} seed(s)) vs "
                      "held-out accuracy (%):", "",
                  "| Input | Difficulty | In-distribution | Held-out |", "|---|---|---|---|"]
        for row in compare_rows:
            for difficulty in DIFFICULTY_LENGTHS:
                a_in = summarise(inside, row, difficulty)[4]
                a_out = summarise(heldout, row, difficulty)[4]
                lines.append(f"| {row} | {difficulty.capitalize()} | {a_in:.1f} | {a_out:.1f} |")
                csv_rows.append(["test", row, difficulty, "", "", "", "", f"{a_in:.2f}", "", "", args.in_distribution,
                                 args.items])
    if args.transfer_items:
        probe_items = generate_raw(EVAL_SEED_BASE + 99, "heldout", args.items, workers=args.workers)
        transfer = cross_modal_probe(generator, args.transfer_items, probe_items)
        lines += ["", "Cross-modal alignment: a fresh decoder trained (400 CTC steps) on one modality's Φ only, "
                      f"frozen encoders, evaluated on {args.items} held-out items (exact match %):", "",
                  "| Decoder trained on | reads audio Φ | reads image Φ |", "|---|---|---|"]
        for source in ("audio", "image"):
            lines.append(f"| {source} Φ | {transfer[(source, 'audio')]:.1f} | {transfer[(source, 'image')]:.1f} |")
            for target in ("audio", "image"):
                csv_rows.append([f"transfer:{source}->{target}", "", "", "", "", "", "",
                                 f"{transfer[(source, target)]:.2f}", "", "", 1, args.items])
    lines += ["", f"Generated by `OMP_NUM_THREADS=1 python benchmarks/instruction_table.py "
                  f"--seeds {args.seeds} --items {args.items}` in {time.time() - started:.0f} s "
                  f"(checkpoint: {provenance(generator)})."]
    write_tables(args.out, "\n".join(lines), csv_rows, args.csv)


if __name__ == "__main__":
    main()
