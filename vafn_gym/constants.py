"""The one source of truth for the world vafn simulates: arm count, workspace, observation layout, control timing.

Every other module imports these names; no number that describes the world is written twice.
"""

from __future__ import annotations

import numpy as np

#: Number of arms sharing the workspace; arms are named 1..NUM_ARMS by users (1-based).
NUM_ARMS: int = 3
#: Arm ids as users say them (1-based).
ARM_IDS: tuple[int, ...] = tuple(range(1, NUM_ARMS + 1))
#: Longest instruction (number of waypoints) the paper considers.
MAX_INSTRUCTION_LENGTH: int = 10
#: Difficulty buckets of the paper, by instruction length (inclusive ranges).
DIFFICULTY_LENGTHS: dict[str, tuple[int, int]] = {"easy": (0, 3), "medium": (4, 6), "hard": (7, 10)}

# --- geometry (metres, world frame; the table centre is the origin, z up) ---
#: Arms stand on a circle of this radius around the table centre, 360/NUM_ARMS degrees apart, facing the centre.
BASE_RADIUS: float = 0.6
#: Yaw (radians) of arm 1's base position on the circle; arm k sits at BASE_YAW0 + (k-1) * 2*pi/NUM_ARMS.
BASE_YAW0: float = 0.0
#: Axis-aligned box every commanded end-effector position is clipped to.
WORKSPACE_LOW: np.ndarray = np.array([-0.75, -0.75, 0.05], dtype=np.float32)
WORKSPACE_HIGH: np.ndarray = np.array([0.75, 0.75, 1.0], dtype=np.float32)
#: The shared region where all reaches overlap: a vertical cylinder around the table centre.
SHARED_RADIUS: float = 0.15
SHARED_Z_RANGE: tuple[float, float] = (0.2, 0.45)
#: Rest ("home") end-effector point of each arm, expressed as (distance in front of its base, height).
HOME_FORWARD: float = 0.25
HOME_HEIGHT: float = 0.55
#: Default per-arm target used when an instruction names arms only: a point in the shared region offset toward the arm.
DEFAULT_TARGET_OFFSET: float = 0.08
DEFAULT_TARGET_HEIGHT: float = 0.3

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

# --- observation layout: per arm [p(3), d(1), phase(1)] ---
POS_SLICE = slice(0, 3)
DIST_INDEX: int = 3
PHASE_INDEX: int = 4
OBS_PER_ARM: int = 5
OBS_DIM: int = OBS_PER_ARM * NUM_ARMS
ACTION_PER_ARM: int = 3
ACTION_DIM: int = ACTION_PER_ARM * NUM_ARMS
#: Phase flags of the observation.
PHASE_WAITING: int = 0
PHASE_EXECUTING: int = 1
PHASE_COMPLETED: int = 2
#: Upper bound on any end-effector-to-target distance: the diagonal of the workspace box.
MAX_DISTANCE: float = float(np.linalg.norm(WORKSPACE_HIGH - WORKSPACE_LOW))


def arm_base_yaw(arm: int) -> float:
    """Yaw (radians) of arm ``arm``'s position on the base circle (1-based arm id)."""
    return BASE_YAW0 + (arm - 1) * 2.0 * np.pi / NUM_ARMS


def arm_base_position(arm: int) -> np.ndarray:
    """World position of arm ``arm``'s base (1-based arm id)."""
    yaw = arm_base_yaw(arm)
    return np.array([BASE_RADIUS * np.cos(yaw), BASE_RADIUS * np.sin(yaw), 0.0])


def _toward_centre(arm: int, distance_from_centre: float, height: float) -> np.ndarray:
    yaw = arm_base_yaw(arm)
    return np.array([distance_from_centre * np.cos(yaw), distance_from_centre * np.sin(yaw), height])


def home_position(arm: int) -> np.ndarray:
    """Rest end-effector point of arm ``arm``: clear of the shared region."""
    return _toward_centre(arm, BASE_RADIUS - HOME_FORWARD, HOME_HEIGHT)


def default_target(arm: int) -> np.ndarray:
    """Target of arm ``arm`` when an instruction gives none."""
    return _toward_centre(arm, DEFAULT_TARGET_OFFSET, DEFAULT_TARGET_HEIGHT)


def obs_slice(arm: int) -> slice:
    """Slice of the 15-D observation that belongs to arm ``arm`` (1-based)."""
    start = (arm - 1) * OBS_PER_ARM
    return slice(start, start + OBS_PER_ARM)


def action_slice(arm: int) -> slice:
    """Slice of the 9-D action that belongs to arm ``arm`` (1-based)."""
    start = (arm - 1) * ACTION_PER_ARM
    return slice(start, start + ACTION_PER_ARM)
