"""Zero-shot transfer of a packaged policy to other robots and arm counts (no retraining).

    python benchmarks/transfer.py --algo sac --n-test 50

Evaluates ``load_pretrained(algo)`` (trained on three KUKA arms) on ``VAFN/MultiArmReach-v1`` with each robot and arm
count, on held-out test instructions of lengths 1-10 (:class:`vafn_gym.InstructionBenchmark`), and writes
``results/learning/transfer_<algo>.md``. A policy whose actor was built for three arms (one-hot arm ids) cannot run on
another arm count: that row says so instead of a number.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

import torch  # noqa: E402

from vafn_gym import InstructionBenchmark, episode_rates  # noqa: E402
from vafn_sb3 import load_pretrained  # noqa: E402

SETTINGS = (
    ("kuka", 3), ("panda", 3), ("xarm", 3), ("kuka", 4), ("kuka", 6),
)


def main() -> None:
    """Evaluate the packaged policy on every setting; print and write a Markdown table."""
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--algo", default="sac", help="algorithm of the packaged policy")
    parser.add_argument("--n-test", type=int, default=50, help="held-out instructions per setting")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "results" / "learning", help="output folder")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = load_pretrained(args.algo)
    lines = [f"# Zero-shot transfer of the packaged `{args.algo}` policy (trained on 3 KUKA arms)", "",
             f"`python benchmarks/transfer.py --algo {args.algo} --n-test {args.n_test}`; held-out test instructions, "
             "lengths 1-10, `VAFN/MultiArmReach-v1`, default targets, inactive arms held.", "",
             "| robot | arms | success | collision rate | mean steps |", "|---|---|---|---|---|"]
    for robot, n_arms in SETTINGS:
        bench = InstructionBenchmark("VAFN/MultiArmReach-v1", 1, 10, n_test=args.n_test,
                                     env_kwargs={"robot": robot, "n_arms": n_arms})
        try:
            rows = bench.evaluate(model)
        except ValueError as error:  # the actor's input layout does not fit this arm count
            line = f"| {robot} | {n_arms} | not applicable: {str(error)[:90]} | | |"
        else:
            rates = episode_rates(rows)
            line = (f"| {robot} | {n_arms} | {rates['success']:.2f} | {rates['collision']:.2f} | "
                    f"{rates['episode_steps']:.0f} |")
        print(line, flush=True)
        lines.append(line)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"transfer_{args.algo}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
