"""Training wrappers for the VAFN envs (Gymnasium wrappers; the zoo's ``env_wrapper`` hyperparameter takes them)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from vafn_gym.constants import GOAL_SLICE
from vafn_gym.dynamics import Dynamics, DynamicsSampler

__all__ = ["DynamicsTasks", "GoalDetours"]


class DynamicsTasks(gym.Wrapper):
    """Makes dynamics variants the env's *tasks*: ``set_task(variant)`` fixes the arms' dynamics (instructions are still
    drawn by the env), ``sampler.fixed_set`` lists the train variants. MAML-SAC then meta-learns over variants.

    ``set_task(None)`` returns to the env's own ``dynamics`` setting (e.g. a variant drawn at every reset), which is
    what MAML-SAC's warm-up and the end of its ``learn`` use.

    :param env: a :class:`~vafn_gym.envs.MultiArmEnv` (any wrappers).
    :param split: the variant split whose list ``sampler`` gives ("train"; "test" only to evaluate).
    """

    def __init__(self, env: gym.Env, split: str = "train") -> None:
        super().__init__(env)
        if not hasattr(env.unwrapped, "set_dynamics"):
            raise TypeError(f"DynamicsTasks needs a MultiArmEnv, got {type(env.unwrapped).__name__}")
        self.sampler = DynamicsSampler(split)

    def set_task(self, task: Any) -> None:
        """Fix the dynamics variant (a :class:`Dynamics` or a dict of its fields; ``None``: the env's own setting)."""
        self.env.unwrapped.set_dynamics(None if task is None else Dynamics.coerce(task))

    def get_task(self) -> Dynamics:
        """The dynamics the arms follow now."""
        return self.env.unwrapped.dynamics


class GoalDetours(gym.Wrapper):
    """Goal-observing training env whose active arm sometimes observes a wrong goal at a waypoint's start.

    A policy that reads its target from the observation is run on hidden targets with an *estimated* goal
    (``vafn_sb3.TargetInferencePolicy``); an early estimate can be centimetres off, so the arm heads somewhere else
    and must turn when the estimate moves. Trained only on true goals it has never been there, and it can stall. With
    probability ``probability`` a new waypoint's active arm observes a decoy (its target displaced uniformly within
    a ball of ``radius`` metres) for 1 to ``max_steps`` steps, then its true target. The reward, the distance reading
    and everything else are the env's own: only the goal entries of the observation change.

    :param env: a :class:`~vafn_gym.envs.MultiArmEnv` (any wrappers) with ``observe_goal=True`` and ``history=1``.
    :param probability: chance that a waypoint starts with a decoy goal.
    :param radius: largest displacement of a decoy from the target (metres, the observation's frame).
    :param max_steps: longest decoy, in control steps.
    """

    def __init__(self, env: gym.Env, probability: float = 0.5, radius: float = 0.12, max_steps: int = 30) -> None:
        super().__init__(env)
        base = env.unwrapped
        if not getattr(base, "observe_goal", False) or getattr(base, "history", None) != 1:
            raise ValueError(
                "GoalDetours needs a MultiArmEnv with observe_goal=True and history=1, got "
                f"observe_goal={getattr(base, 'observe_goal', None)}, history={getattr(base, 'history', None)}"
            )
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"probability must be in [0, 1], got {probability}")
        if not radius > 0.0:
            raise ValueError(f"radius must be positive, got {radius}")
        if int(max_steps) != max_steps or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {max_steps}")
        self.probability, self.radius, self.max_steps = float(probability), float(radius), int(max_steps)
        self._waypoint: tuple[int | None, int] | None = None
        self._offset = np.zeros(3)
        self._steps_left = 0
        self._rng = np.random.default_rng()

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Reset the env (and the decoy stream with ``seed``)."""
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None:
            self._rng = np.random.default_rng(seed)  # its own stream: the env's targets stay the unwrapped env's
        self._waypoint = None
        return self._detour(obs), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Step the env; the active arm's goal is the decoy while one lasts."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._steps_left -= 1
        return self._detour(obs), reward, terminated, truncated, info

    def _detour(self, obs: np.ndarray) -> np.ndarray:
        base = self.env.unwrapped
        arm = base.active_arm
        waypoint = (arm, base.task.waypoint_index)
        if waypoint != self._waypoint:  # a new waypoint (or episode): maybe draw a decoy
            self._waypoint = waypoint
            self._steps_left = 0
            if arm is not None and self._rng.random() < self.probability:
                direction = self._rng.normal(size=3)
                length = self.radius * self._rng.random() ** (1.0 / 3.0)  # uniform in the ball
                self._offset = direction / np.linalg.norm(direction) * length
                self._steps_left = int(self._rng.integers(1, self.max_steps + 1))
        if arm is None or self._steps_left <= 0:
            return obs
        obs = obs.copy()
        block = base.obs_slice(arm)
        goal = slice(block.start + GOAL_SLICE.start, block.start + GOAL_SLICE.stop)
        space = self.observation_space
        obs[goal] = np.clip(obs[goal] + self._offset, space.low[goal], space.high[goal])
        return obs
