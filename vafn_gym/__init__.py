"""vafn_gym: N PyBullet arms behind Gymnasium envs, the instruction format, the Dynamic Instruction Queue, tasks.

Importing the package registers the environment IDs listed in :data:`ENV_IDS` with Gymnasium.
"""

from gymnasium.envs.registration import register

from vafn_gym.benchmarks import InstructionBenchmark, confidence_half_width, episode_rates, run_episode
from vafn_gym.controllers import RandomPolicy, ScriptedController, trilaterate
from vafn_gym.dynamics import DYNAMICS_VARIANTS, Dynamics, DynamicsSampler
from vafn_gym.embodiment import EMBODIMENT_VARIANTS
from vafn_gym.envs import MultiArmEnv, MultiArmStreamEnv
from vafn_gym.instructions import Instruction, Waypoint, difficulty_of
from vafn_gym.layout import ArmLayout
from vafn_gym.queue import (
    ArrivalProcess,
    InstructionQueue,
    PoissonArrivals,
    QueuedInstruction,
    QueueFullError,
    ScheduledArrivals,
)
from vafn_gym.robots import KUKA_IIWA, PANDA, ROBOTS, XARM6, RobotSpec
from vafn_gym.task import INACTIVE_ARM_MODES, TARGET_MODES, WAITING_GOALS, InstructionTask, RewardConfig
from vafn_gym.tasks import SPLITS, TaskSampler
from vafn_gym.wrappers import DynamicsTasks, GoalDetours

#: ID -> (entry point, default kwargs). docs/environments.md documents each one.
_REGISTRY = {
    "VAFN/ThreeArmReach-v1": ("vafn_gym.envs:MultiArmEnv", {"n_arms": 3, "targets": "default"}),
    "VAFN/ThreeArmReachHidden-v1": ("vafn_gym.envs:MultiArmEnv", {"n_arms": 3, "targets": "per_arm"}),
    "VAFN/ThreeArmReachGoal-v1": (
        "vafn_gym.envs:MultiArmEnv", {"n_arms": 3, "targets": "per_arm", "observe_goal": True}
    ),
    "VAFN/ThreeArmStream-v1": ("vafn_gym.envs:MultiArmStreamEnv", {"n_arms": 3, "targets": "default"}),
    "VAFN/MultiArmReach-v1": ("vafn_gym.envs:MultiArmEnv", {}),
}

ENV_IDS: list[str] = []
for _env_id, (_entry_point, _kwargs) in _REGISTRY.items():
    # Episodes are truncated by the env itself (the budget depends on the instruction length), so no TimeLimit.
    register(id=_env_id, entry_point=_entry_point, kwargs=_kwargs)
    ENV_IDS.append(_env_id)

__all__ = [
    "EMBODIMENT_VARIANTS",
    "DYNAMICS_VARIANTS",
    "ENV_IDS",
    "INACTIVE_ARM_MODES",
    "WAITING_GOALS",
    "KUKA_IIWA",
    "PANDA",
    "ROBOTS",
    "SPLITS",
    "TARGET_MODES",
    "XARM6",
    "ArmLayout",
    "ArrivalProcess",
    "Dynamics",
    "DynamicsSampler",
    "DynamicsTasks",
    "GoalDetours",
    "Instruction",
    "InstructionBenchmark",
    "InstructionQueue",
    "InstructionTask",
    "MultiArmEnv",
    "MultiArmStreamEnv",
    "PoissonArrivals",
    "QueueFullError",
    "QueuedInstruction",
    "RewardConfig",
    "RobotSpec",
    "ScheduledArrivals",
    "RandomPolicy",
    "ScriptedController",
    "TaskSampler",
    "Waypoint",
    "confidence_half_width",
    "difficulty_of",
    "episode_rates",
    "run_episode",
    "trilaterate",
]
