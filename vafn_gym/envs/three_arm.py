"""ThreeArmEnv: the simulator, three arms and the instruction-following task composed into one Gymnasium env.

The observation layout, the reward and the phase logic live here and nowhere else.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from vafn_gym.arm import Arm
from vafn_gym.constants import (
    ACTION_DIM,
    ARM_IDS,
    BASE_RADIUS,
    CONTROL_DT,
    DIST_INDEX,
    MAX_DISTANCE,
    N_SUBSTEPS,
    NUM_ARMS,
    OBS_DIM,
    PHASE_COMPLETED,
    PHASE_EXECUTING,
    PHASE_INDEX,
    PHASE_WAITING,
    POS_SLICE,
    SUCCESS_TOLERANCE,
    V_MAX,
    WORKSPACE_HIGH,
    WORKSPACE_LOW,
    action_slice,
    obs_slice,
)
from vafn_gym.instructions import Instruction
from vafn_gym.sim import BulletSim
from vafn_gym.tasks import DEFAULT_TASK_FAMILY, TASK_FAMILIES, TaskSampler

#: Dense-reward weights (documented in the README, "Reward").
PROGRESS_WEIGHT = 10.0
WAYPOINT_BONUS = 1.0
HOLD_WEIGHT = 0.5
COLLISION_PENALTY = 5.0
PROXIMITY_PENALTY = 1.0
#: Episode budget when no max_episode_steps is given: BASE + PER_WAYPOINT * len(instruction) steps.
BASE_EPISODE_STEPS = 50
STEPS_PER_WAYPOINT = 80
MARKER_RADIUS = 0.02
TABLE_COLOUR = (0.55, 0.4, 0.25, 1.0)
ARM_COLOURS = ((0.9, 0.2, 0.2, 0.8), (0.2, 0.7, 0.2, 0.8), (0.2, 0.3, 0.9, 0.8))
ARM_PAIRS = tuple((a, b) for a in ARM_IDS for b in ARM_IDS if a < b)


class ThreeArmEnv(gym.Env):
    """Three KUKA arms around one table follow an :class:`Instruction` (an ordered list of arm/target waypoints).

    :param task_family: "order" (targets are each arm's default point; the 15-D observation makes every order
        solvable without adaptation), "hidden_targets" (targets sampled per task and absent from the observation:
        they must be inferred from reward) or "goal_visible" (as hidden_targets, plus the active target appended to the
        observation, 18-D).
    :param instruction: a fixed instruction for every episode (anything :meth:`Instruction.coerce` accepts);
        ``None`` samples one per episode from the task sampler.
    :param split: which split of the task distribution to sample from ("train", "validation", "test").
    :param min_length: shortest sampled instruction.
    :param max_length: longest sampled instruction.
    :param split_seed: seed of the train/validation/test assignment of orders.
    :param reward_type: "dense" (shaped, default) or "sparse" (+1 per reached waypoint, -1 per collision step).
    :param terminate_on_collision: end the episode at the first arm-arm contact.
    :param safety_margin: if > 0, also penalise arm pairs closer than this (metres, from ``getClosestPoints``).
    :param max_episode_steps: truncation horizon; ``None`` gives ``50 + 80 * len(instruction)``.
    :param render_mode: "rgb_array" (headless TinyRenderer) or "human" (GUI window; needs a display).
    :param render_width: frame width in pixels.
    :param render_height: frame height in pixels.
    :param n_substeps: physics steps (of ``PHYSICS_DT``) per control step; the default gives ``CONTROL_DT``.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": int(round(1.0 / CONTROL_DT))}

    def __init__(
        self,
        task_family: str = DEFAULT_TASK_FAMILY,
        instruction: Any = None,
        split: str = "train",
        min_length: int = 1,
        max_length: int = 10,
        split_seed: int = 0,
        reward_type: str = "dense",
        terminate_on_collision: bool = False,
        safety_margin: float = 0.0,
        max_episode_steps: int | None = None,
        render_mode: str | None = None,
        render_width: int = 480,
        render_height: int = 360,
        n_substeps: int = N_SUBSTEPS,
    ) -> None:
        if task_family not in TASK_FAMILIES:
            raise ValueError(f"task_family must be one of {TASK_FAMILIES}, got {task_family!r}")
        if reward_type not in ("dense", "sparse"):
            raise ValueError(f"reward_type must be 'dense' or 'sparse', got {reward_type!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        if safety_margin < 0:
            raise ValueError(f"safety_margin must be >= 0, got {safety_margin}")
        self.task_family = task_family
        self.reward_type = reward_type
        self.terminate_on_collision = terminate_on_collision
        self.safety_margin = float(safety_margin)
        self.fixed_max_episode_steps = max_episode_steps
        self.render_mode = render_mode
        self.render_size = (int(render_width), int(render_height))
        self.sampler = TaskSampler(split, task_family, min_length, max_length, split_seed=split_seed)
        self._task: Instruction | None = None if instruction is None else Instruction.coerce(instruction)

        if n_substeps < 1:
            raise ValueError(f"n_substeps must be >= 1, got {n_substeps}")
        self.sim = BulletSim(gui=render_mode == "human", n_substeps=n_substeps)
        with self.sim.no_rendering():
            self.sim.load_urdf("plane.urdf", np.zeros(3))
            self.sim.create_table_top(BASE_RADIUS, TABLE_COLOUR)
            self.arms = {arm_id: Arm(self.sim, arm_id) for arm_id in ARM_IDS}
            self.markers = {
                arm_id: self.sim.create_marker(self.arms[arm_id].home, MARKER_RADIUS, ARM_COLOURS[arm_id - 1])
                for arm_id in ARM_IDS
            }

        self.action_space = spaces.Box(-1.0, 1.0, shape=(ACTION_DIM,), dtype=np.float32)
        self.observation_space = self._make_observation_space()
        self.instruction = Instruction()
        self.waypoint_index = 0
        self.steps = 0
        self.collided = False

    # --- spaces and observation ---
    def _make_observation_space(self) -> spaces.Box:
        per_arm_low = np.concatenate([WORKSPACE_LOW, [0.0, PHASE_WAITING]])
        per_arm_high = np.concatenate([WORKSPACE_HIGH, [MAX_DISTANCE, PHASE_COMPLETED]])
        low, high = np.tile(per_arm_low, NUM_ARMS), np.tile(per_arm_high, NUM_ARMS)
        if self.task_family == "goal_visible":
            low, high = np.concatenate([low, WORKSPACE_LOW]), np.concatenate([high, WORKSPACE_HIGH])
        return spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)

    @property
    def active_arm(self) -> int | None:
        """The arm whose waypoint is being executed (1-based), or None when the instruction is complete."""
        if self.waypoint_index < len(self.instruction):
            return self.instruction[self.waypoint_index].arm
        return None

    def current_target(self, arm_id: int) -> np.ndarray:
        """Arm ``arm_id``'s current target: its next pending waypoint's target, or its home point when it has none."""
        for index in range(self.waypoint_index, len(self.instruction)):
            if self.instruction[index].arm == arm_id:
                return self.instruction[index].target_array
        return self.arms[arm_id].home

    def phase(self, arm_id: int) -> int:
        """Phase flag of an arm: 1 executing, 0 waiting for a later waypoint, 2 completed (no waypoint left)."""
        if arm_id == self.active_arm:
            return PHASE_EXECUTING
        if arm_id in self.instruction.remaining_arms(self.waypoint_index):
            return PHASE_WAITING
        return PHASE_COMPLETED

    def _positions(self) -> dict[int, np.ndarray]:
        return {arm_id: arm.ee_position for arm_id, arm in self.arms.items()}

    def _distances(self, positions: dict[int, np.ndarray]) -> np.ndarray:
        """Distance of each arm (in ``ARM_IDS`` order) to its current target."""
        return np.array([np.linalg.norm(positions[arm_id] - self.current_target(arm_id)) for arm_id in ARM_IDS])

    def _observation(self, positions: dict[int, np.ndarray], distances: np.ndarray) -> np.ndarray:
        obs = np.zeros(self.observation_space.shape, dtype=np.float64)
        for arm_id, distance in zip(ARM_IDS, distances):
            block = obs[obs_slice(arm_id)]
            block[POS_SLICE] = positions[arm_id]
            block[DIST_INDEX] = distance
            block[PHASE_INDEX] = self.phase(arm_id)
        if self.task_family == "goal_visible" and self.active_arm is not None:
            obs[OBS_DIM:] = self.current_target(self.active_arm)
        return np.clip(obs, self.observation_space.low, self.observation_space.high).astype(np.float32)

    def observe(self) -> np.ndarray:
        """The current observation, without stepping (e.g. after a controller starts an instruction)."""
        positions = self._positions()
        return self._observation(positions, self._distances(positions))

    # --- Meta-World-style task API ---
    def set_task(self, task: Any) -> None:
        """Use ``task`` (anything :meth:`Instruction.coerce` accepts; ``None`` = sample) from the next reset on."""
        self._task = None if task is None else Instruction.coerce(task)

    def get_task(self) -> Instruction:
        """The instruction of the current episode."""
        return self.instruction

    # --- episode ---
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Home every arm and start an instruction (``options={"instruction": ...}`` overrides the task for one episode)."""
        super().reset(seed=seed)
        if seed is not None:
            self.sampler.seed(int(self.np_random.integers(2**63)))
        options = options or {}
        if "instruction" in options:
            instruction = Instruction.coerce(options["instruction"])
        elif self._task is not None:
            instruction = self._task
        else:
            instruction = self.sampler.sample()
        for arm in self.arms.values():
            arm.reset()
        self._start_instruction(instruction)
        positions = self._positions()
        distances = self._distances(positions)
        return self._observation(positions, distances), self._info(distances, collision=False)

    def _start_instruction(self, instruction: Instruction) -> None:
        self.instruction = instruction
        self.waypoint_index = 0
        self.steps = 0
        self.collided = False
        self._update_markers()

    def max_episode_steps(self) -> int:
        """Truncation horizon of the current episode."""
        if self.fixed_max_episode_steps is not None:
            return self.fixed_max_episode_steps
        return self.default_instruction_budget()

    def default_instruction_budget(self) -> int:
        """Steps the current instruction gets by default: ``50 + 80 * len(instruction)``."""
        return BASE_EPISODE_STEPS + STEPS_PER_WAYPOINT * len(self.instruction)

    def _update_markers(self) -> None:
        for arm_id, marker in self.markers.items():
            self.sim.move_marker(marker, self.current_target(arm_id))

    def _validate_action(self, action: Any) -> np.ndarray:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (ACTION_DIM,):
            raise ValueError(f"action must have shape ({ACTION_DIM},), got {action.shape}")
        if not np.all(np.isfinite(action)):
            bad = np.flatnonzero(~np.isfinite(action)).tolist()
            raise ValueError(f"action has non-finite entries at indices {bad}; nothing was sent to the simulator")
        return np.clip(action, -1.0, 1.0)

    def _apply_action(self, action: np.ndarray, positions: dict[int, np.ndarray]) -> None:
        for arm_id, arm in self.arms.items():
            arm.command_velocity(action[action_slice(arm_id)] * V_MAX, self.sim.dt, positions[arm_id])
        self.sim.step()

    def _arm_contact(self) -> bool:
        return any(self.sim.contact_count(self.arms[a].body, self.arms[b].body) > 0 for a, b in ARM_PAIRS)

    def _too_close(self) -> bool:
        return self.safety_margin > 0 and any(
            self.sim.closest_points_count(self.arms[a].body, self.arms[b].body, self.safety_margin) > 0
            for a, b in ARM_PAIRS
        )

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Apply a 9-D end-effector velocity command (3 per arm, in [-1, 1] × ``V_MAX``) for one control step."""
        positions, reward, collision = self._advance(action)
        terminated = self.active_arm is None or (collision and self.terminate_on_collision)
        truncated = not terminated and self.steps >= self.max_episode_steps()
        distances = self._distances(positions)
        return self._observation(positions, distances), reward, terminated, truncated, self._info(distances, collision)

    def _advance(self, action: Any) -> tuple[dict[int, np.ndarray], float, bool]:
        """Validate and apply an action, then advance the waypoint; returns (positions, reward, collision)."""
        action = self._validate_action(action)
        active = self.active_arm
        target = self.current_target(active) if active is not None else None
        positions_before = self._positions()
        distance_before = distance_after = 0.0
        if active is not None:
            distance_before = float(np.linalg.norm(positions_before[active] - target))

        self._apply_action(action, positions_before)
        self.steps += 1
        positions = self._positions()
        collision = self._arm_contact()
        self.collided |= collision

        reached = 0
        if active is not None:
            distance_after = float(np.linalg.norm(positions[active] - target))
            if distance_after < SUCCESS_TOLERANCE:
                reached = 1
                self.waypoint_index += 1
                self._update_markers()
        return positions, self._reward(positions, active, distance_before, distance_after, reached, collision), collision

    def _reward(
        self, positions: dict[int, np.ndarray], active: int | None, before: float, after: float, reached: int,
        collision: bool,
    ) -> float:
        if self.reward_type == "sparse":
            return float(reached) - float(collision)
        holding = [np.linalg.norm(positions[i] - self.arms[i].home) for i in ARM_IDS if i != active]
        reward = PROGRESS_WEIGHT * (before - after) + WAYPOINT_BONUS * reached - HOLD_WEIGHT * float(np.mean(holding))
        reward -= COLLISION_PENALTY * float(collision) + PROXIMITY_PENALTY * float(self._too_close())
        return float(reward)

    def _info(self, distances: np.ndarray, collision: bool) -> dict[str, Any]:
        complete = self.active_arm is None
        return {
            "is_success": bool(complete and not self.collided),
            "collision": bool(collision),
            "collided": bool(self.collided),
            "active_arm": self.active_arm,
            "waypoint_index": self.waypoint_index,
            "instruction": self.instruction,
            "distances": distances,
        }

    # --- rendering ---
    def render(self) -> np.ndarray | None:
        """An RGB frame in "rgb_array" mode (the GUI draws itself in "human" mode)."""
        if self.render_mode != "rgb_array":
            return None
        width, height = self.render_size
        return self.sim.render(width, height, target=np.array([0.0, 0.0, 0.3]), distance=1.7, yaw=30.0, pitch=-30.0)

    def close(self) -> None:
        """Release the physics client; safe to call twice."""
        self.sim.close()
