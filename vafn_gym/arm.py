"""One arm: a robot spec at a base pose, and the end-effector velocity command → exact hold → IK → joint targets law."""

from __future__ import annotations

import numpy as np

from vafn_gym.constants import V_MAX, WORKSPACE_HIGH, WORKSPACE_LOW
from vafn_gym.robots import RobotSpec
from vafn_gym.sim import BulletSim

#: IK iterations for a per-step command (small moves) and for the one-off home-pose solve.
STEP_IK_ITERATIONS = 20
HOME_IK_ITERATIONS = 200
#: When the measured end effector is this far from the commanded point (e.g. after a collision or an unreachable
#: command), the command restarts from the measured point so that it cannot run away from the arm.
TRACKING_BOUND = 0.05


class Arm:
    """One robot arm standing at ``base_position``, facing the table centre.

    The command is integrated from the last *commanded* point, not from the measured end effector, so a zero velocity
    commands exactly the same joint targets again and the arm does not sag.

    :param sim: the physics client that owns the arm.
    :param spec: the robot model.
    :param base_position: world position of the base.
    :param base_yaw: yaw of the base position on the layout circle (the arm is turned to face the centre).
    :param home_point: nominal rest point of the end effector.
    """

    def __init__(
        self, sim: BulletSim, spec: RobotSpec, base_position: np.ndarray, base_yaw: float, home_point: np.ndarray
    ) -> None:
        self.sim = sim
        self.spec = spec
        self.joints = list(spec.joints)
        self.rest_pose = np.asarray(spec.rest_pose, dtype=np.float64)
        self.base_position = np.asarray(base_position, dtype=np.float64)
        self.body = sim.load_urdf(spec.urdf, self.base_position, yaw=base_yaw + spec.base_yaw_offset)
        if spec.joint_damping is not None:
            for joint in self.joints:
                sim.set_joint_damping(self.body, joint, spec.joint_damping)
        # pybullet's IK works on every movable joint (fingers included): limits and rest pose cover them all, and the
        # controlled joints are picked out of its answer.
        movable = sim.movable_joints(self.body)
        self._ik_indices = [movable.index(j) for j in self.joints]
        self._ik_limits = sim.joint_limits(self.body, movable)
        self._ik_rest = np.mean(self._ik_limits, axis=0)
        self._ik_rest[self._ik_indices] = self.rest_pose
        self.home_joints = self._solve(np.asarray(home_point, dtype=np.float64))
        self._movable = movable
        self._joint_targets = self.home_joints
        #: Pose every reset teleports to: all movable joints (fingers included, so they cannot creep across episodes);
        #: :meth:`settle` replaces it by the pose the motors actually hold.
        self._reset_pose = self._ik_rest.copy()
        self._reset_pose[self._ik_indices] = self.home_joints
        self.reset()
        #: Where the end effector rests; :meth:`settle` measures it after gravity has acted.
        self.home = self.ee_position

    def _solve(self, point: np.ndarray) -> np.ndarray:
        angles = self.rest_pose.copy()
        for _ in range(3):
            self.sim.reset_joints(self.body, self.joints, angles)
            angles = self._ik(point, HOME_IK_ITERATIONS)
        return angles

    def _ik(self, point: np.ndarray, iterations: int) -> np.ndarray:
        solution = self.sim.inverse_kinematics(
            self.body, self.spec.ee_link, point, self._ik_rest, self._ik_limits, iterations=iterations
        )
        return solution[self._ik_indices]

    def settle(self) -> None:
        """Record the pose the home joint targets hold under gravity (call after the simulator ran a few steps).

        Position control leaves the arm a few millimetres below its IK solution; teleporting to the settled pose makes
        every episode start at rest, so a held arm does not move at all.
        """
        self._reset_pose = self.sim.joint_angles(self.body, self._movable)
        self.reset()
        self.home = self.ee_position

    def reset(self) -> None:
        """Teleport to the home pose with zero velocity and hold it (bit-exact, unlike saveState/restoreState)."""
        self.sim.reset_joints(self.body, self._movable, self._reset_pose)
        self._joint_targets = self.home_joints
        self.sim.control_joints(self.body, self.joints, self.home_joints, self.spec.joint_forces)
        self.commanded = self.ee_position

    @property
    def ee_position(self) -> np.ndarray:
        """Current end-effector position (world metres)."""
        return self.sim.link_position(self.body, self.spec.ee_link)

    def command_velocity(self, velocity: np.ndarray, dt: float, position: np.ndarray) -> np.ndarray:
        """Move the commanded point by ``velocity * dt`` (clipped to the workspace) and track it with IK.

        :param velocity: end-effector velocity (m/s).
        :param dt: control step (s).
        :param position: the measured end-effector position (the caller has just read it).
        :return: the commanded end-effector point.
        """
        if np.linalg.norm(self.commanded - position) > TRACKING_BOUND:
            self.commanded = np.asarray(position, dtype=np.float64)
        target = np.clip(self.commanded + velocity * dt, WORKSPACE_LOW, WORKSPACE_HIGH)
        if not np.array_equal(target, self.commanded):
            self._joint_targets = self._ik(target, STEP_IK_ITERATIONS)
        self.commanded = target
        self.sim.control_joints(self.body, self.joints, self._joint_targets, self.spec.joint_forces)
        return target

    def command_toward(self, goal: np.ndarray, dt: float, position: np.ndarray) -> np.ndarray:
        """Move the commanded point straight toward ``goal`` (the env's low-level return/hold).

        The step keeps the direction of ``goal - commanded`` and is scaled so that no axis exceeds ``V_MAX``: a
        per-axis clip would bend the path (diagonal first) and sweep the arm through its neighbours' space.
        """
        delta = goal - self.commanded
        steps = max(1.0, float(np.max(np.abs(delta))) / (V_MAX * dt))
        return self.command_velocity(delta / steps / dt, dt, position)
