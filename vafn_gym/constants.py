"""World constants shared by every layout: workspace box, control timing, tolerances and the per-arm observation block.

Nothing here depends on the number of arms or on the robot model: those live in :mod:`vafn_gym.layout` and
:mod:`vafn_gym.robots` and are passed to the env, so two layouts can live in one process.
"""

from __future__ import annotations

import numpy as np

#: Longest instruction (number of waypoints) the paper considers.
MAX_INSTRUCTION_LENGTH: int = 10
#: Difficulty buckets of the paper, by instruction length (inclusive ranges).
DIFFICULTY_LENGTHS: dict[str, tuple[int, int]] = {"easy": (0, 3), "medium": (4, 6), "hard": (7, 10)}

# --- geometry (metres, world frame; the table centre is the origin, z up) ---
#: Axis-aligned box every commanded end-effector position is clipped to.
WORKSPACE_LOW: np.ndarray = np.array([-0.75, -0.75, 0.05], dtype=np.float32)
WORKSPACE_HIGH: np.ndarray = np.array([0.75, 0.75, 1.0], dtype=np.float32)
#: Upper bound on any end-effector-to-target distance: the diagonal of the workspace box.
MAX_DISTANCE: float = float(np.linalg.norm(WORKSPACE_HIGH - WORKSPACE_LOW))

# --- task and control ---
#: A waypoint is reached when the active end effector is within this distance of its target (metres).
SUCCESS_TOLERANCE: float = 0.05
#: Largest end-effector speed an action of magnitude 1 commands, per axis (m/s).
V_MAX: float = 1.0
#: PyBullet physics step and the number of physics steps per env step.
PHYSICS_DT: float = 1.0 / 240.0
N_SUBSTEPS: int = 5
#: Constraint-solver iterations per physics step. Bullet's default is 50; stiff position-controlled arms track as well
#: with 10 (the scripted controller's success is unchanged) and the physics step costs about 1.4x less.
SOLVER_ITERATIONS: int = 10
#: Duration of one env (control) step in seconds.
CONTROL_DT: float = PHYSICS_DT * N_SUBSTEPS

# --- observation layout: per arm [p(3), d(1), phase(1)] (+ the arm's current target(3) when the goal is observed) ---
POS_SLICE = slice(0, 3)
DIST_INDEX: int = 3
PHASE_INDEX: int = 4
GOAL_SLICE = slice(5, 8)
OBS_PER_ARM: int = 5
OBS_PER_ARM_WITH_GOAL: int = 8
ACTION_PER_ARM: int = 3
#: Phase flags of the observation.
PHASE_WAITING: int = 0
PHASE_EXECUTING: int = 1
PHASE_COMPLETED: int = 2
