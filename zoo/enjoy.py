"""Watch or record a trained vafn agent (or the scripted controller) on a VAFN env; rgb_array frames -> GIF / MP4.

    python zoo/enjoy.py --pretrained sac --instruction 2,3,1,3 --record demo.gif          # the packaged policy
    python zoo/enjoy.py --pretrained sac --n-test 100                                      # held-out evaluation
    python zoo/enjoy.py --algo sac --env VAFN/ThreeArmReach-v1 -f logs --record results/sac.gif
    python zoo/enjoy.py --algo sac --env VAFN/ThreeArmReach-v1 -f logs --render-mode human     # GUI window
    python zoo/enjoy.py --scripted --env VAFN/ThreeArmReach-v1 --instruction 2,3,1,3 --record demo.mp4

The model is found like ``python -m rl_zoo3.enjoy`` finds it (``-f/--exp-id/--load-best``) and rebuilt without
unpickling (:func:`vafn_sb3.loading.load_model`); the env kwargs saved with the run are reused, and its VecNormalize
statistics (a pickle) only with ``--trust-remote-code``. Runs one episode (one instruction) by default; recorded frames
carry the overlay of :mod:`vafn_gym.overlay`. Prints return, success and collision per episode (each episode is
:func:`vafn_gym.run_episode`). With ``--n-test N`` it instead scores the policy on the first N instructions of the
held-out suite of :class:`vafn_gym.InstructionBenchmark` (the protocol of every curve in the project; 200 in all).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402
from huggingface_sb3 import EnvironmentName  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize  # noqa: E402
from tqdm import tqdm  # noqa: E402

import vafn_gym  # noqa: E402
from vafn_gym.benchmarks import episode_seed, run_episode  # noqa: E402
from vafn_gym.overlay import VIDEO_SUFFIXES, FrameOverlay, VideoWriter  # noqa: E402
from vafn_media.cli import OneLineParser  # noqa: E402
from vafn_sb3.loading import add_trust_flag, load_model  # noqa: E402
from zoo.registry import register_algorithms, require_algorithm  # noqa: E402
from zoo.run_config import load_run_config  # noqa: E402

def load_run(algo: str, env_id: str, folder: str, exp_id: int, load_best: bool,
             trust_remote_code: bool = False) -> tuple[Any, dict, str | None]:
    """(model, env_kwargs, vecnormalize path or None) of a zoo run ``<folder>/<algo>/<EnvName>_<exp_id>``.

    The model loads with :func:`vafn_sb3.loading.load_model`, which rebuilds the SB3 zip without unpickling it; SB3's
    unpickling ``load`` and the run's ``vecnormalize.pkl`` (a pickle) are read only with ``trust_remote_code``.
    """
    from rl_zoo3.utils import get_model_path

    require_algorithm(algo)
    env_name = EnvironmentName(env_id)
    try:
        _, model_path, log_path = get_model_path(exp_id, folder, algo, env_name, load_best)
    except AssertionError as error:  # rl_zoo3 asserts that the run folder exists
        raise ValueError(f"-f {folder} --algo {algo}: {error}") from None
    config_path = Path(log_path) / str(env_name) / "config.yml"
    env_kwargs: dict = {}
    if config_path.is_file():
        config = load_run_config(config_path)
        env_kwargs = dict(config.get("env_kwargs") or {})
    stats = Path(log_path) / str(env_name) / "vecnormalize.pkl"
    if stats.is_file() and not trust_remote_code:
        raise ValueError(f"{stats} is a pickle (VecNormalize statistics), which runs code when loaded; refused. Pass "
                         "--trust-remote-code only if you made this run or trust its source")
    model, _ = load_model(model_path, algo, trust_remote_code=trust_remote_code)
    return model, env_kwargs, str(stats) if stats.is_file() else None


class RecordingWrapper(gym.Wrapper):
    """Renders every ``frame_skip``-th step (and every episode's first and last) with the overlay into ``writer``."""

    def __init__(self, env: gym.Env, writer: VideoWriter, frame_skip: int = 1) -> None:
        super().__init__(env)
        self.writer = writer
        self.overlay = FrameOverlay(env)
        self.frame_skip = max(int(frame_skip), 1)
        self._first: dict | None = None

    def _record(self, info: dict) -> None:
        self.writer.append(self.overlay(self.env.render(), info))

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict]:
        """Reset; the episode's first frame is recorded when it starts stepping."""
        obs, info = self.env.reset(**kwargs)
        self._first = info
        return obs, info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Step; record the frame when it is due or the episode ended."""
        if self._first is not None:
            self._record(self._first)
            self._first = None
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated or truncated or self.env.unwrapped.task.steps % self.frame_skip == 0:
            self._record(info)
        return obs, reward, terminated, truncated, info


def run(
    policy: Any,
    env_id: str,
    env_kwargs: dict,
    n_steps: int | None,
    render_mode: str | None,
    record: Path | None,
    stats_path: str | None = None,
    deterministic: bool = True,
    seed: int = 0,
    frame_skip: int = 1,
    n_episodes: int = 1,
) -> list[dict[str, float]]:
    """Roll ``policy`` for ``n_episodes`` episodes (or ``n_steps`` env steps when given, whichever ends first).

    Each episode is :func:`vafn_gym.run_episode` (episode ``e`` resets with ``vafn_gym.episode_seed(seed, e)``).
    Returns one ``{return, success, collision, length}`` per finished episode. With ``record`` the labelled frames
    stream to the video file as they are rendered (nothing is held in memory).
    """
    if record is not None and record.suffix not in VIDEO_SUFFIXES:
        raise ValueError(f"--record must end in one of {VIDEO_SUFFIXES}, got {record}")
    mode = "rgb_array" if record is not None else render_mode
    fps = max(1.0, vafn_gym.MultiArmEnv.metadata["render_fps"] / frame_skip)  # real-time playback
    writer = VideoWriter(record, fps) if record is not None else None
    env = gym.make(env_id, render_mode=mode, **env_kwargs)
    if writer is not None:
        env = RecordingWrapper(env, writer, frame_skip)
    transform = None
    if stats_path is not None:  # the run's observation statistics, frozen
        normalizer = VecNormalize.load(stats_path, DummyVecEnv([lambda: env]))
        normalizer.training, normalizer.norm_reward = False, False
        transform = normalizer.normalize_obs
    episodes: list[dict[str, float]] = []
    step = 0
    bar = tqdm(total=n_episodes, desc="episodes", unit="episode", disable=n_episodes < 2 and writer is None)
    try:
        while len(episodes) < n_episodes and (n_steps is None or step < n_steps):
            row = run_episode(policy, env, episode_seed(seed, len(episodes)), deterministic, transform,
                              max_steps=None if n_steps is None else n_steps - step)
            step += row["steps"]
            if row["outcome"] == "unfinished":
                break
            episode = {"return": row["return"], "success": row["success"], "collision": row["collision"],
                       "length": float(row["steps"])}
            episodes.append(episode)
            bar.update(1)
            tqdm.write(f"episode {len(episodes)}: return {episode['return']:.2f}, success {episode['success']:.0f}, "
                       f"collision {episode['collision']:.0f}, length {row['steps']}")
    finally:
        bar.close()
        env.close()
        if writer is not None and writer.n_frames:
            path = writer.close()
            print(f"wrote {path.resolve()} ({writer.n_frames} frames at {writer.fps:g} fps, "
                  f"{len(episodes)} episode{'s' if len(episodes) != 1 else ''})")
    return episodes


def evaluate_held_out(policy: Any, env_id: str, env_kwargs: dict, n_test: int) -> list[dict[str, Any]]:
    """Score ``policy`` once on each of the first ``n_test`` held-out test instructions (the versioned suite, lengths
    1-10) and print the rates."""
    rows = vafn_gym.InstructionBenchmark(env_id, n_test=n_test, env_kwargs=env_kwargs).evaluate(policy)
    rates = vafn_gym.episode_rates(rows)
    print(f"{env_id}: success {rates['success']:.3f}, collision rate {rates['collision']:.3f} "
          f"on {len(rows)} held-out instructions")
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    """Command-line entry point; returns the per-episode results."""
    parser = OneLineParser(
        prog="enjoy.py", description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        epilog="Example: python zoo/enjoy.py --pretrained sac --instruction 2,3,1,3 --record runs/enjoy/sac.mp4",
    )
    parser.add_argument("--algo", default="sac", help="zoo algorithm key of the trained agent (with -f)")
    parser.add_argument("--env", default="VAFN/ThreeArmReach-v1", choices=vafn_gym.ENV_IDS, help="environment ID")
    parser.add_argument("-f", "--folder", default="logs", help="zoo log folder the trained run is in")
    parser.add_argument("--exp-id", type=int, default=0, help="run number (0: latest)")
    parser.add_argument("--load-best", action="store_true", help="load best_model.zip instead of the final model")
    parser.add_argument("--scripted", action="store_true", help="run vafn_gym.ScriptedController (no trained agent)")
    parser.add_argument("--pretrained", default=None, help="run the packaged policy of this algorithm (e.g. sac)")
    parser.add_argument("--n-test", type=int, default=0, help="score on N held-out test instructions instead (0: off)")
    parser.add_argument("--n-episodes", type=int, default=1,
                        help="episodes to run; each executes one instruction (the fixed one, or a sampled one)")
    parser.add_argument("-n", "--n-timesteps", type=int, default=None,
                        help="stop after this many env steps even if the episodes are not finished (None: no cap)")
    parser.add_argument("--instruction", default=None, help="fixed instruction, e.g. 2,3,1,3 (default: sampled)")
    parser.add_argument("--env-kwargs", nargs="*", default=[], help="extra env kwargs as key:value (values eval'd)")
    parser.add_argument("--render-mode", choices=["human", "rgb_array"], default=None,
                        help="human opens a GUI window (default: no rendering unless --record)")
    parser.add_argument("--record", type=Path, default=None,
                        help="write labelled frames to this .gif or .mp4 (streamed while the episodes run)")
    parser.add_argument("--frame-skip", type=int, default=2, help="record every N-th control step")
    parser.add_argument("--stochastic", action="store_true", help="sample actions instead of the deterministic policy")
    parser.add_argument("--seed", type=int, default=0, help="seed of the env")
    add_trust_flag(parser)
    args = parser.parse_args(argv)
    if (args.n_timesteps is not None and args.n_timesteps < 1) or args.frame_skip < 1 or args.n_episodes < 1:
        parser.error("-n, --n-episodes and --frame-skip must be >= 1")
    if args.render_mode == "human" and not os.environ.get("DISPLAY"):
        parser.error("--render-mode human needs a display; use --record out.gif on a headless machine")
    try:
        return _run_main(args)
    except (ValueError, OSError, yaml.YAMLError) as error:  # bad input: one line, exit 2
        parser.fail(error)


def _run_main(args: argparse.Namespace) -> list[dict[str, Any]]:
    """:func:`main` after parsing; bad input raises ``ValueError`` / ``OSError``."""
    register_algorithms()
    stats = None
    env_kwargs: dict = {}
    if args.pretrained is not None:
        from vafn_sb3 import load_pretrained

        policy = load_pretrained(args.pretrained, env_id=args.env)
    elif not args.scripted:
        policy, env_kwargs, stats = load_run(args.algo, args.env, args.folder, args.exp_id, args.load_best,
                                             args.trust_remote_code)
    for item in args.env_kwargs:
        key, _, value = item.partition(":")
        try:
            env_kwargs[key] = eval(value)  # same convention as the zoo's --env-kwargs (the user's own text)
        except Exception as error:  # noqa: BLE001 - any error of the expression is a bad argument
            raise ValueError(f"--env-kwargs {item!r}: {type(error).__name__}: {error}") from None
    if args.scripted:
        probe = gym.make(args.env, **env_kwargs)
        policy = vafn_gym.ScriptedController.for_env(probe)
        probe.close()
    if args.n_test > 0:
        return evaluate_held_out(policy, args.env, env_kwargs, args.n_test)
    if args.instruction is not None:
        env_kwargs["instruction"] = args.instruction
    return run(policy, args.env, env_kwargs, args.n_timesteps, args.render_mode, args.record, stats,
               not args.stochastic, args.seed, args.frame_skip, args.n_episodes)


if __name__ == "__main__":
    main()
