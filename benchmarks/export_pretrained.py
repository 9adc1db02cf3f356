"""Turn a trained model (SB3 zip) into a packaged weights-only policy with its provenance and held-out numbers.

    python benchmarks/export_pretrained.py --algo sac --model runs/sac_seed0.zip \\
        --summary results/learning/sac_ThreeArmReach-v1_summary.json

Writes ``vafn_sb3/pretrained/<algo>__<EnvName>.zip`` (weights only; ``--out`` another folder) and ``.json`` (the
commit, the training command and time from the learning summary, plus a fresh evaluation of exactly the exported file
on ``--n-test`` held-out instructions).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

import torch  # noqa: E402

from vafn_gym import InstructionBenchmark, episode_rates  # noqa: E402
from vafn_sb3 import load_weights, save_weights  # noqa: E402
from vafn_sb3.loading import add_trust_flag, load_model_or_exit  # noqa: E402
from vafn_sb3.pretrained import pretrained_path  # noqa: E402
from zoo.jobs import git_commit  # noqa: E402
from zoo.registry import register_algorithms, require_algorithm  # noqa: E402


def main() -> None:
    """Export, reload the exported file and evaluate it; write the metadata."""
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--algo", required=True, help="zoo key of the algorithm (required; default: none)")
    parser.add_argument("--env", default="VAFN/ThreeArmReach-v1", help="env ID the model was trained on")
    parser.add_argument("--model", type=Path, required=True,
                        help="a model saved by benchmarks/learning.py --save (weights only, or an SB3 zip, rebuilt "
                        "without unpickling; with --trust-remote-code SB3's own load keeps its pickled settings too)")
    parser.add_argument("--summary", type=Path, required=True, help="the learning summary the model came from")
    parser.add_argument("--seed", type=int, default=0, help="which seed of the summary the model is")
    parser.add_argument("--n-test", type=int, default=100, help="held-out instructions of the stored evaluation")
    parser.add_argument("--note", default=None,
                        help="a sentence stored with the policy, e.g. why one that fails is shipped (None: no note)")
    parser.add_argument("--out", type=Path, default=None,
                        help="folder of the exported pair (None: the package's vafn_sb3/pretrained)")
    add_trust_flag(parser)
    args = parser.parse_args()
    path = pretrained_path(args.algo, args.env)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        path = args.out / path.name
    torch.set_num_threads(1)
    register_algorithms()
    require_algorithm(args.algo)
    model, _ = load_model_or_exit(args.model, args.algo, trust_remote_code=args.trust_remote_code)
    save_weights(model, path)
    policy = load_weights(path)  # exactly the shipped file
    start = time.perf_counter()
    rows = InstructionBenchmark(args.env, 1, 10, n_test=args.n_test).evaluate(policy)
    rates = episode_rates(rows)
    summary = json.loads(args.summary.read_text())
    command = shlex.split(summary["command"])
    # a weights-only file keeps no step count: the training command's own
    steps = int(model.num_timesteps) or (int(command[command.index("--steps") + 1]) if "--steps" in command else 0)
    info = {
        "algo": args.algo,
        "env_id": args.env,
        "commit": git_commit(),
        "training_command": summary["command"],
        "training_seed": args.seed,
        "training_env_steps": steps,
        "training_wall_s": summary["wall_s"],
        "training_cpu_s": summary["cpu_s"],
        "evaluation": {
            "protocol": f"InstructionBenchmark({args.env!r}, 1, 10, n_test={args.n_test}).evaluate",
            **{key: rates[key] for key in ("success", "collision", "episode_steps")},
            "eval_wall_s": round(time.perf_counter() - start, 1),
        },
        "export_command": shlex.join(sys.argv),
        **({"note": args.note} if args.note else {}),
    }
    path.with_suffix(".json").write_text(
        json.dumps(info, indent=2) + "\n"
    )
    print(json.dumps(info, indent=2))


if __name__ == "__main__":
    main()
