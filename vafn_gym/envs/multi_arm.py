"""MultiArmEnv: a simulator, N arms of one robot model and an instruction task composed into one Gymnasium env.

The observation is N blocks of ``[ee position (3), distance to current target, phase flag]`` (plus the arm's current
target when ``observe_goal=True``); the action is N blocks of an end-effector velocity in ``[-1, 1]^3 × V_MAX``. With
three arms that is the paper's 15-D observation and 9-D action.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from vafn_gym.arm import Arm
from vafn_gym.checks import check_bool, check_choice, check_int, check_number
from vafn_gym.constants import (
    DIST_INDEX,
    GOAL_SLICE,
    MAX_DISTANCE,
    MAX_INSTRUCTION_LENGTH,
    N_SUBSTEPS,
    OBS_PER_ARM,
    OBS_PER_ARM_WITH_GOAL,
    PHASE_COMPLETED,
    PHASE_INDEX,
    PHASE_WAITING,
    PHYSICS_DT,
    POS_SLICE,
    SUCCESS_TOLERANCE,
    V_MAX,
    WORKSPACE_HIGH,
    WORKSPACE_LOW,
)
from vafn_gym.dynamics import Dynamics, DynamicsSampler
from vafn_gym.instructions import Instruction
from vafn_gym.layout import FRAMES, MAX_ARMS, ArmLayout
from vafn_gym.robots import RobotSpec, get_robot
from vafn_gym.sim import BulletSim
from vafn_gym.task import (
    INACTIVE_ARM_MODES, REWARD_TYPES, TARGET_MODES, WAITING_GOALS, InstructionTask, RewardConfig,
)
from vafn_gym.tasks import SPLITS, TaskSampler

#: Episode budget when no max_steps is given: BASE + PER_WAYPOINT * len(instruction) steps.
BASE_EPISODE_STEPS = 50
STEPS_PER_WAYPOINT = 80
#: In "hold" mode the active arm waits until every other arm is within this distance of its home point.
CLEARANCE_DISTANCE = 0.08
#: Control steps the arms run at home when the env is built, to measure the pose they hold under gravity.
SETTLE_STEPS = 20
MARKER_RADIUS = 0.02
TABLE_COLOUR = (0.55, 0.4, 0.25, 1.0)
MAX_RENDER_SIZE = 4096
#: Largest ``success_tolerance`` (metres): beyond it a "reach" no longer means much in this workspace.
MAX_SUCCESS_TOLERANCE = 0.2
#: Largest ``history`` (readings per arm block).
MAX_HISTORY = 64


class MultiArmEnv(gym.Env):
    """N robot arms around one table follow an :class:`Instruction` (an ordered list of arm/target waypoints).

    :param n_arms: number of arms (ignored when ``layout`` is given).
    :param robot: robot model: "kuka" (default), "panda", "xarm" or a :class:`RobotSpec`.
    :param layout: a full :class:`ArmLayout` (base circle, homes, default targets, shared region); by default
        ``n_arms`` arms on the robot's preferred base circle.
    :param targets: where the targets of arm-only waypoints come from: "default" (each arm's fixed point),
        "per_arm" (one hidden target per arm per instruction, reused on every visit) or "per_waypoint".
    :param observe_goal: append each arm's current target to its observation block (8 numbers per arm instead of 5).
    :param history: readings per arm block, newest first: ``history=4`` gives each arm its last four
        ``[position, distance, phase]`` readings (20 numbers instead of 5; the block starts with the current reading, so
        code that reads a block's first numbers is unaffected). A memoryless policy can then estimate where a hidden
        target lies from how its distance changed as it moved. Readings before the episode start repeat the first one.
    :param frame: "world" (default): positions, targets and velocities in the table's frame; "base": each arm's
        block gives its position (and target) in that arm's own base frame (origin at its base, x toward the table
        centre, z up) and its action block is a velocity in that frame. Every arm then sees the same reach problem, so
        one shared actor without arm ids learns all of them and runs on any number of arms (docs/learning.md, "More
        arms"). A shared actor's ``neighbours`` summary compares positions across blocks and needs "world".
    :param inactive_arms: "hold": the env returns every non-active arm home and holds it there, those arms' action
        entries are ignored (``info["ignored_arms"]``), and the active arm is held until the others are clear of the
        shared region (``info["gated"]``); "policy": every arm's action counts and inactive arms are rewarded for
        progress toward home.
    :param waiting_goal: what a waiting arm (phase 0) observes its distance (and goal) to: "target" (default), its
        next waypoint's target; "home", its home point, where the env or the home-progress reward sends it until its
        turn. The active arm always observes its target, a completed arm its home.
    :param instruction: a fixed instruction for every episode (anything :meth:`Instruction.coerce` accepts); ``None``
        samples one per episode from the task sampler.
    :param split: which split of the task distribution to sample from ("train", "validation", "test").
    :param min_length: shortest sampled instruction.
    :param max_length: longest sampled instruction.
    :param split_seed: seed of the train/validation/test assignment of orders.
    :param reward_type: "dense" (shaped, default) or "sparse" (+1 per reached waypoint, -1 on the first contact).
    :param reward_kwargs: overrides of :class:`RewardConfig` weights, e.g. ``dict(progress_weight=5.0)``.
    :param terminate_on_collision: end the episode at the first arm-arm contact.
    :param safety_margin: if > 0, also penalise arm pairs closer than this (metres, from ``getClosestPoints``).
    :param success_tolerance: distance (m) at which a waypoint counts as reached (default 0.05). Training with a smaller
        value than the one evaluated on moves the deterministic policy's resting point inside the evaluated tolerance:
        see docs/learning.md, "Training tolerance".
    :param max_steps: truncation horizon; ``None`` gives ``50 + 80 * len(instruction)``. (``gym.make``'s own
        ``max_episode_steps`` adds Gymnasium's ``TimeLimit`` wrapper on top, as for any env.)
    :param render_mode: "rgb_array" (headless TinyRenderer) or "human" (GUI window; needs a display).
    :param render_width: frame width in pixels.
    :param render_height: frame height in pixels.
    :param n_substeps: physics steps (of ``PHYSICS_DT``) per control step.
    :param dynamics: how the arms respond to the policy's commands (:mod:`vafn_gym.dynamics`): ``None`` (nominal), a
        :class:`Dynamics` or a dict of its fields (fixed), or "train" / "test" to draw a variant of that split of
        :data:`~vafn_gym.dynamics.DYNAMICS_VARIANTS` at every reset (``info["dynamics"]`` names it). Only the policy's
        velocity commands are affected, not the env's own return-home motion of held arms.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": int(round(1.0 / (PHYSICS_DT * N_SUBSTEPS)))}

    def __init__(
        self,
        n_arms: int = 3,
        robot: str | RobotSpec = "kuka",
        layout: ArmLayout | None = None,
        targets: str = "default",
        observe_goal: bool = False,
        history: int = 1,
        frame: str = "world",
        inactive_arms: str = "hold",
        waiting_goal: str = "target",
        instruction: Any = None,
        split: str = "train",
        min_length: int = 1,
        max_length: int = MAX_INSTRUCTION_LENGTH,
        split_seed: int = 0,
        reward_type: str = "dense",
        reward_kwargs: Mapping[str, Any] | None = None,
        terminate_on_collision: bool = False,
        safety_margin: float = 0.0,
        success_tolerance: float = SUCCESS_TOLERANCE,
        max_steps: int | None = None,
        render_mode: str | None = None,
        render_width: int = 480,
        render_height: int = 360,
        n_substeps: int = N_SUBSTEPS,
        dynamics: Any = None,
    ) -> None:
        self.robot = get_robot(robot)
        if isinstance(dynamics, str):
            self.dynamics_sampler: DynamicsSampler | None = DynamicsSampler(dynamics)
            self.dynamics = self.dynamics_sampler.variants[0]
        else:
            self.dynamics_sampler, self.dynamics = None, Dynamics.coerce(dynamics)
        self._fixed_dynamics: Dynamics | None = None
        self._pending_actions: list[np.ndarray] = []
        if layout is None:
            layout = ArmLayout(n_arms=check_int("n_arms", n_arms, 2, MAX_ARMS), base_radius=self.robot.base_radius)
        elif not isinstance(layout, ArmLayout):
            raise TypeError(f"layout must be an ArmLayout, got {type(layout).__name__}")
        layout.check_feasible(self.robot)
        self.layout = layout
        self.targets = check_choice("targets", targets, TARGET_MODES)
        self.observe_goal = check_bool("observe_goal", observe_goal)
        self.history = check_int("history", history, 1, MAX_HISTORY)
        self.frame = check_choice("frame", frame, FRAMES)
        self.inactive_arms = check_choice("inactive_arms", inactive_arms, INACTIVE_ARM_MODES)
        self.waiting_goal = check_choice("waiting_goal", waiting_goal, WAITING_GOALS)
        check_choice("split", split, SPLITS)
        check_choice("reward_type", reward_type, REWARD_TYPES)
        if reward_kwargs is not None and not isinstance(reward_kwargs, Mapping):
            raise TypeError(f"reward_kwargs must be a dict, got {type(reward_kwargs).__name__}")
        reward = RewardConfig.from_kwargs(reward_kwargs)
        self.terminate_on_collision = check_bool("terminate_on_collision", terminate_on_collision)
        self.safety_margin = check_number("safety_margin", safety_margin, 0.0, 1.0)
        self.fixed_max_steps = (
            None if max_steps is None else check_int("max_steps", max_steps, 1)
        )
        if render_mode is not None:
            check_choice("render_mode", render_mode, self.metadata["render_modes"])
        self.render_mode = render_mode
        self.render_size = (
            check_int("render_width", render_width, 1, MAX_RENDER_SIZE),
            check_int("render_height", render_height, 1, MAX_RENDER_SIZE),
        )
        n_substeps = check_int("n_substeps", n_substeps, 1, 1000)
        self.sampler = TaskSampler(
            split, self.targets, check_int("min_length", min_length, 0), check_int("max_length", max_length, 0),
            split_seed=check_int("split_seed", split_seed), layout=layout,
        )
        self._task: Instruction | None = None if instruction is None else self._coerce(instruction)

        self.sim = BulletSim(gui=render_mode == "human", n_substeps=n_substeps)
        with self.sim.no_rendering():
            self.sim.load_urdf("plane.urdf", np.zeros(3))
            self.sim.create_table_top(layout.base_radius, TABLE_COLOUR)
            self.arms = {
                arm: Arm(self.sim, self.robot, layout.base_position(arm), layout.base_yaw(arm), layout.home_point(arm))
                for arm in layout.arm_ids
            }
            self.markers = {
                arm: self.sim.create_marker(self.arms[arm].home, MARKER_RADIUS, layout.colour(arm))
                for arm in layout.arm_ids
            }
        for _ in range(SETTLE_STEPS):
            self.sim.step()
        for arm in self.arms.values():
            arm.settle()
        self._base_masses = {i: self.sim.link_mass(arm.body, self.robot.ee_link) for i, arm in self.arms.items()}
        self._apply_dynamics(self.dynamics)
        homes = {arm_id: arm.home for arm_id, arm in self.arms.items()}
        self.task = InstructionTask(
            layout, self.targets, self.inactive_arms, reward_type, reward, homes,
            check_number("success_tolerance", success_tolerance, 1e-3, MAX_SUCCESS_TOLERANCE), self.waiting_goal,
        )

        self.reading_size = OBS_PER_ARM_WITH_GOAL if self.observe_goal else OBS_PER_ARM
        self.obs_per_arm = self.reading_size * self.history
        self._readings: np.ndarray | None = None  # (history, n_arms, reading_size), newest first
        self.action_space = spaces.Box(-1.0, 1.0, shape=(layout.action_dim,), dtype=np.float32)
        self.observation_space = self._make_observation_space()
        self.gated = False
        #: The settings that define this env's world, task and reward (a twin env is ``MultiArmEnv(**world_kwargs)``).
        self.world_kwargs: dict[str, Any] = dict(
            layout=layout, robot=self.robot, targets=self.targets, observe_goal=self.observe_goal, history=self.history,
            frame=self.frame, inactive_arms=self.inactive_arms, waiting_goal=self.waiting_goal, reward_type=reward_type,
            reward_kwargs=reward.as_dict(),
            terminate_on_collision=self.terminate_on_collision, safety_margin=self.safety_margin, n_substeps=n_substeps,
            split_seed=split_seed, dynamics=dynamics if isinstance(dynamics, str) else self.dynamics,
        )

    @property
    def n_arms(self) -> int:
        """Number of arms."""
        return self.layout.n_arms

    def _coerce(self, instruction: Any) -> Instruction:
        instruction = Instruction.coerce(instruction, n_arms=self.layout.n_arms)
        if len(instruction) > MAX_INSTRUCTION_LENGTH:
            raise ValueError(f"instruction has {len(instruction)} waypoints; at most {MAX_INSTRUCTION_LENGTH}")
        return instruction

    # --- spaces and observation ---
    def _make_observation_space(self) -> spaces.Box:
        point_low, point_high = WORKSPACE_LOW.astype(np.float64), WORKSPACE_HIGH.astype(np.float64)
        if self.frame == "base":
            # Any workspace point seen from a base on the circle; the same bounds for every layout whose bases stand
            # within the workspace's radius, so a model saved on one robot loads with an env of another.
            radius = float(np.linalg.norm(np.maximum(-point_low[:2], point_high[:2])))
            reach = radius + max(radius, self.layout.base_radius)
            point_low, point_high = np.array([-reach, -reach, point_low[2]]), np.array([reach, reach, point_high[2]])
        low = np.concatenate([point_low, [0.0, PHASE_WAITING]])
        high = np.concatenate([point_high, [MAX_DISTANCE, PHASE_COMPLETED]])
        if self.observe_goal:
            low, high = np.concatenate([low, point_low]), np.concatenate([high, point_high])
        low, high = np.tile(low, self.n_arms * self.history), np.tile(high, self.n_arms * self.history)
        return spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)

    def obs_slice(self, arm: int) -> slice:
        """Slice of the observation that belongs to ``arm`` (1-based)."""
        return self.layout.block_slice(arm, self.obs_per_arm)

    def observed_point(self, arm: int, point: np.ndarray) -> np.ndarray:
        """A world point as ``arm``'s observation block gives it (unchanged in the "world" frame)."""
        if self.frame == "base":
            return self.layout.to_base_frame(arm, point)
        return np.asarray(point, dtype=np.float64)

    def _positions(self) -> dict[int, np.ndarray]:
        return {arm_id: arm.ee_position for arm_id, arm in self.arms.items()}

    def _reading(self, positions: Mapping[int, np.ndarray], distances: np.ndarray) -> np.ndarray:
        """This step's ``(n_arms, reading_size)`` readings: position, distance, phase (and goal) of every arm."""
        reading = np.zeros((self.n_arms, self.reading_size), dtype=np.float64)
        for row, (arm, distance) in enumerate(zip(self.layout.arm_ids, distances)):
            reading[row, POS_SLICE] = self.observed_point(arm, positions[arm])
            reading[row, DIST_INDEX] = distance
            reading[row, PHASE_INDEX] = self.task.phase(arm)
            if self.observe_goal:
                reading[row, GOAL_SLICE] = self.observed_point(arm, self.task.goal(arm))
        return reading

    def _observation(
        self, positions: Mapping[int, np.ndarray], distances: np.ndarray, record: bool = True
    ) -> np.ndarray:
        """The observation for ``positions``; ``record`` pushes this reading into the history (once per control step),
        otherwise it only stands in for the newest one."""
        reading = self._reading(positions, distances)
        if self._readings is None:
            readings = np.repeat(reading[None], self.history, axis=0)
        else:
            readings = np.concatenate([reading[None], self._readings[:-1] if record else self._readings[1:]])
        if record:
            self._readings = readings
        obs = readings.transpose(1, 0, 2).reshape(-1)  # arm by arm, newest reading first within each arm's block
        return np.clip(obs, self.observation_space.low, self.observation_space.high).astype(np.float32)

    def observe(self) -> np.ndarray:
        """The current observation, without stepping (e.g. after a controller starts an instruction)."""
        positions = self._positions()
        return self._observation(positions, self.task.distances(positions), record=False)

    # --- the task, as Meta-World exposes it ---
    @property
    def instruction(self) -> Instruction:
        """The instruction being executed (targets resolved)."""
        return self.task.instruction

    @property
    def active_arm(self) -> int | None:
        """The arm executing the current waypoint, or None."""
        return self.task.active_arm

    def set_task(self, task: Any) -> None:
        """Use ``task`` (anything :meth:`Instruction.coerce` accepts; ``None`` = sample) from the next reset on."""
        self._task = None if task is None else self._coerce(task)

    def set_dynamics(self, dynamics: Any) -> None:
        """Change how the arms respond *now* (mid-episode too) and keep it over resets; ``None`` returns to the env's
        own ``dynamics`` setting (nominal, fixed or a split drawn at every reset)."""
        if dynamics is None:
            self._fixed_dynamics = None
            return
        self._fixed_dynamics = Dynamics.coerce(dynamics)
        self._apply_dynamics(self._fixed_dynamics)

    def _apply_dynamics(self, dynamics: Dynamics) -> None:
        self.dynamics = dynamics
        for arm_id, arm in self.arms.items():
            self.sim.set_link_mass(arm.body, self.robot.ee_link, self._base_masses[arm_id] + dynamics.payload)
        self._pending_actions = self._pending_actions[-dynamics.action_delay:] if dynamics.action_delay else []

    def get_task(self) -> Instruction:
        """The instruction of the current episode, targets resolved (pass it to :meth:`set_task` to replay it)."""
        return self.task.instruction

    # --- episode ---
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Home every arm and start an instruction.

        ``options={"instruction": ...}`` overrides the task for one episode.
        """
        if options is not None and not isinstance(options, Mapping):
            raise TypeError(f"options must be a dict or None, got {type(options).__name__}")
        instruction = None
        if options and "instruction" in options:
            instruction = self._coerce(options["instruction"])  # validated before anything changes
        super().reset(seed=seed)
        if seed is not None:
            self.sampler.seed(int(self.np_random.integers(2**63)))
            if self.dynamics_sampler is not None:
                self.dynamics_sampler.seed(int(self.np_random.integers(2**63)))
        if self._fixed_dynamics is not None:
            self._apply_dynamics(self._fixed_dynamics)
        elif self.dynamics_sampler is not None:
            self._apply_dynamics(self.dynamics_sampler.sample())
        self._pending_actions = []
        for arm in self.arms.values():
            arm.reset()
        self._readings = None
        self._begin_episode(instruction)
        positions = self._positions()
        distances = self.task.distances(positions)
        return self._observation(positions, distances), self._info(distances, contact=False)

    def _begin_episode(self, instruction: Instruction | None) -> None:
        """Start the episode's instruction: the option's, the fixed task's or a sampled one."""
        if instruction is None:
            instruction = self._task if self._task is not None else self.sampler.sample()
        self.start_instruction(instruction)

    def start_instruction(self, instruction: Instruction) -> None:
        """Begin ``instruction`` from the arms' current state (targets resolved with the env's random stream)."""
        self.task.start(self.task.resolve(instruction, self.np_random))
        self.gated = False
        self._update_markers()

    def max_episode_steps(self) -> int:
        """Truncation horizon of the current episode."""
        if self.fixed_max_steps is not None:
            return self.fixed_max_steps
        return self.default_instruction_budget()

    def default_instruction_budget(self) -> int:
        """Steps the current instruction gets by default: ``50 + 80 * len(instruction)``."""
        return BASE_EPISODE_STEPS + STEPS_PER_WAYPOINT * len(self.task.instruction)

    def _update_markers(self) -> None:
        for arm, marker in self.markers.items():
            self.sim.move_marker(marker, self.task.current_target(arm))

    def _validate_action(self, action: Any) -> np.ndarray:
        try:
            raw = np.asarray(action)
            if raw.dtype.kind not in "iuf":
                raise TypeError(f"dtype {raw.dtype}")
            array = raw.astype(np.float64)
        except (TypeError, ValueError, OverflowError) as error:
            raise ValueError(
                f"action must be {self.layout.action_dim} real numbers; got entries that are not ({error})"
            ) from error
        if array.shape != (self.layout.action_dim,):
            raise ValueError(f"action must have shape ({self.layout.action_dim},), got {array.shape}")
        if not np.all(np.isfinite(array)):
            bad = np.flatnonzero(~np.isfinite(array)).tolist()
            raise ValueError(f"action has non-finite entries at indices {bad}; nothing was sent to the simulator")
        return np.clip(array, -1.0, 1.0)

    def _clear_of_shared_region(self, positions: Mapping[int, np.ndarray], active: int) -> bool:
        return all(
            np.linalg.norm(positions[arm] - self.arms[arm].home) < CLEARANCE_DISTANCE
            for arm in self.layout.arm_ids if arm != active
        )

    def _delayed(self, action: np.ndarray) -> np.ndarray:
        """The action that takes effect now: the one sent ``action_delay`` steps ago (zeros before the episode)."""
        delay = self.dynamics.action_delay
        if delay == 0:
            return action
        self._pending_actions.append(action)
        if len(self._pending_actions) <= delay:
            return np.zeros_like(action)
        return self._pending_actions.pop(0)

    def _apply_action(self, action: np.ndarray, positions: Mapping[int, np.ndarray]) -> None:
        dt, active = self.sim.dt, self.task.active_arm
        action = self._delayed(action)
        hold_mode = self.inactive_arms == "hold"
        self.gated = hold_mode and active is not None and not self._clear_of_shared_region(positions, active)
        for arm_id, arm in self.arms.items():
            if hold_mode and arm_id != active:
                arm.command_toward(arm.home, dt, positions[arm_id])
            elif self.gated:
                arm.command_velocity(np.zeros(3), dt, positions[arm_id])
            else:
                velocity = action[self.layout.action_slice(arm_id)] * V_MAX
                if self.frame == "base":
                    velocity = self.layout.base_to_world_vector(arm_id, velocity)
                arm.command_velocity(self.dynamics.velocity(velocity), dt, positions[arm_id])
        self.sim.step()

    def _arm_contact(self) -> bool:
        return any(self.sim.contact_count(self.arms[a].body, self.arms[b].body) > 0 for a, b in self.layout.arm_pairs)

    def _too_close(self) -> bool:
        return self.safety_margin > 0 and any(
            self.sim.closest_points_count(self.arms[a].body, self.arms[b].body, self.safety_margin) > 0
            for a, b in self.layout.arm_pairs
        )

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Apply an end-effector velocity command (3 per arm, in [-1, 1] × ``V_MAX``) for one control step."""
        positions, reward, contact = self._advance(action)
        terminated = self.task.complete or (contact and self.terminate_on_collision)
        truncated = not terminated and self.task.steps >= self.max_episode_steps()
        distances = self.task.distances(positions)
        return self._observation(positions, distances), reward, terminated, truncated, self._info(distances, contact)

    def _advance(self, action: Any) -> tuple[dict[int, np.ndarray], float, bool]:
        """Validate and apply an action, account it in the task; returns (positions, reward, contact)."""
        action = self._validate_action(action)
        before = self._positions()
        self._apply_action(action, before)
        after = self._positions()
        contact = self._arm_contact()
        index = self.task.waypoint_index
        reward = self.task.step(before, after, contact, self._too_close())
        if self.task.waypoint_index != index:
            self._update_markers()
        return after, reward, contact

    def _info(self, distances: np.ndarray, contact: bool) -> dict[str, Any]:
        info = self.task.info(distances, contact)
        active = self.task.active_arm
        info["gated"] = self.gated
        info["dynamics"] = self.dynamics
        info["ignored_arms"] = (
            [arm for arm in self.layout.arm_ids if arm != active or self.gated] if self.inactive_arms == "hold" else []
        )
        return info

    # --- rendering ---
    def render(self) -> np.ndarray | None:
        """An RGB frame in "rgb_array" mode (the GUI draws itself in "human" mode)."""
        if self.render_mode != "rgb_array":
            return None
        width, height = self.render_size
        return self.sim.render(width, height, **self.camera())

    def camera(self) -> dict[str, Any]:
        """The orbit camera of :meth:`render`: look-at ``target``, ``distance``, ``yaw`` and ``pitch`` (degrees)."""
        return {"target": np.array([0.0, 0.0, 0.3]), "distance": 1.1 + self.layout.base_radius, "yaw": 30.0,
                "pitch": -30.0}

    def close(self) -> None:
        """Release the physics client; safe to call twice."""
        self.sim.close()
