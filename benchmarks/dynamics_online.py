"""The robot changes mid-stream: does the online controller finish the running instruction and the ones after it?

    python benchmarks/dynamics_online.py --out results/adaptation/dynamics

For every held-out dynamics variant (``vafn_gym.dynamics.DYNAMICS_VARIANTS["test"]``) a stream of ``--n-instructions``
held-out test instructions (lengths 2-3) runs under :class:`vafn_sb3.OnlineController` on nominal dynamics; after the
first instruction has run ``--change-after`` steps the stream's arms switch to the variant. Controllers (one model,
trained on the nominal robot; default the packaged MAML-SAC):

- ``unadapted``: the model as it is (K = 0), never told;
- ``maml-announced``: told at once (``announce_dynamics``): MAML-SAC re-adapts on the twin (``--k`` inner rounds on
  ``--n-support`` twin steps);
- ``identify-announced``: told at once: the turn of the response is identified on ``--n-support`` twin steps and undone
  (:class:`vafn_sb3.inference.DynamicsCompensation`);
- ``identify-online``: never told: the turn is identified from the arm's own last steps (``steps to identify``: control
  steps from the change until its fit is within 20° of the variant's turn, on variants turned by 30° or more).

Writes ``dynamics_online.md`` (rates over variants, first-action latency after an announcement) and prints it.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

import vafn_gym  # noqa: E402,F401  (registers the env IDs)
from vafn_gym.benchmarks import suite_tasks  # noqa: E402
from vafn_gym.dynamics import DYNAMICS_VARIANTS, DYNAMICS_VERSION, Dynamics  # noqa: E402
from vafn_gym.files import repository_commit  # noqa: E402
from vafn_sb3 import OnlineController, load_pretrained  # noqa: E402
from vafn_sb3.inference.dynamics import DynamicsCompensation  # noqa: E402
from vafn_sb3.loading import add_trust_flag, load_model_or_exit  # noqa: E402

CONTROLLERS = ("unadapted", "maml-announced", "identify-announced", "identify-online")


def controller_for(name: str, model: Any, stream: gym.Env, args: argparse.Namespace) -> OnlineController:
    """The online controller of one row of the study."""
    n_arms = stream.unwrapped.n_arms
    if name == "unadapted":
        return OnlineController(model, stream, k=0)
    if name == "maml-announced":
        return OnlineController(model, stream, k=args.k, n_support=args.n_support)
    if name == "identify-announced":
        return OnlineController(DynamicsCompensation(model, n_arms), stream, k=1, n_support=args.n_support)
    return OnlineController(DynamicsCompensation(model, n_arms, online=True), stream, k=0)


def run_stream(name: str, model: Any, variant: Dynamics, tasks: list, args: argparse.Namespace) -> dict[str, Any]:
    """One stream: the instructions queued at step 0, the variant switched on mid-first-instruction."""
    stream = gym.make("VAFN/ThreeArmStream-v1", arrivals={0: [t.to_code() for t in tasks]}, auto_dequeue=False,
                      horizon=args.horizon)
    controller = controller_for(name, model, stream, args)
    changed, announced, identified_after = False, name.endswith("announced"), -1
    compensation = controller.model if name == "identify-online" else None
    try:
        while stream.unwrapped.total_steps < args.horizon:
            controller.step()
            log = controller.log
            if not changed and log and stream.unwrapped.total_steps - log[0].start_step >= args.change_after:
                stream.unwrapped.set_dynamics(variant)
                if announced:
                    controller.announce_dynamics(variant)
                changed, change_step = True, stream.unwrapped.total_steps
            if changed and compensation is not None and identified_after < 0 and turned_back(compensation, variant):
                identified_after = stream.unwrapped.total_steps - change_step
            if len(log) == len(tasks) and log[-1].outcome != "running":
                break
    finally:
        controller.close()
        stream.close()
    log = controller.log
    event = controller.dynamics_events[0] if controller.dynamics_events else {}
    return {"controller": name, "variant": variant.label,
            "changed_success": float(bool(log) and log[0].success),
            "later_success": float(np.mean([e.success for e in log[1:]])) if len(log) > 1 else 0.0,
            "completed": sum(e.success for e in log), "collisions": sum(e.collisions > 0 for e in log),
            "first_action_ms": 1000 * event.get("first_action_s", float("nan")), "identified_after": identified_after}


def turned_back(compensation: DynamicsCompensation, variant: Dynamics) -> bool:
    """Whether the online fit is usable and within 20° of ``variant``'s turn."""
    response = compensation.response
    error = (response.rotation - variant.action_rotation + 180.0) % 360.0 - 180.0
    return response.usable and abs(error) <= 20.0


def main() -> None:
    """Every controller on every held-out variant; write and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=None, help="a MAML-SAC model trained on the nominal robot "
                        "(default: the packaged one)")
    add_trust_flag(parser)
    parser.add_argument("--n-instructions", type=int, default=3, help="instructions per stream")
    parser.add_argument("--change-after", type=int, default=15, help="steps into the first instruction")
    parser.add_argument("--k", type=int, default=5, help="maml-announced: inner rounds")
    parser.add_argument("--n-support", type=int, default=25, help="twin steps an announcement adapts on")
    parser.add_argument("--horizon", type=int, default=2000, help="stream steps at most")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "results" / "adaptation" / "dynamics",
                        help="output folder")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.model is None:
        model, source = load_pretrained("maml_sac"), "the packaged `maml_sac` (nominal VAFN/ThreeArmReach-v1)"
    else:
        model, source = load_model_or_exit(args.model, "maml_sac", trust_remote_code=args.trust_remote_code)[0], \
            f"`{args.model.name}`"
    env = gym.make("VAFN/ThreeArmReach-v1")
    tasks = suite_tasks(env, "test", min_length=2, max_length=3, n=args.n_instructions)
    env.close()
    start = time.perf_counter()
    rows = [run_stream(name, model, variant, tasks, args)
            for name, variant in tqdm([(n, v) for n in CONTROLLERS for v in DYNAMICS_VARIANTS["test"]])]
    lines = [f"# A changed robot mid-stream ({DYNAMICS_VERSION}, {len(DYNAMICS_VARIANTS['test'])} held-out variants)",
             "", f"Command: `python benchmarks/dynamics_online.py {shlex.join(sys.argv[1:])}` (commit "
             f"{repository_commit(REPO_ROOT)}); model: {source}; {len(tasks)} held-out instructions per stream "
             f"({', '.join(t.to_code() for t in tasks)}); the variant switched on {args.change_after} steps into the "
             f"first; {time.perf_counter() - start:.0f} s.", "",
             "| controller | instruction running at the change | instructions after it | streams with a contact "
             "| announcement → first action (ms, median / max) | steps to identify (median / max) |",
             "|---|---|---|---|---|---|"]
    for name in CONTROLLERS:
        mine = [r for r in rows if r["controller"] == name]
        latency = [r["first_action_ms"] for r in mine if not np.isnan(r["first_action_ms"])]
        timing = f"{np.median(latency):.0f} / {np.max(latency):.0f}" if latency else "–"
        turned = [r["identified_after"] for r, v in zip(mine, DYNAMICS_VARIANTS["test"])
                  if abs(v.action_rotation) >= 30]
        found = "–" if name != "identify-online" else (
            f"{np.median(turned):.0f} / {np.max(turned):.0f}" if min(turned) >= 0
            else f"{sum(t < 0 for t in turned)} never")
        lines.append(f"| {name} | {sum(r['changed_success'] for r in mine):.0f}/{len(mine)} | "
                     f"{np.mean([r['later_success'] for r in mine]):.2f} | {sum(r['collisions'] > 0 for r in mine)} "
                     f"| {timing} | {found} |")
    lines += ["", "Per variant (instruction at the change ✓/✗, then the share of later ones):", "",
              "| variant | " + " | ".join(CONTROLLERS) + " |", "|---|" + "---|" * len(CONTROLLERS)]
    for variant in DYNAMICS_VARIANTS["test"]:
        cells = [next(r for r in rows if r["controller"] == n and r["variant"] == variant.label) for n in CONTROLLERS]
        lines.append(f"| {variant.label} | " + " | ".join(
            f"{'✓' if c['changed_success'] else '✗'} {c['later_success']:.2f}" for c in cells) + " |")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "dynamics_online.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
