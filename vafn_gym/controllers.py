"""ScriptedController: solves any instruction from the observation alone (the ceiling for every learning curve).

It never reads simulator state or the instruction. Where the active target is not in the observation, only its
distance, the controller *trilaterates* it: it moves the arm along three probe directions, then solves the linear
least-squares system given by ``|p_k - t|^2 = d_k^2`` and keeps refining the estimate as new (p, d) pairs arrive.
Only one arm enters the shared region at a time: the active arm waits until every other arm is back near its home.
It works for any number of arms and any robot: it only needs each arm's home point.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from vafn_gym.constants import (
    ACTION_PER_ARM,
    CONTROL_DT,
    DIST_INDEX,
    GOAL_SLICE,
    OBS_PER_ARM,
    OBS_PER_ARM_WITH_GOAL,
    PHASE_EXECUTING,
    PHASE_INDEX,
    POS_SLICE,
    V_MAX,
)
from vafn_gym.layout import ArmLayout

#: Probe moves (unit directions) made by a newly active arm before the first trilateration.
PROBE_DIRECTIONS = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
#: Another arm counts as "clear" when its end effector is within this distance of its home point.
CLEAR_DISTANCE = 0.08
#: Proportional gain, in units of one full-speed step.
GAIN = 1.0


def trilaterate(points: Sequence[np.ndarray], distances: Sequence[float]) -> np.ndarray | None:
    """The point at ``distances`` from ``points`` (linear least squares), or None while the points span no volume.

    Subtracting the first equation ``|p_0 - t|^2 = d_0^2`` from the others leaves a linear system in ``t``; it
    determines ``t`` once four of the points are not coplanar.
    """
    if len(points) < 4:
        return None
    points = np.asarray(points, dtype=np.float64)
    dists = np.asarray(distances, dtype=np.float64)
    a = 2.0 * (points[1:] - points[0])
    b = (points[1:] ** 2).sum(1) - (points[0] ** 2).sum() - dists[1:] ** 2 + dists[0] ** 2
    if np.linalg.matrix_rank(a, tol=1e-4) < 3:
        return None
    return np.linalg.lstsq(a, b, rcond=None)[0]

class ScriptedController:
    """A deterministic policy with ``predict(obs) -> (action, None)`` like an SB3 model.

    :param homes: rest end-effector point per arm id (1..N), in the observation's frame; :meth:`for_env` reads them
        from an env.
    :param observe_goal: observations carry each arm's current target (8 numbers per arm instead of 5).
    :param history: readings per arm block (the env's ``history``; only the newest is used).
    """

    def __init__(self, homes: Mapping[int, np.ndarray], observe_goal: bool = False, history: int = 1) -> None:
        self.homes = {int(arm): np.asarray(point, dtype=np.float64) for arm, point in homes.items()}
        self.arm_ids = tuple(sorted(self.homes))
        if self.arm_ids != tuple(range(1, len(self.arm_ids) + 1)):
            raise ValueError(f"homes must be keyed by arm ids 1..N, got {list(self.homes)}")
        self.observe_goal = observe_goal
        self.obs_per_arm = (OBS_PER_ARM_WITH_GOAL if observe_goal else OBS_PER_ARM) * history
        self.reset()

    @classmethod
    def for_env(cls, env: gym.Env) -> ScriptedController:
        """A controller for ``env`` (any wrapper around a :class:`MultiArmEnv`, in either observation frame)."""
        base = env.unwrapped
        # Homes in the frame the observation and action use: the geometry below is the same in every frame.
        homes = {arm_id: base.observed_point(arm_id, arm.home) for arm_id, arm in base.arms.items()}
        return cls(homes, observe_goal=base.observe_goal, history=base.history)

    def reset(self) -> None:
        """Forget the target estimate (call at every episode start)."""
        self._active: int | None = None
        self._samples: list[tuple[np.ndarray, float]] = []
        self._previous_distance: float | None = None

    def _velocity_toward(self, position: np.ndarray, goal: np.ndarray) -> np.ndarray:
        step = V_MAX * CONTROL_DT
        return np.clip(GAIN * (goal - position) / step, -1.0, 1.0)

    def act(self, observation: np.ndarray) -> np.ndarray:
        """The joint action for one observation."""
        obs = np.asarray(observation, dtype=np.float64)
        blocks = {arm: obs[ArmLayout.block_slice(arm, self.obs_per_arm)] for arm in self.arm_ids}
        positions = {arm: block[POS_SLICE] for arm, block in blocks.items()}
        distances = {arm: block[DIST_INDEX] for arm, block in blocks.items()}
        active = next((arm for arm, block in blocks.items() if round(block[PHASE_INDEX]) == PHASE_EXECUTING), None)
        # A new waypoint starts when the active arm changes or its distance jumps (the same arm reaches again).
        jumped = self._previous_distance is not None and active is not None and (
            distances[active] > self._previous_distance + V_MAX * CONTROL_DT * 2
        )
        if active != self._active or jumped:
            self._active, self._samples = active, []
        action = np.zeros(ACTION_PER_ARM * len(self.arm_ids))
        for arm in self.arm_ids:
            if arm != active:
                action[ArmLayout.block_slice(arm, ACTION_PER_ARM)] = self._velocity_toward(
                    positions[arm], self.homes[arm]
                )
        if active is not None:
            command = self._active_command(active, blocks[active], positions, distances)
            action[ArmLayout.block_slice(active, ACTION_PER_ARM)] = command
        return action.astype(np.float32)

    def _active_command(
        self, active: int, block: np.ndarray, positions: dict[int, np.ndarray], distances: dict[int, float]
    ) -> np.ndarray:
        self._previous_distance = float(distances[active])
        others_clear = all(
            np.linalg.norm(positions[arm] - self.homes[arm]) < CLEAR_DISTANCE for arm in self.arm_ids if arm != active
        )
        if not others_clear:  # wait at home; probing now would gather no information while the env holds the arm
            self._samples = []
            return self._velocity_toward(positions[active], self.homes[active])
        self._samples.append((positions[active].copy(), float(distances[active])))
        if self.observe_goal:
            target = block[GOAL_SLICE]
        else:
            probe = len(self._samples) - 1
            if probe < len(PROBE_DIRECTIONS):
                return PROBE_DIRECTIONS[probe]
            target = trilaterate([p for p, _ in self._samples], [d for _, d in self._samples])
        if target is None:
            return self._velocity_toward(positions[active], self.homes[active])
        return self._velocity_toward(positions[active], target)

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: Any = None, deterministic: bool = True
    ) -> tuple[np.ndarray, None]:
        """SB3-style ``predict``: returns ``(action, None)``; batched observations give batched actions."""
        obs = np.asarray(observation)
        if obs.ndim == 2:
            return np.stack([self.act(o) for o in obs]), None
        return self.act(obs), None


class RandomPolicy:
    """Uniformly random actions with SB3's ``predict`` signature (a lower reference).

    :param action_space: the env's action space.
    :param seed: seed of the action stream.
    """

    def __init__(self, action_space: gym.spaces.Box, seed: int) -> None:
        self.action_space = action_space
        self.action_space.seed(seed)

    def predict(self, observation: np.ndarray, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, None]:
        """A random action (``observation`` is ignored)."""
        return self.action_space.sample(), None
