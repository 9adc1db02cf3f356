"""Zero-shot transfer of a trained policy to other robots and arm counts (no retraining).

    python benchmarks/transfer.py --algo sac --n-test 50
    python benchmarks/transfer.py --algo sac --models 'runs/base3/sac_*_seed*.zip' \
        --env-kwargs '{"frame": "base"}' --tag _base
    python benchmarks/transfer.py --algo sac --n-test 30 --embodiment --tag _embodiment

``--embodiment`` runs the three-arm variants of ``vafn_gym.EMBODIMENT_VARIANTS`` instead (payload, damped joints,
weaker motors, moved bases, other robots), each beside the scripted controller on the same instructions: where the
scripted controller fails, the variant is out of reach of any policy, not a failure to adapt.

Evaluates ``load_pretrained(algo)`` (trained on three KUKA arms), or each of the saved ``--models`` (one per seed), on
``VAFN/MultiArmReach-v1`` with each robot and arm count, on held-out test instructions of lengths 1-10
(:class:`vafn_gym.InstructionBenchmark`), and writes ``results/learning/transfer_<algo><tag>.md``. On another arm count
the shared actor runs through :func:`vafn_sb3.shared_actor_for_env`; an actor built with one-hot ids for three arms
cannot, and that row says so instead of a number.
"""

from __future__ import annotations

import argparse
import glob
import json
import shlex
import sys
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from vafn_gym import EMBODIMENT_VARIANTS, InstructionBenchmark, ScriptedController, episode_rates  # noqa: E402
from vafn_gym.benchmarks import confidence_half_width  # noqa: E402
from vafn_gym.constants import ACTION_PER_ARM  # noqa: E402
from vafn_sb3 import load_pretrained, shared_actor_for_env  # noqa: E402
from vafn_sb3.loading import add_trust_flag, load_model_or_exit  # noqa: E402
from zoo.jobs import short_commit  # noqa: E402

SETTINGS = (
    ("kuka", 3), ("panda", 3), ("xarm", 3), ("kuka", 4), ("kuka", 6),
)
METRICS = ("success", "collision", "episode_steps")


def policy_for(model: Any, env: gym.Env) -> Any:
    """``model`` itself where ``env`` has its spaces, else its shared actor rebuilt for ``env``'s arm count."""
    if model.observation_space.shape == env.observation_space.shape:
        return model
    return shared_actor_for_env(model, env)


def mean_ci(values: list[float]) -> str:
    """``mean ± 95 % half width`` over seeds (the mean alone for one seed)."""
    array = np.asarray(values, dtype=np.float64)
    half = float(confidence_half_width(array[:, None])[0])
    return f"{array.mean():.2f} ± {half:.2f}" if len(array) > 1 else f"{array.mean():.2f}"


def main() -> None:
    """Evaluate the policy (or every seed's) on every setting; print and write a Markdown table."""
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--algo", default="sac", help="algorithm of the policy")
    parser.add_argument("--models", default=None,
                        help="glob of saved models (one per seed) instead of the packaged policy")
    parser.add_argument("--env-kwargs", type=json.loads, default={},
                        help='JSON kwargs of every evaluation env, e.g. \'{"frame": "base"}\' (match the training env)')
    parser.add_argument("--n-test", type=int, default=50, help="held-out instructions per setting")
    parser.add_argument("--embodiment", action="store_true",
                        help="the embodiment variants on three arms (with the scripted controller) instead")
    parser.add_argument("--tag", default="", help="suffix of the output file")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "results" / "learning", help="output folder")
    add_trust_flag(parser)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.models is None:
        models, source = [load_pretrained(args.algo)], f"the packaged `{args.algo}` policy"
    else:
        paths = sorted(glob.glob(args.models))
        if not paths:
            raise SystemExit(f"no model matches {args.models!r}")
        models = [load_model_or_exit(path, args.algo, trust_remote_code=args.trust_remote_code)[0] for path in paths]
        source = f"`{args.algo}`, {len(paths)} seed(s): " + ", ".join(Path(p).name for p in paths)
    trained_arms = models[0].action_space.shape[0] // ACTION_PER_ARM
    command = shlex.join(["python", "benchmarks/transfer.py", *sys.argv[1:]])
    if args.embodiment:
        settings = [(label, {"n_arms": 3, **kwargs}) for label, kwargs in EMBODIMENT_VARIANTS.items()]
        header = ["variant", "success", "collision rate", "mean steps", "scripted controller's success"]
    else:
        settings = [(f"{robot} | {n_arms}", {"robot": robot, "n_arms": n_arms}) for robot, n_arms in SETTINGS]
        header = ["robot", "arms", "success", "collision rate", "mean steps"]
    lines = [f"# Zero-shot transfer of {source} (trained on {trained_arms} arms)", "",
             f"`{command}` (commit {short_commit()}); held-out test instructions, lengths 1-10, "
             f"`VAFN/MultiArmReach-v1`, default targets, inactive arms held, env kwargs "
             f"{json.dumps(args.env_kwargs)}; mean ± 95 % CI over seeds.", "",
             "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for label, kwargs in settings:
        bench = InstructionBenchmark("VAFN/MultiArmReach-v1", 1, 10, n_test=args.n_test,
                                     env_kwargs={**args.env_kwargs, **kwargs})
        probe = bench.make_env()
        try:
            per_seed = [episode_rates(bench.evaluate(policy_for(model, probe))) for model in models]
        except ValueError as error:  # the actor's input layout does not fit this arm count
            line = f"| {label} | not applicable: {str(error)[:90]} | | |"
        else:
            line = f"| {label} | " + " | ".join(mean_ci([r[m] for r in per_seed]) for m in METRICS) + " |"
            if args.embodiment:
                line += f" {episode_rates(bench.evaluate(ScriptedController.for_env(probe)))['success']:.2f} |"
        finally:
            probe.close()
        print(line, flush=True)
        lines.append(line)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"transfer_{args.algo}{args.tag}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
