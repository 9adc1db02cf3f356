"""Where a trained policy fails: its failed held-out episodes counted by outcome, failing arm and timing.

    python benchmarks/failures.py runs/models/sac_seed0.zip --env-kwargs '{"inactive_arms": "policy"}'
    python benchmarks/failures.py --pretrained sac

Runs the policy once on each held-out test instruction (:class:`vafn_gym.InstructionBenchmark`, lengths 1-10, the
episodes of every other benchmark) and counts the failed episodes by outcome (collision or timeout), the arm that was
active when it went wrong, and whether it went wrong within ``--handover-steps`` env steps of the previous waypoint
(a hand-over: the next arm set off while the last one was still near its target). Prints a Markdown table.

With ``--k K`` the model first adapts to each instruction as ``benchmarks/adaptation.py`` does (the same support
seeds and evaluation episode: ``evaluate_adaptation`` with one episode), so its failures are those of that study's
rows at K (e.g. ``--env VAFN/ThreeArmReachHidden-v1 --max-length 4 --n-test 15 --k 50``).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

import torch  # noqa: E402

from vafn_gym import InstructionBenchmark, episode_rates  # noqa: E402
from vafn_sb3 import load_pretrained  # noqa: E402
from vafn_sb3.common.adaptation import evaluate_adaptation  # noqa: E402
from vafn_sb3.loading import add_trust_flag, load_model_or_exit  # noqa: E402


def failure_table(failed: list[dict], handover_steps: int) -> list[str]:
    """Markdown rows counting the failed episodes ``failed`` (:func:`vafn_gym.run_episode` rows)."""
    counts = Counter(
        (row["outcome"], row["failed_arm"], row["steps_after_waypoint"] <= handover_steps) for row in failed
    )
    lines = [f"| outcome | active arm | within {handover_steps} steps of the last waypoint | episodes |",
             "|---|---|---|---|"]
    for (outcome, arm, handover), count in counts.most_common():
        lines.append(f"| {outcome} | {arm} | {'yes' if handover else 'no'} | {count} |")
    return lines


def main() -> None:
    """Evaluate one saved or packaged policy and print its failures."""
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("model", nargs="?", type=Path, help="a saved model (.zip or weights-only file)")
    parser.add_argument("--pretrained", default=None, help="evaluate a packaged policy instead (e.g. sac)")
    parser.add_argument("--algo", default=None, help="force the model's algorithm key")
    add_trust_flag(parser)
    parser.add_argument("--env", default="VAFN/ThreeArmReach-v1", help="env ID")
    parser.add_argument("--env-kwargs", type=json.loads, default={},
                        help="JSON, e.g. '{\"inactive_arms\": \"policy\"}'")
    parser.add_argument("--n-test", type=int, default=100, help="held-out test instructions")
    parser.add_argument("--min-length", type=int, default=1, help="shortest test instruction")
    parser.add_argument("--max-length", type=int, default=10, help="longest test instruction")
    parser.add_argument("--k", type=int, default=0, help="adaptation steps before each episode (0: none)")
    parser.add_argument("--n-support", type=int, default=400, help="support transitions per adaptation (with --k)")
    parser.add_argument("--seed", type=int, default=0, help="support and episode seed of the adaptation study (--k)")
    parser.add_argument("--handover-steps", type=int, default=10,
                        help="a failure this many env steps or fewer after a waypoint counts as at the hand-over")
    args = parser.parse_args()
    if (args.model is None) == (args.pretrained is None):
        parser.error("give a model path or --pretrained ALGO (one of them)")
    if args.k < 0:
        parser.error(f"--k must be >= 0, got {args.k}")
    torch.set_num_threads(1)
    if args.pretrained is not None:
        model = load_pretrained(args.pretrained, env_id=args.env)
    else:
        model, _ = load_model_or_exit(args.model, args.algo, trust_remote_code=args.trust_remote_code)
    benchmark = InstructionBenchmark(args.env, args.min_length, args.max_length, n_test=args.n_test,
                                     env_kwargs=args.env_kwargs)
    if args.k == 0:
        rows = benchmark.evaluate(model)
    else:
        adapted = evaluate_adaptation(model, args.env, benchmark.test_tasks, args.n_support, [args.k],
                                      n_eval_episodes=1, seed=args.seed, env_kwargs=args.env_kwargs,
                                      keep_episodes=True)
        rows = [{"length": len(task), **row["episodes"][0]} for task, row in zip(benchmark.test_tasks, adapted)]
    rates = episode_rates(rows)
    failed = [row for row in rows if row["outcome"] != "success"]
    after = f" after {args.k} adaptation steps on {args.n_support} support transitions" if args.k else ""
    print(f"{len(rows)} held-out instructions{after}: success {rates['success']:.2f}, collision rate "
          f"{rates['collision']:.2f}, {len(failed)} failed\n")
    if failed:
        print("\n".join(failure_table(failed, args.handover_steps)))


if __name__ == "__main__":
    main()
