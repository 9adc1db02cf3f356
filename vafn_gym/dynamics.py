"""Dynamics variants: how the arms respond to the policy's commands, and the fixed train / test family over them.

A :class:`Dynamics` changes *how to move*, not where to go: the commanded velocity is rotated (a base mounted at another
yaw than the controller assumes), scaled (a controller with another gain), capped (a slower controller), delayed
(actuation latency) and the end effector may carry a payload. The variant family :data:`DYNAMICS_FAMILY` is data, like
the instruction splits: fixed, versioned lists of train and test variants that never share a variant, so a meta-learner
trained on the train list is evaluated on variants it has never seen.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from vafn_gym.checks import check_int, check_number

#: Bounds a variant's fields are checked against (the family samples inside narrower ranges).
MAX_GAIN = 5.0
MAX_DELAY = 10
MAX_PAYLOAD = 10.0
MAX_SPEED = 10.0
#: Split names of the variant family (``dynamics="train"`` samples a train variant at every reset).
DYNAMICS_SPLITS = ("train", "test")


def turn_about_z(vectors: np.ndarray, degrees: float) -> np.ndarray:
    """``vectors`` (last axis x, y, z) turned counter-clockwise by ``degrees`` about the vertical axis."""
    angle = np.radians(degrees)
    cos, sin = np.cos(angle), np.sin(angle)
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    return np.stack([cos * x - sin * y, sin * x + cos * y, z], axis=-1)


@dataclass(frozen=True)
class Dynamics:
    """One dynamics variant of every arm (the nominal robot by default).

    :param action_gain: the commanded end-effector velocity is ``action_gain`` times the nominal one.
    :param action_delay: control steps between an action and its effect (the arm keeps executing older commands).
    :param action_rotation: yaw (degrees) by which the commanded velocity is turned about the vertical axis.
    :param speed_limit: cap on the commanded speed per axis (m/s); ``None`` leaves ``action_gain * V_MAX``.
    :param payload: extra mass (kg) at the end effector.
    """

    action_gain: float = 1.0
    action_delay: int = 0
    action_rotation: float = 0.0
    speed_limit: float | None = None
    payload: float = 0.0

    def __post_init__(self) -> None:
        check_number("action_gain", self.action_gain, 0.0, MAX_GAIN)
        check_int("action_delay", self.action_delay, 0, MAX_DELAY)
        check_number("action_rotation", self.action_rotation, -180.0, 180.0)
        if self.speed_limit is not None:
            check_number("speed_limit", self.speed_limit, 1e-3, MAX_SPEED)
        check_number("payload", self.payload, 0.0, MAX_PAYLOAD)

    @classmethod
    def coerce(cls, value: Any) -> Dynamics:
        """A :class:`Dynamics` from itself, ``None`` (nominal) or a dict of its fields (unknown keys are refused)."""
        if value is None:
            return cls()
        if isinstance(value, Dynamics):
            return value
        if isinstance(value, Mapping):
            unknown = sorted(set(value) - {f.name for f in fields(cls)})
            if unknown:
                raise ValueError(f"unknown dynamics field(s) {unknown}; known: {[f.name for f in fields(cls)]}")
            return cls(**value)
        raise TypeError(f"dynamics must be a Dynamics, a dict of its fields or None, got {type(value).__name__}")

    def as_dict(self) -> dict[str, Any]:
        """The fields as plain values (JSON-ready)."""
        return asdict(self)

    @property
    def label(self) -> str:
        """A short name for tables, e.g. ``"gain 1.6, delay 2, rot -60°"``."""
        parts = [f"gain {self.action_gain:.2g}", f"delay {self.action_delay}", f"rot {self.action_rotation:+.0f}°"]
        if self.speed_limit is not None:
            parts.append(f"≤{self.speed_limit:.2g} m/s")
        if self.payload:
            parts.append(f"{self.payload:.2g} kg")
        return ", ".join(parts)

    def velocity(self, velocity: np.ndarray) -> np.ndarray:
        """The velocity the arm executes for a commanded world-frame ``velocity`` (rotated, scaled, capped)."""
        moved = self.action_gain * turn_about_z(np.asarray(velocity, dtype=np.float64), self.action_rotation)
        if self.speed_limit is not None:
            moved = np.clip(moved, -self.speed_limit, self.speed_limit)
        return moved


NOMINAL = Dynamics()


@dataclass(frozen=True)
class DynamicsFamily:
    """Ranges of a dynamics family and a seeded sampler over them (the task-pool interface MAML-SAC reads).

    Gains are drawn log-uniformly, delays uniformly over integers, rotations uniformly; a quarter of the variants get a
    speed limit and a quarter a payload.
    """

    gain: tuple[float, float] = (0.4, 2.5)
    delay: tuple[int, int] = (0, 3)
    rotation: tuple[float, float] = (-150.0, 150.0)
    speed_limit: tuple[float, float] = (0.3, 0.8)
    payload: tuple[float, float] = (0.5, 2.0)

    def sample(self, rng: np.random.Generator) -> Dynamics:
        """One variant drawn with ``rng``."""
        gain = float(np.exp(rng.uniform(np.log(self.gain[0]), np.log(self.gain[1]))))
        return Dynamics(
            action_gain=round(gain, 3),
            action_delay=int(rng.integers(self.delay[0], self.delay[1] + 1)),
            action_rotation=round(float(rng.uniform(*self.rotation)), 1),
            speed_limit=round(float(rng.uniform(*self.speed_limit)), 3) if rng.random() < 0.25 else None,
            payload=round(float(rng.uniform(*self.payload)), 2) if rng.random() < 0.25 else 0.0,
        )

    def fixed_set(self, n: int, seed: int = 0) -> list[Dynamics]:
        """``n`` variants drawn with ``seed`` (the same list for the same arguments)."""
        rng = np.random.default_rng(seed)
        return [self.sample(rng) for _ in range(check_int("n", n, 0))]


#: Version of the variant lists below: change it whenever the family or the lists change.
DYNAMICS_VERSION = "dynamics-v1"
DYNAMICS_FAMILY = DynamicsFamily()
#: The variants meta-learners and domain randomisation train on, and the held-out variants they are evaluated on.
DYNAMICS_VARIANTS: dict[str, tuple[Dynamics, ...]] = {
    "train": tuple(DYNAMICS_FAMILY.fixed_set(40, seed=0)),
    "test": tuple(DYNAMICS_FAMILY.fixed_set(12, seed=1)),
}


class DynamicsSampler:
    """Draws variants of one split of :data:`DYNAMICS_VARIANTS` (what ``dynamics="train"`` samples each reset).

    :param split: "train" or "test".
    :param seed: seed of the draws.
    """

    def __init__(self, split: str = "train", seed: int | None = None) -> None:
        if split not in DYNAMICS_SPLITS:
            raise ValueError(f"dynamics split must be one of {list(DYNAMICS_SPLITS)}, got {split!r}")
        self.split = split
        self.variants = DYNAMICS_VARIANTS[split]
        self.rng = np.random.default_rng(seed)

    def seed(self, seed: int | None) -> None:
        """Reseed the draws."""
        self.rng = np.random.default_rng(seed)

    def sample(self) -> Dynamics:
        """One variant of the split."""
        return self.variants[int(self.rng.integers(len(self.variants)))]

    def fixed_set(self, n: int, seed: int = 0) -> list[Dynamics]:
        """The split's first ``n`` variants (all of them when ``n`` is larger); ``seed`` is unused (the list is
        fixed)."""
        return list(self.variants[: check_int("n", n, 0)])
