"""ArmLayout: where N arms stand, where they rest, their default targets, and their slices of the joint spaces."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vafn_gym.constants import ACTION_PER_ARM, WORKSPACE_HIGH, WORKSPACE_LOW
from vafn_gym.robots import RobotSpec

#: Arms a layout may hold (bases closer than MIN_BASE_SPACING make the circle infeasible well before this).
MAX_ARMS: int = 8
#: Two neighbouring bases must be at least this far apart (metres): the arms' links would overlap otherwise.
MIN_BASE_SPACING: float = 0.35
#: Two waiting arms' home points must be at least this far apart (metres).
MIN_HOME_SPACING: float = 0.2
#: Frames an env can observe positions and take velocities in: the table's ("world") or each arm's own ("base").
FRAMES: tuple[str, ...] = ("world", "base")
_PALETTE = (
    (0.9, 0.2, 0.2), (0.2, 0.7, 0.2), (0.2, 0.3, 0.9), (0.9, 0.7, 0.1),
    (0.6, 0.2, 0.8), (0.1, 0.7, 0.8), (0.9, 0.4, 0.6), (0.5, 0.5, 0.5),
)


@dataclass(frozen=True)
class ArmLayout:
    """N arms on a circle around the table centre, each facing it; arm ids are 1..N as users say them.

    :param n_arms: number of arms (2..MAX_ARMS).
    :param base_radius: radius of the circle the bases stand on.
    :param base_yaw0: angle of arm 1's base on the circle; arm k sits at ``base_yaw0 + (k-1)*2*pi/n_arms``.
    :param home_forward: the rest point lies this far in front of the base (toward the centre).
    :param home_height: height of the rest point.
    :param default_target_offset: default target: this far from the centre, toward the arm's base.
    :param default_target_height: height of the default targets.
    :param shared_radius: radius of the shared region (a vertical cylinder around the centre) hidden targets come from.
    :param shared_z_range: height range of the shared region.
    """

    n_arms: int = 3
    base_radius: float = 0.6
    base_yaw0: float = 0.0
    home_forward: float = 0.25
    home_height: float = 0.55
    default_target_offset: float = 0.08
    default_target_height: float = 0.3
    shared_radius: float = 0.15
    shared_z_range: tuple[float, float] = (0.2, 0.45)

    def __post_init__(self) -> None:
        if isinstance(self.n_arms, bool) or not isinstance(self.n_arms, (int, np.integer)):
            raise TypeError(f"n_arms must be an integer, got {type(self.n_arms).__name__}")
        if not 2 <= self.n_arms <= MAX_ARMS:
            raise ValueError(f"n_arms must be between 2 and {MAX_ARMS}, got {self.n_arms}")
        for name in ("base_radius", "home_forward", "home_height", "default_target_height", "shared_radius"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        low, high = self.shared_z_range
        if not (np.isfinite(low) and np.isfinite(high) and 0 < low <= high):
            raise ValueError(f"shared_z_range must be 0 < low <= high, got {self.shared_z_range!r}")

    # --- ids and slices ---
    @property
    def arm_ids(self) -> tuple[int, ...]:
        """Arm ids as users say them: 1..n_arms."""
        return tuple(range(1, self.n_arms + 1))

    @property
    def arm_pairs(self) -> tuple[tuple[int, int], ...]:
        """Every unordered pair of arm ids (the pairs checked for contacts)."""
        return tuple((a, b) for a in self.arm_ids for b in self.arm_ids if a < b)

    @property
    def action_dim(self) -> int:
        """Size of the joint action: 3 end-effector velocity components per arm."""
        return ACTION_PER_ARM * self.n_arms

    def action_slice(self, arm: int) -> slice:
        """Slice of the joint action that belongs to ``arm``."""
        return self.block_slice(arm, ACTION_PER_ARM)

    @staticmethod
    def block_slice(arm: int, per_arm: int) -> slice:
        """Slice of a joint vector made of ``per_arm``-sized blocks that belongs to ``arm``."""
        return slice((arm - 1) * per_arm, arm * per_arm)

    # --- geometry ---
    def base_yaw(self, arm: int) -> float:
        """Angle (radians) of ``arm``'s base position on the circle."""
        return self.base_yaw0 + (arm - 1) * 2.0 * np.pi / self.n_arms

    def _toward_centre(self, arm: int, distance_from_centre: float, height: float) -> np.ndarray:
        yaw = self.base_yaw(arm)
        return np.array([distance_from_centre * np.cos(yaw), distance_from_centre * np.sin(yaw), height])

    def base_position(self, arm: int) -> np.ndarray:
        """World position of ``arm``'s base."""
        return self._toward_centre(arm, self.base_radius, 0.0)

    def _heading(self, arm: int) -> np.ndarray:
        """Rotation from ``arm``'s base frame to the world: its x axis points from the base to the table centre."""
        heading = self.base_yaw(arm) + np.pi
        cos, sin = np.cos(heading), np.sin(heading)
        return np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]])

    def to_base_frame(self, arm: int, point: np.ndarray) -> np.ndarray:
        """A world point in ``arm``'s base frame (origin at its base, x toward the table centre, z up)."""
        return self._heading(arm).T @ (np.asarray(point, dtype=np.float64) - self.base_position(arm))

    def base_to_world_vector(self, arm: int, vector: np.ndarray) -> np.ndarray:
        """A direction (e.g. a velocity) given in ``arm``'s base frame, expressed in the world frame."""
        return self._heading(arm) @ np.asarray(vector, dtype=np.float64)

    def home_point(self, arm: int) -> np.ndarray:
        """Nominal rest end-effector point of ``arm``, clear of the shared region."""
        return self._toward_centre(arm, self.base_radius - self.home_forward, self.home_height)

    def default_target(self, arm: int) -> np.ndarray:
        """``arm``'s target when an instruction gives none (a point of the shared region offset toward the arm)."""
        return self._toward_centre(arm, self.default_target_offset, self.default_target_height)

    def sample_shared_target(self, rng: np.random.Generator) -> np.ndarray:
        """A point drawn uniformly from the shared region."""
        radius = self.shared_radius * np.sqrt(rng.uniform())
        angle = rng.uniform(0.0, 2.0 * np.pi)
        return np.array([radius * np.cos(angle), radius * np.sin(angle), rng.uniform(*self.shared_z_range)])

    def colour(self, arm: int, alpha: float = 0.8) -> tuple[float, float, float, float]:
        """RGBA colour of ``arm`` (markers, plots)."""
        return (*_PALETTE[(arm - 1) % len(_PALETTE)], alpha)

    # --- feasibility ---
    def check_feasible(self, robot: RobotSpec) -> None:
        """Raise ``ValueError`` naming the problem when ``robot`` arms cannot solve tasks on this layout."""
        spacing = 2.0 * self.base_radius * np.sin(np.pi / self.n_arms)
        if spacing < MIN_BASE_SPACING:
            raise ValueError(
                f"{self.n_arms} arms on a {self.base_radius} m circle stand {spacing:.2f} m apart "
                f"(< {MIN_BASE_SPACING} m): increase base_radius"
            )
        home_spacing = 2.0 * (self.base_radius - self.home_forward) * np.sin(np.pi / self.n_arms)
        if home_spacing < MIN_HOME_SPACING:
            raise ValueError(f"home points {home_spacing:.2f} m apart (< {MIN_HOME_SPACING} m): increase base_radius")
        farthest = self.base_radius + self.shared_radius
        if farthest > robot.reach:
            raise ValueError(
                f"{robot.name} reaches {robot.reach} m but the far side of the shared region is {farthest:.2f} m from "
                f"its base: decrease base_radius or shared_radius"
            )
        for arm in self.arm_ids:
            for point in (self.home_point(arm), self.default_target(arm)):
                if np.any(point < WORKSPACE_LOW) or np.any(point > WORKSPACE_HIGH):
                    raise ValueError(
                        f"arm {arm}'s home or default target {point.round(3).tolist()} leaves the workspace"
                    )
