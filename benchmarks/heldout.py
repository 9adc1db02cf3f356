"""Held-out benchmark: a packaged policy on every instruction of the versioned test suite, by instruction length.

    python benchmarks/heldout.py --pretrained sac maml_sac --env VAFN/ThreeArmReach-v1

Runs :meth:`vafn_gym.InstructionBenchmark.evaluate` (one episode per instruction, the one protocol of
:mod:`vafn_gym.benchmarks`) over the whole held-out suite (``heldout-v1``: 200 distinct test-split instructions, every
length 1-10) and writes ``<out>/heldout.md`` and ``<out>/heldout.csv`` (one row per policy and instruction) with the
commit they came from.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))
os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

import vafn_gym  # noqa: E402,F401  (registers the env IDs)
from vafn_gym import InstructionBenchmark, episode_rates  # noqa: E402
from vafn_gym.benchmarks import HELDOUT_VERSION  # noqa: E402
from vafn_gym.files import repository_commit, write_csv_rows  # noqa: E402


def table(name: str, rows: list[dict]) -> list[str]:
    """Markdown lines: one row per instruction length, then the whole suite."""
    lines = [f"### {name}", "", "| length | instructions | success | collision | mean steps |", "|---|---|---|---|---|"]
    for length in sorted({row["length"] for row in rows}):
        rates = episode_rates([row for row in rows if row["length"] == length])
        count = sum(row["length"] == length for row in rows)
        lines.append(f"| {length} | {count} | {rates['success']:.3f} | {rates['collision']:.3f} | "
                     f"{rates['episode_steps']:.0f} |")
    rates = episode_rates(rows)
    lines.append(f"| all | {len(rows)} | {rates['success']:.3f} | {rates['collision']:.3f} | "
                 f"{rates['episode_steps']:.0f} |")
    return lines + [""]


def main(argv: list[str] | None = None) -> list[dict]:
    """Parse arguments, evaluate every policy on the whole suite, write the table and the rows."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--pretrained", nargs="+", default=["sac", "maml_sac"], help="packaged policies (algorithms)")
    parser.add_argument("--env", default="VAFN/ThreeArmReach-v1", help="env ID of the packaged policies")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "results", help="output folder")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    from vafn_sb3 import load_pretrained

    benchmark = InstructionBenchmark(args.env)
    distinct = len({task.to_code() for task in benchmark.test_tasks})
    lines = [f"# Held-out suite ({HELDOUT_VERSION})", "",
             f"`python benchmarks/heldout.py --pretrained {' '.join(args.pretrained)} --env {args.env}` at commit "
             f"{repository_commit(REPO_ROOT)}: {len(benchmark.test_tasks)} test instructions ({distinct} distinct), "
             "one deterministic episode each.", ""]
    all_rows = []
    for algo in args.pretrained:
        start = time.perf_counter()
        rows = benchmark.evaluate(load_pretrained(algo, args.env))
        wall = time.perf_counter() - start
        lines += table(f"{algo} on {args.env} ({wall:.0f} s)", rows)
        all_rows += [{"policy": algo, **{k: v for k, v in row.items() if k != "return_terms"}} for row in rows]
        print("\n".join(table(algo, rows)), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "heldout.md").write_text("\n".join(lines))
    write_csv_rows(all_rows, args.out / "heldout.csv", missing="")
    return all_rows


if __name__ == "__main__":
    main()
