"""Robot models: everything robot-specific (URDF, joints, end-effector link, forces, rest pose) in one spec each.

All three ship inside the pybullet wheel (``pybullet_data``); a new robot is a new :class:`RobotSpec`, no core code.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RobotSpec:
    """A position-controlled arm model loaded from ``pybullet_data``.

    :param name: short name used by the ``robot=`` env kwarg.
    :param urdf: path inside ``pybullet_data``.
    :param joints: indices of the controlled (revolute) joints, base to tip.
    :param ee_link: link index whose frame is the end effector.
    :param joint_force: position-control force limit per joint (N·m).
    :param rest_pose: null-space rest posture (one angle per controlled joint) that also seeds the home-pose solve.
    :param base_yaw_offset: yaw (radians) added so that the model's forward axis faces the table centre.
    :param reach: horizontal reach from the base axis (metres) used by the layout feasibility check.
    :param base_radius: radius of the base circle the default layout uses for this robot.
    :param joint_damping: viscous damping of every controlled joint (None: the URDF's own).
    """

    name: str
    urdf: str
    joints: tuple[int, ...]
    ee_link: int
    joint_force: float
    rest_pose: tuple[float, ...]
    base_yaw_offset: float = np.pi
    reach: float = 0.8
    base_radius: float = 0.6
    joint_damping: float | None = None

    def __post_init__(self) -> None:
        if len(self.rest_pose) != len(self.joints):
            raise ValueError(f"{self.name}: rest_pose has {len(self.rest_pose)} angles for {len(self.joints)} joints")
        if not self.joint_force > 0:
            raise ValueError(f"{self.name}: joint_force must be > 0, got {self.joint_force}")
        if self.joint_damping is not None and not self.joint_damping >= 0:
            raise ValueError(f"{self.name}: joint_damping must be >= 0, got {self.joint_damping}")

    @property
    def joint_forces(self) -> np.ndarray:
        """Force limit per controlled joint."""
        return np.full(len(self.joints), self.joint_force)


#: 7-DOF KUKA LBR iiwa (the paper's arm and the default).
KUKA_IIWA = RobotSpec(
    name="kuka", urdf="kuka_iiwa/model.urdf", joints=tuple(range(7)), ee_link=6, joint_force=300.0,
    rest_pose=(0.0, 0.6, 0.0, -1.6, 0.0, 0.9, 0.0), reach=0.8,
)
#: 7-DOF Franka Emika Panda (fingers left open and uncontrolled); the end effector is the hand's grasp frame.
PANDA = RobotSpec(
    name="panda", urdf="franka_panda/panda.urdf", joints=tuple(range(7)), ee_link=11, joint_force=240.0,
    rest_pose=(0.0, 0.2, 0.0, -2.0, 0.0, 2.2, 0.8), reach=0.8,
)
#: 6-DOF UFactory xArm6.
XARM6 = RobotSpec(
    name="xarm", urdf="xarm/xarm6_robot.urdf", joints=tuple(range(1, 7)), ee_link=6, joint_force=200.0,
    rest_pose=(0.0, -0.3, -0.6, 0.0, 0.9, 0.0), reach=0.68, base_radius=0.5,
)

ROBOTS: dict[str, RobotSpec] = {spec.name: spec for spec in (KUKA_IIWA, PANDA, XARM6)}


def get_robot(robot: str | RobotSpec) -> RobotSpec:
    """A :class:`RobotSpec` from a name in :data:`ROBOTS` or a spec; ``ValueError`` listing the names otherwise."""
    if isinstance(robot, RobotSpec):
        return robot
    if isinstance(robot, str) and robot in ROBOTS:
        return ROBOTS[robot]
    raise ValueError(f"robot must be one of {sorted(ROBOTS)} or a RobotSpec, got {robot!r}")
