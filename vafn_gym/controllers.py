"""ScriptedController: solves any instruction from the 15-D observation alone (the ceiling for every learning curve).

It never reads simulator state or the instruction. The target of the active arm is not in the observation, only its
distance, so the controller *trilaterates* it: it moves the arm along three probe directions, then solves the linear
least-squares system given by ``|p_k - t|^2 = d_k^2`` and keeps refining the estimate as new (p, d) pairs arrive.
Only one arm enters the shared region at a time: the active arm waits until every other arm is back near its home.
"""

from __future__ import annotations

import numpy as np

from vafn_gym.constants import (
    ARM_IDS,
    CONTROL_DT,
    DIST_INDEX,
    NUM_ARMS,
    OBS_PER_ARM,
    PHASE_EXECUTING,
    PHASE_INDEX,
    POS_SLICE,
    V_MAX,
    action_slice,
    home_position,
    obs_slice,
)

#: Probe moves (unit directions) made by a newly active arm before the first trilateration.
PROBE_DIRECTIONS = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
#: Another arm counts as "clear" when its end effector is within this distance of its home point.
CLEAR_DISTANCE = 0.08
#: Proportional gain, in units of one full-speed step.
GAIN = 1.0


class ScriptedController:
    """A deterministic policy with ``predict(obs) -> (action, None)`` like an SB3 model.

    :param homes: rest end-effector point per arm (defaults to the nominal home points of the constants module).
    """

    def __init__(self, homes: dict[int, np.ndarray] | None = None) -> None:
        self.homes = homes or {arm: home_position(arm) for arm in ARM_IDS}
        self.reset()

    def reset(self) -> None:
        """Forget the target estimate (call at every episode start)."""
        self._active: int | None = None
        self._samples: list[tuple[np.ndarray, float]] = []
        self._previous_distance: float | None = None

    def _velocity_toward(self, position: np.ndarray, goal: np.ndarray) -> np.ndarray:
        step = V_MAX * CONTROL_DT
        return np.clip(GAIN * (goal - position) / step, -1.0, 1.0)

    def _estimate_target(self) -> np.ndarray | None:
        if len(self._samples) < 4:
            return None
        points = np.array([p for p, _ in self._samples])
        dists = np.array([d for _, d in self._samples])
        a = 2.0 * (points[1:] - points[0])
        b = (points[1:] ** 2).sum(1) - (points[0] ** 2).sum() - dists[1:] ** 2 + dists[0] ** 2
        if np.linalg.matrix_rank(a, tol=1e-4) < 3:
            return None
        return np.linalg.lstsq(a, b, rcond=None)[0]

    def act(self, observation: np.ndarray) -> np.ndarray:
        """The 9-D action for one observation."""
        obs = np.asarray(observation, dtype=np.float64)[: NUM_ARMS * OBS_PER_ARM]
        positions = {arm: obs[obs_slice(arm)][POS_SLICE] for arm in ARM_IDS}
        distances = {arm: obs[obs_slice(arm)][DIST_INDEX] for arm in ARM_IDS}
        active = next((arm for arm in ARM_IDS if round(obs[obs_slice(arm)][PHASE_INDEX]) == PHASE_EXECUTING), None)
        # A new waypoint starts when the active arm changes or its distance jumps (the same arm reaches again).
        jumped = self._previous_distance is not None and active is not None and (
            distances[active] > self._previous_distance + V_MAX * CONTROL_DT * 2
        )
        if active != self._active or jumped:
            self._active, self._samples = active, []
        action = np.zeros(3 * NUM_ARMS)
        for arm in ARM_IDS:
            if arm != active:
                action[action_slice(arm)] = self._velocity_toward(positions[arm], self.homes[arm])
        if active is not None:
            self._samples.append((positions[active].copy(), float(distances[active])))
            self._previous_distance = float(distances[active])
            others_clear = all(
                np.linalg.norm(positions[arm] - self.homes[arm]) < CLEAR_DISTANCE for arm in ARM_IDS if arm != active
            )
            probe = len(self._samples) - 1
            target = self._estimate_target()
            if probe < len(PROBE_DIRECTIONS):
                command = PROBE_DIRECTIONS[probe]
            elif target is None or not others_clear:
                command = self._velocity_toward(positions[active], self.homes[active])
            else:
                command = self._velocity_toward(positions[active], target)
            action[action_slice(active)] = command
        return action.astype(np.float32)

    def run_episode(self, env, seed: int | None = None) -> dict:
        """Run one whole episode of ``env`` (reset with ``seed``) and return the last step's ``info``."""
        obs, info = env.reset(seed=seed)
        self.reset()
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(self.act(obs))
            done = terminated or truncated
        return info

    def predict(self, observation: np.ndarray, state=None, episode_start=None, deterministic: bool = True):
        """SB3-style ``predict``: returns ``(action, None)``; batched observations give batched actions."""
        obs = np.asarray(observation)
        if obs.ndim == 2:
            return np.stack([self.act(o) for o in obs]), None
        return self.act(obs), None
