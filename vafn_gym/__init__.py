"""vafn_gym: three PyBullet arms behind Gymnasium envs, the instruction format, the Dynamic Instruction Queue, tasks."""

from vafn_gym.instructions import ARM_IDS, Instruction, Waypoint, difficulty_of

__all__ = ["ARM_IDS", "Instruction", "Waypoint", "difficulty_of"]
