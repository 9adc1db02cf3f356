"""A thin wrapper around one PyBullet physics client (DIRECT by default): loading, stepping, contacts, camera."""

from __future__ import annotations

import functools
import os
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType

import numpy as np

from vafn_gym.constants import N_SUBSTEPS, PHYSICS_DT, SOLVER_ITERATIONS


@functools.cache
def pybullet() -> ModuleType:
    """The ``pybullet`` module, imported on first use."""
    # Importing vafn_gym for its instruction format or queue (as vafn_media does) must not load the simulator and
    # print its build banner.
    import pybullet as module

    return module


def display_available() -> bool:
    """Whether a GUI client can open a window on this machine."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class BulletSim:
    """One PyBullet client: the only place that talks to ``pybullet`` directly.

    :param gui: open a GUI window (needs a display) instead of a headless DIRECT client.
    :param physics_dt: physics time step in seconds.
    :param n_substeps: physics steps per call to :meth:`step`.
    """

    def __init__(self, gui: bool = False, physics_dt: float = PHYSICS_DT, n_substeps: int = N_SUBSTEPS) -> None:
        if gui and not display_available():
            raise RuntimeError("render_mode='human' needs a display (DISPLAY is unset); use render_mode='rgb_array'")
        import pybullet_data

        self._p = pybullet()
        self.client = self._p.connect(self._p.GUI if gui else self._p.DIRECT)
        if self.client < 0:
            raise RuntimeError("could not connect to a PyBullet physics server")
        # An env dropped without close() must not keep its physics server (tens of MB each).
        self._finalizer = weakref.finalize(self, _disconnect, self.client)
        self.physics_dt = physics_dt
        self.n_substeps = n_substeps
        self._p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=self.client)
        self._p.setTimeStep(physics_dt, physicsClientId=self.client)
        self._p.setGravity(0, 0, -9.81, physicsClientId=self.client)
        self._p.setPhysicsEngineParameter(numSolverIterations=SOLVER_ITERATIONS, physicsClientId=self.client)
        if gui:
            self._p.configureDebugVisualizer(self._p.COV_ENABLE_GUI, 0, physicsClientId=self.client)

    @property
    def dt(self) -> float:
        """Simulated seconds per :meth:`step`."""
        return self.physics_dt * self.n_substeps

    @contextmanager
    def no_rendering(self) -> Iterator[None]:
        """Pause GUI rendering while loading bodies (a no-op in DIRECT mode)."""
        self._p.configureDebugVisualizer(self._p.COV_ENABLE_RENDERING, 0, physicsClientId=self.client)
        try:
            yield
        finally:
            self._p.configureDebugVisualizer(self._p.COV_ENABLE_RENDERING, 1, physicsClientId=self.client)

    def load_urdf(self, path: str, position: np.ndarray, yaw: float = 0.0, fixed: bool = True) -> int:
        """Load a URDF from ``pybullet_data`` at ``position`` rotated by ``yaw``; returns the body id."""
        orientation = self._p.getQuaternionFromEuler([0.0, 0.0, yaw])
        return self._p.loadURDF(
            path, list(position), orientation, useFixedBase=fixed,
            flags=self._p.URDF_ENABLE_CACHED_GRAPHICS_SHAPES, physicsClientId=self.client,
        )

    def create_marker(self, position: np.ndarray, radius: float, rgba: tuple[float, float, float, float]) -> int:
        """A ghost sphere (visual only, no collision) used to show targets."""
        visual = self._p.createVisualShape(
            self._p.GEOM_SPHERE, radius=radius, rgbaColor=rgba, physicsClientId=self.client
        )
        return self._p.createMultiBody(
            baseVisualShapeIndex=visual, basePosition=list(position), physicsClientId=self.client
        )

    def create_table_top(self, radius: float, rgba: tuple[float, float, float, float]) -> int:
        """A flat visual-only disc on the floor that marks the shared table."""
        visual = self._p.createVisualShape(
            self._p.GEOM_CYLINDER, radius=radius, length=0.002, rgbaColor=rgba, physicsClientId=self.client
        )
        return self._p.createMultiBody(
            baseVisualShapeIndex=visual, basePosition=[0, 0, 0.001], physicsClientId=self.client
        )

    def move_marker(self, body: int, position: np.ndarray) -> None:
        """Teleport a marker body."""
        self._p.resetBasePositionAndOrientation(body, list(position), [0, 0, 0, 1], physicsClientId=self.client)

    def step(self) -> None:
        """Advance the physics by ``n_substeps`` steps."""
        for _ in range(self.n_substeps):
            self._p.stepSimulation(physicsClientId=self.client)

    def link_position(self, body: int, link: int) -> np.ndarray:
        """World position of a link frame (computed forward kinematics)."""
        state = self._p.getLinkState(body, link, computeForwardKinematics=True, physicsClientId=self.client)
        return np.array(state[4])

    def reset_joints(self, body: int, joints: list[int], angles: np.ndarray) -> None:
        """Teleport joints to ``angles`` with zero velocity."""
        for joint, angle in zip(joints, angles):
            self._p.resetJointState(body, joint, float(angle), targetVelocity=0.0, physicsClientId=self.client)

    def movable_joints(self, body: int) -> list[int]:
        """Indices of the non-fixed joints, in the order pybullet's IK reports them."""
        n_joints = self._p.getNumJoints(body, physicsClientId=self.client)
        infos = (self._p.getJointInfo(body, j, physicsClientId=self.client) for j in range(n_joints))
        return [info[0] for info in infos if info[2] != self._p.JOINT_FIXED]

    def joint_angles(self, body: int, joints: list[int]) -> np.ndarray:
        """Current joint angles."""
        return np.array([state[0] for state in self._p.getJointStates(body, joints, physicsClientId=self.client)])

    def control_joints(self, body: int, joints: list[int], targets: np.ndarray, forces: np.ndarray) -> None:
        """Position-control ``joints`` toward ``targets`` with per-joint force limits."""
        self._p.setJointMotorControlArray(
            body, joints, self._p.POSITION_CONTROL, targetPositions=list(targets), forces=list(forces),
            physicsClientId=self.client,
        )

    def inverse_kinematics(
        self, body: int, link: int, position: np.ndarray, rest_pose: np.ndarray, limits: tuple[np.ndarray, np.ndarray],
        iterations: int = 20,
    ) -> np.ndarray:
        """Position-only IK with null-space rest pose; returns joint angles."""
        lower, upper = limits
        return np.array(
            self._p.calculateInverseKinematics(
                body, link, list(position), lowerLimits=list(lower), upperLimits=list(upper),
                jointRanges=list(upper - lower), restPoses=list(rest_pose), maxNumIterations=iterations,
                residualThreshold=1e-4, physicsClientId=self.client,
            )
        )

    def joint_limits(self, body: int, joints: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper joint limits from the URDF."""
        infos = [self._p.getJointInfo(body, j, physicsClientId=self.client) for j in joints]
        return np.array([i[8] for i in infos]), np.array([i[9] for i in infos])

    def link_mass(self, body: int, link: int) -> float:
        """Mass (kg) of a link."""
        return float(self._p.getDynamicsInfo(body, link, physicsClientId=self.client)[0])

    def set_joint_damping(self, body: int, joint: int, damping: float) -> None:
        """Change the viscous damping of a joint."""
        self._p.changeDynamics(body, joint, jointDamping=float(damping), physicsClientId=self.client)

    def set_link_mass(self, body: int, link: int, mass: float) -> None:
        """Change the mass (kg) of a link."""
        self._p.changeDynamics(body, link, mass=float(mass), physicsClientId=self.client)

    def contact_count(self, body_a: int, body_b: int) -> int:
        """Number of contact points between two bodies after the last step."""
        return len(self._p.getContactPoints(body_a, body_b, physicsClientId=self.client))

    def closest_points_count(self, body_a: int, body_b: int, distance: float) -> int:
        """Number of point pairs between two bodies closer than ``distance`` (slow: use only for safety margins)."""
        return len(self._p.getClosestPoints(body_a, body_b, distance, physicsClientId=self.client))

    def render(
        self, width: int, height: int, target: np.ndarray, distance: float, yaw: float, pitch: float
    ) -> np.ndarray:
        """An RGB frame (height, width, 3) uint8 from an orbit camera, TinyRenderer in DIRECT mode."""
        view = self._p.computeViewMatrixFromYawPitchRoll(
            list(target), distance, yaw, pitch, 0, 2, physicsClientId=self.client
        )
        proj = self._p.computeProjectionMatrixFOV(60, width / height, 0.05, 10.0, physicsClientId=self.client)
        _, _, rgba, _, _ = self._p.getCameraImage(
            width, height, view, proj, renderer=self._p.ER_TINY_RENDERER, shadow=0, physicsClientId=self.client,
        )
        return np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[:, :, :3].copy()

    def close(self) -> None:
        """Disconnect; safe to call twice."""
        self._finalizer()
        self.client = -1


def _disconnect(client: int) -> None:
    p = pybullet()
    try:
        p.disconnect(physicsClientId=client)
    except p.error:
        pass
