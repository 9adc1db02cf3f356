"""The instruction format: an immutable ordered sequence of waypoints, each naming an arm and a target.

This module is the single definition of that format; every producer (parser, task sampler, multimedia generator) and
every consumer (queue, environment, controllers) goes through :class:`Instruction`.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from typing import Any, Iterable, Iterator, Sequence

import numpy as np

from vafn_gym.constants import (
    ARM_IDS,
    DIFFICULTY_LENGTHS,
    MAX_INSTRUCTION_LENGTH,
    WORKSPACE_HIGH,
    WORKSPACE_LOW,
    default_target,
)

_SEPARATORS = re.compile(r"[\s,;]+")


def difficulty_of(length: int) -> str:
    """Paper difficulty bucket ("easy", "medium" or "hard") of an instruction with ``length`` waypoints."""
    for name, (low, high) in DIFFICULTY_LENGTHS.items():
        if low <= length <= high:
            return name
    raise ValueError(f"instruction length {length} is outside 0..{MAX_INSTRUCTION_LENGTH}")


def _check_arm(value: Any, position: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        if isinstance(value, (float, np.floating)) and float(value).is_integer():
            value = int(value)
        else:
            raise ValueError(f"waypoint {position}: arm {value!r} is not an integer arm id in {list(ARM_IDS)}")
    if int(value) not in ARM_IDS:
        raise ValueError(f"waypoint {position}: arm {int(value)} is not one of {list(ARM_IDS)}")
    return int(value)


def _check_target(value: Any, position: int) -> tuple[float, float, float]:
    try:
        target = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"waypoint {position}: target {value!r} is not numeric") from error
    if target.shape != (3,):
        raise ValueError(f"waypoint {position}: target must have 3 coordinates, got shape {target.shape}")
    if not np.all(np.isfinite(target)):
        raise ValueError(f"waypoint {position}: target {target.tolist()} is not finite")
    if np.any(target < WORKSPACE_LOW) or np.any(target > WORKSPACE_HIGH):
        raise ValueError(
            f"waypoint {position}: target {target.tolist()} is outside the workspace "
            f"[{WORKSPACE_LOW.tolist()}, {WORKSPACE_HIGH.tolist()}]"
        )
    return (float(target[0]), float(target[1]), float(target[2]))


@dataclass(frozen=True)
class Waypoint:
    """One step of an instruction: arm ``arm`` (1-based) reaches ``target`` (world metres)."""

    arm: int
    target: tuple[float, float, float]

    def __post_init__(self) -> None:
        object.__setattr__(self, "arm", _check_arm(self.arm, 0))
        object.__setattr__(self, "target", _check_target(self.target, 0))

    @property
    def target_array(self) -> np.ndarray:
        """The target as a fresh float64 array."""
        return np.array(self.target)


class Instruction(Sequence[Waypoint]):
    """An immutable, validated, ordered sequence of 0..MAX_INSTRUCTION_LENGTH waypoints.

    :param waypoints: the waypoints, in execution order.
    """

    __slots__ = ("_waypoints",)

    def __init__(self, waypoints: Iterable[Waypoint] = ()) -> None:
        items = tuple(waypoints)
        if len(items) > MAX_INSTRUCTION_LENGTH:
            raise ValueError(f"instruction has {len(items)} waypoints; at most {MAX_INSTRUCTION_LENGTH} are allowed")
        for position, item in enumerate(items):
            if not isinstance(item, Waypoint):
                raise ValueError(f"waypoint {position}: expected a Waypoint, got {type(item).__name__}")
        self._waypoints: tuple[Waypoint, ...] = items

    # --- constructors ---
    @classmethod
    def from_arms(cls, arms: Iterable[Any], targets: Iterable[Any] | None = None) -> "Instruction":
        """Build from arm ids (``[2, 3, 1]``) and optional per-waypoint targets (default: each arm's default target)."""
        if isinstance(arms, (str, bytes)):
            raise ValueError("from_arms expects a sequence of integers; use Instruction.parse for strings")
        try:
            arm_list = list(arms)
        except TypeError:
            raise ValueError(f"cannot interpret {arms!r} as an instruction: expected a sequence of arm ids") from None
        if len(arm_list) > MAX_INSTRUCTION_LENGTH:
            raise ValueError(f"instruction has {len(arm_list)} waypoints; at most {MAX_INSTRUCTION_LENGTH} are allowed")
        arm_ids = [_check_arm(value, position) for position, value in enumerate(arm_list)]
        if targets is None:
            target_list = [default_target(arm) for arm in arm_ids]
        else:
            try:
                target_list = list(targets)
            except TypeError:
                raise ValueError(f"targets {targets!r} are not a sequence of 3-D points") from None
            if len(target_list) != len(arm_ids):
                raise ValueError(f"{len(arm_ids)} arms but {len(target_list)} targets")
        return cls(
            Waypoint(arm, _check_target(target, position))
            for position, (arm, target) in enumerate(zip(arm_ids, target_list))
        )

    @classmethod
    def parse(cls, text: str, allow_empty: bool = True) -> "Instruction":
        """Parse machine code: ``"2,3,1"``, ``"2 3 1"``, ``"[2, 3, 1]"``, ``"231"`` or a JSON document.

        :param text: the code to parse.
        :param allow_empty: whether an empty (or blank) string means the empty instruction.
        """
        if not isinstance(text, str):
            raise ValueError(f"expected a string, got {type(text).__name__}")
        stripped = text.strip()
        if stripped.startswith("{") or (stripped.startswith("[") and ("{" in stripped or "[" in stripped[1:])):
            return cls.from_json(stripped)
        body = stripped
        if body.startswith("[") or body.startswith("<"):
            closing = {"[": "]", "<": ">"}[body[0]]
            if not body.endswith(closing):
                raise ValueError(f"unbalanced bracket in instruction {text!r}")
            body = body[1:-1].strip()
        if not body:
            if allow_empty:
                return cls()
            raise ValueError("empty instruction string")
        tokens = [token for token in _SEPARATORS.split(body) if token]
        if len(tokens) == 1 and tokens[0].isdigit() and len(tokens[0]) > 1:
            tokens = list(tokens[0])  # compact form "231"
        arms = []
        for position, token in enumerate(tokens):
            if not re.fullmatch(r"[+-]?\d+", token):
                raise ValueError(f"token {position} ({token!r}) in {text!r} is not an integer arm id")
            arms.append(int(token))
        return cls.from_arms(arms)

    @classmethod
    def from_json(cls, document: str | bytes | dict | list) -> "Instruction":
        """Build from JSON: ``[2, 3]``, ``{"waypoints": [{"arm": 2, "target": [x, y, z]}, ...]}`` or a list of such."""
        if isinstance(document, (str, bytes)):
            try:
                document = json.loads(document)
            except json.JSONDecodeError as error:
                raise ValueError(f"invalid instruction JSON: {error}") from error
        if isinstance(document, dict):
            if "waypoints" not in document:
                raise ValueError("instruction JSON object needs a 'waypoints' key")
            document = document["waypoints"]
        if not isinstance(document, list):
            raise ValueError(f"instruction JSON must be a list or an object, got {type(document).__name__}")
        if all(not isinstance(item, dict) for item in document):
            return cls.from_arms(document)
        arms, targets = [], []
        for position, item in enumerate(document):
            if not isinstance(item, dict) or "arm" not in item:
                raise ValueError(f"waypoint {position}: expected an object with an 'arm' key, got {item!r}")
            arms.append(item["arm"])
            targets.append(item.get("target"))
        resolved = [default_target(_check_arm(arm, i)) if t is None else t for i, (arm, t) in enumerate(zip(arms, targets))]
        return cls.from_arms(arms, resolved)

    @classmethod
    def coerce(cls, value: "Instruction | str | Iterable[Any]") -> "Instruction":
        """Turn any accepted representation (an Instruction, machine code, a list of arm ids) into an Instruction."""
        if isinstance(value, Instruction):
            return value
        if isinstance(value, (str, bytes)):
            return cls.parse(value.decode() if isinstance(value, bytes) else value)
        if isinstance(value, dict):
            return cls.from_json(value)
        return cls.from_arms(value)

    # --- views ---
    @property
    def arms(self) -> tuple[int, ...]:
        """The arm order, 1-based (``(2, 3, 1)``)."""
        return tuple(w.arm for w in self._waypoints)

    @property
    def targets(self) -> np.ndarray:
        """Targets as an (M, 3) float64 array."""
        return np.array([w.target for w in self._waypoints], dtype=np.float64).reshape(len(self), 3)

    @property
    def difficulty(self) -> str:
        """Paper difficulty bucket: easy (0–3 waypoints), medium (4–6) or hard (7–10)."""
        return difficulty_of(len(self))

    @property
    def has_default_targets(self) -> bool:
        """Whether every waypoint uses its arm's default target."""
        return all(np.allclose(w.target, default_target(w.arm)) for w in self._waypoints)

    def to_code(self) -> str:
        """Machine-code form, e.g. ``"2,3,1"``."""
        return ",".join(str(arm) for arm in self.arms)

    def to_json(self) -> str:
        """JSON form that round-trips through :meth:`from_json`, targets included."""
        return json.dumps({"waypoints": [{"arm": w.arm, "target": list(w.target)} for w in self._waypoints]})

    def remaining_arms(self, index: int) -> set[int]:
        """Arms that still have a waypoint at or after position ``index``."""
        return {w.arm for w in self._waypoints[index:]}

    # --- Sequence protocol ---
    def __len__(self) -> int:
        return len(self._waypoints)

    def __getitem__(self, index):  # type: ignore[override]
        if isinstance(index, slice):
            return Instruction(self._waypoints[index])
        return self._waypoints[index]

    def __iter__(self) -> Iterator[Waypoint]:
        return iter(self._waypoints)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Instruction) and self._waypoints == other._waypoints

    def __hash__(self) -> int:
        return hash(self._waypoints)

    def __repr__(self) -> str:
        if self.has_default_targets:
            return f"Instruction([{self.to_code()}])"
        return f"Instruction({self.to_json()})"

    def __str__(self) -> str:
        return f"[{self.to_code()}]"

