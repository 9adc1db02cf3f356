"""vafn_gym: three PyBullet arms behind Gymnasium envs, the instruction format, the Dynamic Instruction Queue, tasks.

Importing the package registers the environment IDs listed in :data:`ENV_IDS` with Gymnasium.
"""

from gymnasium.envs.registration import register

from vafn_gym.constants import ARM_IDS
from vafn_gym.controllers import ScriptedController
from vafn_gym.instructions import Instruction, Waypoint, difficulty_of
from vafn_gym.queue import (
    ArrivalProcess,
    InstructionQueue,
    PoissonArrivals,
    QueuedInstruction,
    QueueFullError,
    ScheduledArrivals,
)
from vafn_gym.tasks import SPLITS, TASK_FAMILIES, TaskSampler

#: ID -> (entry point, default kwargs). Which task family each ID uses is documented in the README.
_REGISTRY = {
    "VAFN/ThreeArmReach-v0": ("vafn_gym.envs:ThreeArmEnv", {"task_family": "order"}),
    "VAFN/ThreeArmReachHidden-v0": ("vafn_gym.envs:ThreeArmEnv", {"task_family": "hidden_targets"}),
    "VAFN/ThreeArmReachGoal-v0": ("vafn_gym.envs:ThreeArmEnv", {"task_family": "goal_visible"}),
    "VAFN/ThreeArmReachSparse-v0": ("vafn_gym.envs:ThreeArmEnv", {"task_family": "order", "reward_type": "sparse"}),
    "VAFN/ThreeArmStream-v0": ("vafn_gym.envs:ThreeArmStreamEnv", {"task_family": "order"}),
}

ENV_IDS: list[str] = []
for _env_id, (_entry_point, _kwargs) in _REGISTRY.items():
    # Episodes are truncated by the env itself (the budget depends on the instruction length), so no TimeLimit.
    register(id=_env_id, entry_point=_entry_point, kwargs=_kwargs)
    ENV_IDS.append(_env_id)

#: Names served lazily from vafn_gym.multimedia, so that ``import vafn_gym`` never imports torch, librosa or OpenCV.
_MULTIMEDIA_NAMES = ("InstructionGenerator", "MultimediaStream", "Transcription")


def __getattr__(name: str):
    if name in _MULTIMEDIA_NAMES:
        from vafn_gym import multimedia

        return getattr(multimedia, name)
    raise AttributeError(f"module 'vafn_gym' has no attribute {name!r}")


__all__ = [
    "ARM_IDS",
    "ENV_IDS",
    "SPLITS",
    "TASK_FAMILIES",
    "ArrivalProcess",
    "Instruction",
    "InstructionGenerator",
    "InstructionQueue",
    "MultimediaStream",
    "PoissonArrivals",
    "QueueFullError",
    "QueuedInstruction",
    "ScheduledArrivals",
    "ScriptedController",
    "TaskSampler",
    "Transcription",
    "Waypoint",
    "difficulty_of",
]
