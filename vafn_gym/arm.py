"""One KUKA iiwa arm: its URDF, base pose, end-effector link, and the velocity command → IK → joint-target law."""

from __future__ import annotations

import numpy as np

from vafn_gym.constants import WORKSPACE_HIGH, WORKSPACE_LOW, arm_base_position, arm_base_yaw, home_position
from vafn_gym.sim import BulletSim

#: The robot model: a 7-DOF KUKA LBR iiwa shipped inside the pybullet wheel (BSD-style licence, header in the URDF).
URDF_PATH = "kuka_iiwa/model.urdf"
JOINTS = list(range(7))
EE_LINK = 6
JOINT_FORCES = np.full(len(JOINTS), 300.0)
#: A relaxed elbow-up posture used as the IK null-space rest pose and to seed the home-pose solve.
REST_POSE = np.array([0.0, 0.6, 0.0, -1.6, 0.0, 0.9, 0.0])
#: IK iterations for a per-step command (small moves) and for the one-off home-pose solve.
STEP_IK_ITERATIONS = 20
HOME_IK_ITERATIONS = 200


class Arm:
    """Arm ``arm_id`` (1-based) standing on the base circle, facing the table centre.

    :param sim: the physics client that owns the arm.
    :param arm_id: 1-based arm id, as users name arms.
    """

    def __init__(self, sim: BulletSim, arm_id: int) -> None:
        self.sim = sim
        self.arm_id = arm_id
        self.base_position = arm_base_position(arm_id)
        # The URDF's x axis points forward; turn it to face the centre.
        self.body = sim.load_urdf(URDF_PATH, self.base_position, yaw=arm_base_yaw(arm_id) + np.pi)
        self.limits = sim.joint_limits(self.body, JOINTS)
        self.home_joints = self._solve_home()
        self.reset()
        #: Where the end effector actually rests (IK leaves ~1 cm of the nominal home point unreached).
        self.home = self.ee_position

    def _solve_home(self) -> np.ndarray:
        angles = REST_POSE.copy()
        for _ in range(3):
            self.sim.reset_joints(self.body, JOINTS, angles)
            angles = self.sim.inverse_kinematics(
                self.body, EE_LINK, home_position(self.arm_id), REST_POSE, self.limits, iterations=HOME_IK_ITERATIONS
            )[: len(JOINTS)]
        return angles

    def reset(self) -> None:
        """Teleport to the home pose with zero velocity and hold it (bit-exact, unlike saveState/restoreState)."""
        self.sim.reset_joints(self.body, JOINTS, self.home_joints)
        self.sim.control_joints(self.body, JOINTS, self.home_joints, JOINT_FORCES)

    @property
    def ee_position(self) -> np.ndarray:
        """Current end-effector position (world metres)."""
        return self.sim.link_position(self.body, EE_LINK)

    def command_velocity(self, velocity: np.ndarray, dt: float, position: np.ndarray) -> np.ndarray:
        """Integrate an EE velocity over ``dt`` from ``position``, clip to the workspace, solve IK, set joint targets.

        :param velocity: end-effector velocity (m/s).
        :param dt: control step (s).
        :param position: the current end-effector position (the caller has just read it).
        :return: the commanded end-effector point.
        """
        target = np.clip(position + velocity * dt, WORKSPACE_LOW, WORKSPACE_HIGH)
        joints = self.sim.inverse_kinematics(
            self.body, EE_LINK, target, REST_POSE, self.limits, iterations=STEP_IK_ITERATIONS
        )[: len(JOINTS)]
        self.sim.control_joints(self.body, JOINTS, joints, JOINT_FORCES)
        return target
