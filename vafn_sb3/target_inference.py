"""Target inference: run a policy trained with observed targets where the targets are hidden.

A policy trained on ``observe_goal=True`` (e.g. ``VAFN/ThreeArmReachGoal-v1``) reads each arm's target; on the
hidden-target env (``VAFN/ThreeArmReachHidden-v1``) only the distance to it is observed. :class:`TargetInferencePolicy`
fills the gap inside the episode, with no gradient step: when an arm starts a waypoint it makes three one-step probe
moves (the scripted controller's), trilaterates the target from its own (position, distance) readings, and from then
on gives the learned policy the observation it was trained on, with the estimate as the goal (refined at every step).
Two ablations: ``inference="passive"`` drops the probe moves (the policy heads for the centre of the shared region
until its own readings span a volume), ``inference="none"`` never estimates (the goal stays the centre: the
goal-observing policy with nothing inferred, this method's K = 0).
"""

from __future__ import annotations

from collections.abc import Mapping
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
    PHASE_COMPLETED,
    PHASE_EXECUTING,
    PHASE_INDEX,
    PHASE_WAITING,
    POS_SLICE,
    V_MAX,
)
from vafn_gym.controllers import PROBE_DIRECTIONS, trilaterate
from vafn_gym.layout import ArmLayout

__all__ = ["INFERENCE_MODES", "TargetInferencePolicy"]

#: ``inference`` settings: probe moves then trilateration, trilateration of passive readings only, no inference.
INFERENCE_MODES = ("probe", "passive", "none")

#: Readings of one waypoint closer than this (metres) to the previous one are not recorded.
MIN_SEPARATION = 1e-3


class TargetInferencePolicy:
    """A goal-observing SB3 model acting on hidden-target observations through in-episode trilateration.

    :param model: anything with SB3's ``predict`` whose observation has 8 numbers per arm (position, distance, phase,
        goal), i.e. trained with ``observe_goal=True``.
    :param homes: each arm's rest point (arm ids 1..N), in the observation's frame: the goal of a completed arm.
    :param priors: each arm's goal before its target is estimated (e.g. the shared region's centre), same frame.
    :param inference: one of :data:`INFERENCE_MODES`.
    :param waiting_goal: the env's ``waiting_goal``: with "home" a waiting arm's goal is its home, as the model saw it.
    """

    def __init__(
        self,
        model: Any,
        homes: Mapping[int, np.ndarray],
        priors: Mapping[int, np.ndarray],
        inference: str = "probe",
        waiting_goal: str = "target",
    ) -> None:
        self.model = model
        self.arm_ids = tuple(sorted(int(arm) for arm in homes))
        if self.arm_ids != tuple(range(1, len(self.arm_ids) + 1)) or set(priors) != set(self.arm_ids):
            raise ValueError(f"homes and priors must both be keyed by arm ids 1..N, got {list(homes)}, {list(priors)}")
        expected = (len(self.arm_ids) * OBS_PER_ARM_WITH_GOAL,)
        shape = getattr(getattr(model, "observation_space", None), "shape", None)
        if shape != expected:
            raise ValueError(
                f"the model must observe targets ({expected[0]} numbers for {len(self.arm_ids)} arms, "
                f"observe_goal=True), its observation shape is {shape}"
            )
        self.homes = {arm: np.asarray(homes[arm], dtype=np.float64) for arm in self.arm_ids}
        self.priors = {arm: np.asarray(priors[arm], dtype=np.float64) for arm in self.arm_ids}
        if inference not in INFERENCE_MODES:
            raise ValueError(f"inference must be one of {INFERENCE_MODES}, got {inference!r}")
        self.inference = inference
        self.waiting_goal = waiting_goal
        self.reset()

    @classmethod
    def for_env(cls, model: Any, env: gym.Env, inference: str = "probe") -> TargetInferencePolicy:
        """A policy for ``env`` (a hidden-target :class:`MultiArmEnv`, any wrapper, ``history=1``)."""
        base = env.unwrapped
        if base.observe_goal or base.history != 1:
            raise ValueError(
                f"target inference needs hidden-target observations with history=1, the env has "
                f"observe_goal={base.observe_goal}, history={base.history}"
            )
        centre = np.array([0.0, 0.0, float(np.mean(base.layout.shared_z_range))])
        homes = {arm: base.observed_point(arm, arm_obj.home) for arm, arm_obj in base.arms.items()}
        priors = {arm: base.observed_point(arm, centre) for arm in base.arms}
        return cls(model, homes, priors, inference=inference, waiting_goal=base.waiting_goal)

    def reset(self) -> None:
        """Forget every reading and estimate (call at every episode start; ``run_episode`` does)."""
        self._active: int | None = None
        self._points: list[np.ndarray] = []
        self._distances: list[float] = []
        self._estimate: np.ndarray | None = None
        self._previous_distance: float | None = None

    @property
    def estimate(self) -> np.ndarray | None:
        """The active arm's current target estimate (observation frame), or None before the first trilateration."""
        return self._estimate

    def _record(self, active: int, position: np.ndarray, distance: float) -> None:
        # A new waypoint starts when the active arm changes or its distance jumps (the same arm reaching again).
        jumped = self._previous_distance is not None and distance > self._previous_distance + 2 * V_MAX * CONTROL_DT
        if active != self._active or jumped:
            self._active, self._points, self._distances, self._estimate = active, [], [], None
        self._previous_distance = distance
        # A held arm (the env holds it until the others are home) repeats its reading: only new points count.
        if self._points and np.linalg.norm(position - self._points[-1]) < MIN_SEPARATION:
            return
        self._points.append(position.copy())
        self._distances.append(distance)
        estimate = None if self.inference == "none" else trilaterate(self._points, self._distances)
        if estimate is not None:
            self._estimate = estimate

    def goal_observation(self, observation: np.ndarray) -> np.ndarray:
        """The observation the goal-observing model expects, with the current estimates as goals (no recording)."""
        obs = np.asarray(observation, dtype=np.float64)
        blocks = []
        for arm in self.arm_ids:
            block = obs[ArmLayout.block_slice(arm, OBS_PER_ARM)]
            phase = round(block[PHASE_INDEX])
            if phase == PHASE_COMPLETED or (phase == PHASE_WAITING and self.waiting_goal == "home"):
                goal = self.homes[arm]
            elif phase == PHASE_EXECUTING and self._estimate is not None:
                goal = self._estimate
            else:
                goal = self.priors[arm]
            full = np.zeros(OBS_PER_ARM_WITH_GOAL)
            full[POS_SLICE], full[PHASE_INDEX], full[GOAL_SLICE] = block[POS_SLICE], phase, goal
            full[DIST_INDEX] = np.linalg.norm(block[POS_SLICE] - goal)
            blocks.append(full)
        return np.concatenate(blocks).astype(np.float32)

    def act(self, observation: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """The joint action for one observation; records the active arm's reading first."""
        obs = np.asarray(observation, dtype=np.float64)
        blocks = {arm: obs[ArmLayout.block_slice(arm, OBS_PER_ARM)] for arm in self.arm_ids}
        active = next((arm for arm, b in blocks.items() if round(b[PHASE_INDEX]) == PHASE_EXECUTING), None)
        if active is not None:
            self._record(active, blocks[active][POS_SLICE], float(blocks[active][DIST_INDEX]))
        else:  # the instruction is complete: the next waypoint starts afresh
            self._active, self._previous_distance = None, None
        action, _ = self.model.predict(self.goal_observation(obs), deterministic=deterministic)
        action = np.array(action, dtype=np.float32).reshape(-1)
        probe_index = len(self._points) - 1
        probing = self.inference == "probe" and self._estimate is None and probe_index < len(PROBE_DIRECTIONS)
        if probing and active is not None:
            action[ArmLayout.block_slice(active, ACTION_PER_ARM)] = PROBE_DIRECTIONS[probe_index]
        return action

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: Any = None, deterministic: bool = True
    ) -> tuple[np.ndarray, None]:
        """SB3-style ``predict`` for one observation: ``(action, None)``."""
        obs = np.asarray(observation)
        if obs.ndim != 1:
            raise ValueError(f"TargetInferencePolicy keeps per-episode readings: pass one observation, got {obs.shape}")
        return self.act(obs, deterministic=deterministic), None
