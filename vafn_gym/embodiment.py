"""Embodiment variants: another robot, a payload, damped joints, weaker motors, bases moved by a few centimetres.

Where :mod:`vafn_gym.dynamics` changes what a command does (the command-to-motion map), these change the body that
carries the command out, each as the env kwargs that build it. The end-effector velocity command goes through inverse
kinematics and joint position control, so a policy trained on the nominal KUKA arms meets the same command-to-motion
map on all of them, up to how fast the joints can follow (``benchmarks/transfer.py --embodiment`` measures it).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from vafn_gym.layout import ArmLayout
from vafn_gym.robots import KUKA_IIWA

#: ``label -> env kwargs`` of each embodiment variant (on top of the env's own kwargs); the first is the nominal body.
EMBODIMENT_VARIANTS: dict[str, dict[str, Any]] = {
    "nominal (KUKA arms)": {},
    "Panda arms": {"robot": "panda"},
    "xArm6 arms": {"robot": "xarm"},
    "payload 2 kg": {"dynamics": {"payload": 2.0}},
    "payload 5 kg": {"dynamics": {"payload": 5.0}},
    "joint damping 5": {"robot": replace(KUKA_IIWA, joint_damping=5.0)},
    "joint damping 50": {"robot": replace(KUKA_IIWA, joint_damping=50.0)},
    "motors at 30 % force": {"robot": replace(KUKA_IIWA, joint_force=0.3 * KUKA_IIWA.joint_force)},
    "motors at 15 % force": {"robot": replace(KUKA_IIWA, joint_force=0.15 * KUKA_IIWA.joint_force)},
    "motors at 10 % force": {"robot": replace(KUKA_IIWA, joint_force=0.1 * KUKA_IIWA.joint_force)},
    "bases 5 cm inward": {"layout": ArmLayout(base_radius=0.55)},
    "bases 5 cm outward": {"layout": ArmLayout(base_radius=0.65)},
    "bases turned 6 cm about the centre": {"layout": ArmLayout(base_yaw0=0.1)},
}
