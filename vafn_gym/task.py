"""The instruction-following task: target resolution, phases, waypoint advance, reward, success and ``info``.

The env wires the simulator, the arms and this task together (as panda-gym's ``RobotTaskEnv`` does); everything an
episode *means* lives here, in one place.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from collections.abc import Mapping
from typing import Any

import numpy as np

from vafn_gym.constants import PHASE_COMPLETED, PHASE_EXECUTING, PHASE_WAITING, SUCCESS_TOLERANCE
from vafn_gym.instructions import Instruction, Waypoint
from vafn_gym.layout import ArmLayout

#: Where the targets of waypoints that name an arm only come from.
TARGET_MODES = ("default", "per_arm", "per_waypoint")
#: Who moves the arms that are not executing a waypoint: the env's low-level controller, or the policy.
INACTIVE_ARM_MODES = ("hold", "policy")
#: What a waiting arm's observed distance (and goal) refers to: its next target, or its home point.
WAITING_GOALS = ("target", "home")
REWARD_TYPES = ("dense", "sparse")


def resolve_targets(
    instruction: Instruction, targets: str, layout: ArmLayout, rng: np.random.Generator
) -> Instruction:
    """``instruction`` with an explicit target on every waypoint; explicit targets are kept.

    :param targets: "default" (the layout's point of each arm), "per_arm" (one point drawn from the shared region per
        arm, reused on every visit) or "per_waypoint" (one drawn per waypoint). Draws are made in waypoint order.
    """
    drawn: dict[int, np.ndarray] = {}
    waypoints = []
    for waypoint in instruction:
        if waypoint.target is not None:
            target = np.asarray(waypoint.target)
        elif targets == "default":
            target = layout.default_target(waypoint.arm)
        else:
            if targets == "per_waypoint" or waypoint.arm not in drawn:
                drawn[waypoint.arm] = layout.sample_shared_target(rng)
            target = drawn[waypoint.arm]
        waypoints.append(Waypoint(waypoint.arm, tuple(float(x) for x in target)))
    return Instruction(waypoints)


@dataclass(frozen=True)
class RewardConfig:
    """Weights of the dense reward (every field is an env kwarg through ``reward_kwargs=dict(...)``).

    Per step: ``progress_weight`` × decrease of the active arm's distance to its target, ``precision_weight`` × decrease
    of its log-distance ``log(d + precision_scale)`` (steep near the target, so the last centimetres count as much as
    the first decimetres), ``+ waypoint_bonus`` per reached waypoint, ``home_progress_weight`` × decrease of every
    inactive arm's distance to home (only where the policy moves inactive arms), ``- hold_weight`` × mean distance of
    inactive arms from home (a level penalty: off by default, because the learner cannot assign it to the right arm),
    ``- collision_penalty`` once, on the episode's first arm-arm contact, and ``- proximity_penalty`` per step with
    arms closer than the env's ``safety_margin``.
    The sparse reward is ``+1`` per reached waypoint and ``-1`` on the first contact.
    """

    progress_weight: float = 10.0
    precision_weight: float = 1.0
    precision_scale: float = 0.01
    waypoint_bonus: float = 1.0
    home_progress_weight: float = 10.0
    hold_weight: float = 0.0
    collision_penalty: float = 5.0
    proximity_penalty: float = 1.0

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
                raise ValueError(f"reward weight {item.name} must be a finite number, got {value!r}")
        if self.precision_scale <= 0:
            raise ValueError(f"reward weight precision_scale must be > 0, got {self.precision_scale!r}")

    @classmethod
    def from_kwargs(cls, kwargs: Mapping[str, Any] | None) -> RewardConfig:
        """A config from a dict of overrides; ``ValueError`` naming any unknown key."""
        kwargs = dict(kwargs or {})
        known = {item.name for item in fields(cls)}
        unknown = sorted(set(kwargs) - known)
        if unknown:
            raise ValueError(f"unknown reward_kwargs {unknown}; known: {sorted(known)}")
        return cls(**kwargs)

    def as_dict(self) -> dict[str, float]:
        """The weights as a plain dict."""
        return asdict(self)


class InstructionTask:
    """One instruction being executed by the arms of ``layout``.

    :param layout: the arm layout (arm ids, default targets, shared region).
    :param targets: "default" (each arm's fixed default target), "per_arm" (one hidden target per arm per instruction,
        reused for every visit of that arm) or "per_waypoint" (a new hidden target for every waypoint).
    :param inactive_arms: "hold" (the env moves non-active arms) or "policy" (the policy does; adds the home-progress
        reward term).
    :param reward_type: "dense" or "sparse".
    :param reward: the dense-reward weights.
    :param homes: rest point per arm (default: the layout's nominal home points; the env passes the measured ones).
    :param success_tolerance: distance (m) at which the active arm has reached its waypoint.
    :param waiting_goal: "target": a waiting arm's observed distance is to its next waypoint's target; "home": to its
        home point, where the env (or the home-progress reward) sends it until its turn.
    """

    def __init__(
        self, layout: ArmLayout, targets: str = "default", inactive_arms: str = "hold", reward_type: str = "dense",
        reward: RewardConfig | None = None, homes: Mapping[int, np.ndarray] | None = None,
        success_tolerance: float = SUCCESS_TOLERANCE, waiting_goal: str = "target",
    ) -> None:
        self.layout = layout
        self.targets = targets
        self.inactive_arms = inactive_arms
        self.reward_type = reward_type
        self.reward_config = reward or RewardConfig()
        self.homes = dict(homes) if homes is not None else {arm: layout.home_point(arm) for arm in layout.arm_ids}
        self.success_tolerance = success_tolerance
        self.waiting_goal = waiting_goal
        self.instruction = Instruction()
        self.waypoint_index = 0
        self.steps = 0
        self.collided = False
        #: The last step's reward split by term (its values sum to the reward); reported in ``info["reward_terms"]``.
        self.reward_terms: dict[str, float] = {}

    # --- targets ---
    def resolve(self, instruction: Instruction, rng: np.random.Generator) -> Instruction:
        """``instruction`` with every target explicit (waypoints that name an arm only get one by ``targets``)."""
        instruction.check_arms(self.layout.n_arms)
        return resolve_targets(instruction, self.targets, self.layout, rng)

    # --- state ---
    def start(self, instruction: Instruction) -> None:
        """Begin ``instruction`` (targets already resolved)."""
        self.instruction = instruction
        self.waypoint_index = 0
        self.steps = 0
        self.collided = False
        self.reward_terms = {}

    @property
    def active_arm(self) -> int | None:
        """The arm executing the current waypoint, or None when the instruction is complete."""
        if self.waypoint_index < len(self.instruction):
            return self.instruction[self.waypoint_index].arm
        return None

    @property
    def complete(self) -> bool:
        """Whether every waypoint has been reached."""
        return self.active_arm is None

    def current_target(self, arm: int) -> np.ndarray:
        """``arm``'s next pending waypoint target, or its home point when it has none left."""
        for index in range(self.waypoint_index, len(self.instruction)):
            if self.instruction[index].arm == arm:
                return self.instruction[index].target_array
        return self.homes[arm]

    def goal(self, arm: int) -> np.ndarray:
        """The point ``arm``'s observed distance (and goal) refers to: :meth:`current_target`, or home while waiting."""
        if self.waiting_goal == "home" and arm != self.active_arm:
            return self.homes[arm]
        return self.current_target(arm)

    def phase(self, arm: int) -> int:
        """Phase flag: 1 executing, 0 waiting for a later waypoint, 2 completed (no waypoint left)."""
        if arm == self.active_arm:
            return PHASE_EXECUTING
        if arm in self.instruction.remaining_arms(self.waypoint_index):
            return PHASE_WAITING
        return PHASE_COMPLETED

    def distances(self, positions: Mapping[int, np.ndarray]) -> np.ndarray:
        """Distance of every arm (in id order) to its :meth:`goal`."""
        return np.array([np.linalg.norm(positions[arm] - self.goal(arm)) for arm in self.layout.arm_ids])

    # --- one step ---
    def step(
        self, before: Mapping[int, np.ndarray], after: Mapping[int, np.ndarray], contact: bool, too_close: bool
    ) -> float:
        """Account one control step (positions before and after it); advances the waypoint; returns the reward."""
        self.steps += 1
        active = self.active_arm
        first_contact = contact and not self.collided
        self.collided |= contact
        reached, progress, log_progress = 0, 0.0, 0.0
        weights = self.reward_config
        if active is not None:
            target = self.current_target(active)
            distance_before = float(np.linalg.norm(before[active] - target))
            distance_after = float(np.linalg.norm(after[active] - target))
            progress = distance_before - distance_after
            log_progress = np.log(distance_before + weights.precision_scale) - np.log(
                distance_after + weights.precision_scale
            )
            if distance_after < self.success_tolerance:
                reached = 1
                self.waypoint_index += 1
        if self.reward_type == "sparse":
            self.reward_terms = {"waypoint": float(reached), "collision": -float(first_contact)}
            return float(reached) - float(first_contact)
        inactive = [arm for arm in self.layout.arm_ids if arm != active]
        terms = {
            "progress": weights.progress_weight * progress,
            "precision": weights.precision_weight * float(log_progress),
            "waypoint": weights.waypoint_bonus * reached,
        }
        if self.inactive_arms == "policy" and weights.home_progress_weight and inactive:
            home_progress = [
                np.linalg.norm(before[arm] - self.homes[arm]) - np.linalg.norm(after[arm] - self.homes[arm])
                for arm in inactive
            ]
            terms["home_progress"] = weights.home_progress_weight * float(np.sum(home_progress))
        if weights.hold_weight and inactive:
            terms["hold"] = -weights.hold_weight * float(
                np.mean([np.linalg.norm(after[a] - self.homes[a]) for a in inactive])
            )
        terms["collision"] = -weights.collision_penalty * float(first_contact)
        terms["proximity"] = -weights.proximity_penalty * float(too_close)
        self.reward_terms = terms
        return float(sum(terms.values()))

    def info(self, distances: np.ndarray, contact: bool) -> dict[str, Any]:
        """The task part of the env's ``info``."""
        return {
            "is_success": bool(self.complete and not self.collided),
            "collision": bool(contact),
            "collided": bool(self.collided),
            "active_arm": self.active_arm,
            "waypoint_index": self.waypoint_index,
            "instruction": self.instruction,
            "distances": distances,
            "reward_terms": dict(self.reward_terms),
        }
