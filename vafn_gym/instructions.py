"""The instruction format: an immutable ordered sequence of waypoints, each naming an arm and, optionally, a target.

This module is the single definition of that format; every producer (parser, task sampler, multimedia generator) and
every consumer (queue, environment, controllers) goes through :class:`Instruction`.

The format knows nothing about a particular arm layout: arm ids are integers >= 1 and a waypoint without a target
(``target=None``) leaves the target to the environment (its arm's default target, or a hidden per-arm target). Every
constructor takes an optional ``n_arms`` keyword that rejects arms above a layout's count, and
:meth:`Instruction.check_arms` validates an existing instruction against a layout.

Malformed input of any kind (wrong types, bad numbers, overflowing floats, deep nesting, huge or badly encoded text)
raises ``ValueError`` only, with a message of bounded length that names the problem.
"""

from __future__ import annotations

import itertools
import json
import math
import re
import reprlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

import numpy as np

from vafn_gym.constants import DIFFICULTY_LENGTHS, MAX_INSTRUCTION_LENGTH, WORKSPACE_HIGH, WORKSPACE_LOW

__all__ = ["Instruction", "Waypoint", "difficulty_of", "brief_repr", "MAX_ARM_ID", "MAX_TEXT_LENGTH"]

#: Largest arm id any instruction may name: a sanity bound far above any layout, so that ids stay small numbers.
MAX_ARM_ID: int = 1024
#: Longest instruction text (code or JSON, in characters) the parsers read; anything longer is rejected unread.
MAX_TEXT_LENGTH: int = 65_536
#: Longest value repr quoted in an error message.
REPR_LIMIT: int = 60

_WAYPOINT_KEYS = frozenset({"arm", "target"})
_DOCUMENT_KEYS = frozenset({"waypoints"})
_INTEGER_TOKEN = re.compile(r"[+-]?[0-9]{1,12}")
_DIGITS = re.compile(r"[0-9]+")
_LIST_SEPARATORS = re.compile(r"[,;]")
_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = _REPR.maxlong = REPR_LIMIT


def brief_repr(value: Any, limit: int = REPR_LIMIT) -> str:
    """A repr of ``value`` cut to about ``limit`` characters, safe on any object (for error messages)."""
    try:
        text = _REPR.repr(value)
    except Exception:  # noqa: BLE001 - a huge int (str() limit), a broken __repr__, ...: describe the type only
        text = f"<{type(value).__name__} object>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def difficulty_of(length: int) -> str:
    """Paper difficulty bucket ("easy", "medium" or "hard") of an instruction with ``length`` waypoints."""
    for name, (low, high) in DIFFICULTY_LENGTHS.items():
        if low <= length <= high:
            return name
    raise ValueError(f"instruction length {brief_repr(length)} is outside 0..{MAX_INSTRUCTION_LENGTH}")


@contextmanager
def _only_value_errors(what: str) -> Iterator[None]:
    """Turn any other exception escaping the block into a ValueError, so malformed input never raises anything else."""
    try:
        yield
    except ValueError:
        raise
    except MemoryError:
        raise
    except RecursionError:
        raise ValueError(f"{what}: input is nested too deeply") from None
    except Exception as error:
        raise ValueError(f"{what}: {type(error).__name__}: {brief_repr(str(error))}") from error


def _where(position: int | None) -> str:
    return "waypoint" if position is None else f"waypoint {position}"


def _check_n_arms(n_arms: Any) -> int | None:
    if n_arms is None:
        return None
    if isinstance(n_arms, bool) or not isinstance(n_arms, Integral) or not 1 <= n_arms <= MAX_ARM_ID:
        raise ValueError(f"n_arms must be None or an integer in 1..{MAX_ARM_ID}, got {brief_repr(n_arms)}")
    return int(n_arms)


def _allowed(n_arms: int | None) -> str:
    return f"1..{MAX_ARM_ID if n_arms is None else n_arms}"


def _check_arm(value: Any, position: int | None, n_arms: int | None = None) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Real):
        raise ValueError(f"{_where(position)}: arm {brief_repr(value)} is not an integer arm id")
    if not isinstance(value, Integral):
        number = float(value)
        if not number.is_integer():
            raise ValueError(f"{_where(position)}: arm {brief_repr(value)} is not an integer arm id")
        value = number
    if not 1 <= value <= (MAX_ARM_ID if n_arms is None else n_arms):
        raise ValueError(f"{_where(position)}: arm {brief_repr(value)} is outside the allowed range {_allowed(n_arms)}")
    return int(value)


def _check_coordinate(value: Any, position: int | None) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Real):
        raise ValueError(f"{_where(position)}: target coordinate {brief_repr(value)} is not a real number")
    try:
        number = float(value)
    except (OverflowError, TypeError, ValueError):
        number = math.inf
    if not math.isfinite(number):
        raise ValueError(f"{_where(position)}: target coordinate {brief_repr(value)} is not finite")
    return number


def _check_target(value: Any, position: int | None) -> tuple[float, float, float] | None:
    """Validate a target: ``None`` (the env decides) or an ordered triple of finite reals inside the workspace."""
    if value is None:
        return None
    if isinstance(value, np.ndarray):
        if value.ndim != 1:
            raise ValueError(f"{_where(position)}: target must have 3 coordinates, got an array of shape {value.shape}")
        value = value.tolist()
    elif isinstance(value, (str, bytes, bytearray)) or not isinstance(value, Sequence):
        raise ValueError(f"{_where(position)}: target {brief_repr(value)} is not a list of 3 coordinates")
    if len(value) != 3:
        raise ValueError(f"{_where(position)}: target must have 3 coordinates, got {len(value)}")
    target = tuple(_check_coordinate(coordinate, position) for coordinate in value)
    if any(c < low or c > high for c, low, high in zip(target, WORKSPACE_LOW.tolist(), WORKSPACE_HIGH.tolist())):
        raise ValueError(
            f"{_where(position)}: target {[round(c, 4) for c in target]} is outside the workspace "
            f"[{WORKSPACE_LOW.tolist()}, {WORKSPACE_HIGH.tolist()}]"
        )
    return target  # type: ignore[return-value]


def _ordered_items(values: Any, what: str) -> list[Any]:
    """The items of an ordered container (a sequence, a 1-D array or an iterator): at most MAX_INSTRUCTION_LENGTH.

    Sets, mappings and dict views are refused: their order is not the user's order.
    """
    if isinstance(values, np.ndarray):
        if values.ndim != 1:
            raise ValueError(f"{what} must be one-dimensional, got an array of shape {values.shape}")
        values = values.tolist()
    elif isinstance(values, (str, bytes, bytearray)) or not isinstance(values, (Sequence, Iterator)):
        raise ValueError(f"{what} must be an ordered sequence (list or tuple), got {brief_repr(values)}")
    limit = MAX_INSTRUCTION_LENGTH
    items = list(itertools.islice(values, limit + 1))
    if len(items) > limit:
        raise ValueError(f"{what}: more than {limit} given; an instruction has at most {limit} waypoints")
    return items


def _decode(text: str | bytes | bytearray, what: str) -> str:
    """Text as ASCII ``str``, bounded in length; ValueError for bad encoding, non-ASCII characters or huge input."""
    if len(text) > MAX_TEXT_LENGTH:
        raise ValueError(f"{what} is {len(text)} characters long; at most {MAX_TEXT_LENGTH} are allowed")
    if isinstance(text, (bytes, bytearray)):
        try:
            text = bytes(text).decode("ascii")
        except UnicodeDecodeError:
            raise ValueError(f"{what} {brief_repr(bytes(text))} is not ASCII text") from None
    if not text.isascii():
        raise ValueError(f"{what} {brief_repr(text)} contains non-ASCII characters (write arm ids as ASCII digits)")
    return text


@dataclass(frozen=True)
class Waypoint:
    """One step of an instruction: arm ``arm`` (an id >= 1) reaches ``target`` (world metres; ``None``: env decides)."""

    arm: int
    target: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        with _only_value_errors("waypoint"):
            object.__setattr__(self, "arm", _check_arm(self.arm, None))
            object.__setattr__(self, "target", _check_target(self.target, None))

    @property
    def has_target(self) -> bool:
        """Whether the waypoint carries an explicit target (``False``: the environment decides)."""
        return self.target is not None

    @property
    def target_array(self) -> np.ndarray:
        """The explicit target as a fresh float64 array; ``ValueError`` when the target is left to the environment."""
        if self.target is None:
            raise ValueError(f"waypoint for arm {self.arm} has no explicit target (the environment decides it)")
        return np.array(self.target, dtype=np.float64)


class Instruction(Sequence[Waypoint]):
    """An immutable, validated, ordered sequence of 0..MAX_INSTRUCTION_LENGTH waypoints.

    :param waypoints: the waypoints, in execution order (an ordered container or an iterator of :class:`Waypoint`).
    """

    __slots__ = ("_waypoints",)

    def __init__(self, waypoints: Iterable[Waypoint] = ()) -> None:
        with _only_value_errors("instruction"):
            items = _ordered_items(waypoints, "waypoints")
        for position, item in enumerate(items):
            if not isinstance(item, Waypoint):
                raise ValueError(f"waypoint {position}: expected a Waypoint, got {type(item).__name__}")
        self._waypoints: tuple[Waypoint, ...] = tuple(items)

    # --- constructors ---
    @classmethod
    def from_arms(cls, arms: Iterable[Any], targets: Iterable[Any] | None = None, *,
                  n_arms: int | None = None) -> Instruction:
        """Build from arm ids (``[2, 3, 1]``) and optional per-waypoint targets (``None``: the env decides).

        :param arms: the arm ids, in order (a list, tuple, 1-D array or iterator; not a set).
        :param targets: one target (3 coordinates, or ``None``) per arm, or ``None`` for no explicit targets.
        :param n_arms: when given, arm ids above it are rejected.
        """
        with _only_value_errors("cannot build an instruction"):
            return cls._from_arms(arms, targets, _check_n_arms(n_arms))

    @classmethod
    def _from_arms(cls, arms: Any, targets: Any, n_arms: int | None) -> Instruction:
        if isinstance(arms, (str, bytes, bytearray)):
            raise ValueError("from_arms expects a sequence of integers; use Instruction.parse for strings")
        if isinstance(arms, Mapping) or not isinstance(arms, (Sequence, Iterator, np.ndarray)):
            raise ValueError(
                f"cannot interpret {brief_repr(arms)} as an instruction: expected an ordered list of arm ids"
            )
        arm_ids = [_check_arm(value, position, n_arms) for position, value in enumerate(_ordered_items(arms, "arms"))]
        if targets is None:
            target_list: list[Any] = [None] * len(arm_ids)
        else:
            if isinstance(targets, Real):
                raise ValueError(f"targets {brief_repr(targets)} are not a sequence of 3-D points")
            target_list = _ordered_items(targets, "targets")
            if len(target_list) != len(arm_ids):
                raise ValueError(f"{len(arm_ids)} arms but {len(target_list)} targets")
        waypoints = []
        for position, (arm, target) in enumerate(zip(arm_ids, target_list)):
            waypoints.append(Waypoint(arm, _check_target(target, position)))
        return cls(waypoints)

    @classmethod
    def parse(cls, text: str, allow_empty: bool = True, *, n_arms: int | None = None) -> Instruction:
        """Parse machine code: ``"2,3,1"``, ``"2 3 1"``, ``"[2, 3, 1]"``, ``"<2,3,1>"``, ``"231"`` or a JSON document.

        Only ASCII is accepted; empty tokens (``"2,,3"``, a trailing comma) are errors.

        :param text: the code to parse.
        :param allow_empty: whether an empty (or blank) string means the empty instruction.
        :param n_arms: when given, arm ids above it are rejected.
        """
        if not isinstance(text, str):
            raise ValueError(f"expected a string, got {type(text).__name__}")
        with _only_value_errors("cannot parse instruction"):
            return cls._parse(_decode(text, "instruction text"), allow_empty, _check_n_arms(n_arms))

    @classmethod
    def _parse(cls, text: str, allow_empty: bool, n_arms: int | None) -> Instruction:
        stripped = text.strip()
        if stripped.startswith("{") or (stripped.startswith("[") and ("{" in stripped or "[" in stripped[1:])):
            return cls._from_json(stripped, n_arms)
        body = stripped
        if body.startswith("[") or body.startswith("<"):
            closing = {"[": "]", "<": ">"}[body[0]]
            if not body.endswith(closing):
                raise ValueError(f"unbalanced bracket in instruction {brief_repr(text)}")
            body = body[1:-1].strip()
        if not body:
            if allow_empty:
                return cls()
            raise ValueError("empty instruction string")
        arms = [_token_arm(token, position, text) for position, token in enumerate(_tokens(body, text))]
        return cls._from_arms(arms, None, n_arms)

    @classmethod
    def from_json(cls, document: str | bytes | dict | list, *, n_arms: int | None = None) -> Instruction:
        """Build from JSON: ``[2, 3]``, ``{"waypoints": [{"arm": 2, "target": [x, y, z]}, ...]}`` or a list of such.

        A waypoint object has an ``"arm"`` and an optional ``"target"`` (missing or ``null``: the env decides); any
        other key is an error, and so is any key but ``"waypoints"`` in the outer object.

        :param document: JSON text (ASCII), or the already-decoded list or dict.
        :param n_arms: when given, arm ids above it are rejected.
        """
        with _only_value_errors("invalid instruction JSON"):
            return cls._from_json(document, _check_n_arms(n_arms))

    @classmethod
    def _from_json(cls, document: Any, n_arms: int | None) -> Instruction:
        if isinstance(document, (str, bytes, bytearray)):
            text = _decode(document, "instruction JSON")
            try:
                document = json.loads(text)
            except json.JSONDecodeError as error:
                raise ValueError(f"invalid instruction JSON: {brief_repr(str(error), 120)}") from None
        if isinstance(document, Mapping):
            _check_keys(document, _DOCUMENT_KEYS, "instruction JSON object", required="waypoints")
            document = document["waypoints"]
        if not isinstance(document, (list, tuple)):
            raise ValueError(f"instruction JSON must be a list or an object, got {type(document).__name__}")
        if all(not isinstance(item, Mapping) for item in document):
            return cls._from_arms(document, None, n_arms)
        items = _ordered_items(document, "waypoints")
        arms, targets = [], []
        for position, item in enumerate(items):
            if not isinstance(item, Mapping):
                raise ValueError(f"waypoint {position}: expected an object with an 'arm' key, got {brief_repr(item)}")
            _check_keys(item, _WAYPOINT_KEYS, f"waypoint {position}", required="arm")
            arms.append(item["arm"])
            targets.append(item.get("target"))
        return cls._from_arms(arms, targets, n_arms)

    @classmethod
    def coerce(cls, value: Instruction | str | bytes | Iterable[Any], *, n_arms: int | None = None) -> Instruction:
        """Turn any accepted representation (an Instruction, machine code, JSON, a list of arm ids) into an Instruction.

        :param value: the representation; an :class:`Instruction` is returned as it is (after the ``n_arms`` check).
        :param n_arms: when given, arm ids above it are rejected.
        """
        with _only_value_errors("cannot interpret instruction"):
            limit = _check_n_arms(n_arms)
            if isinstance(value, Instruction):
                if limit is not None:
                    value.check_arms(limit)
                return value
            if isinstance(value, (str, bytes, bytearray)):
                return cls._parse(_decode(value, "instruction text"), True, limit)
            if isinstance(value, Mapping):
                return cls._from_json(value, limit)
            return cls._from_arms(value, None, limit)

    # --- validation against a layout ---
    def check_arms(self, n_arms: int) -> None:
        """Raise ``ValueError`` naming the first waypoint whose arm is not in ``1..n_arms``.

        :param n_arms: the number of arms of the layout the instruction is meant for.
        """
        limit = _check_n_arms(n_arms)
        if limit is None:
            raise ValueError("n_arms must be an integer >= 1, got None")
        for position, waypoint in enumerate(self._waypoints):
            if waypoint.arm > limit:
                raise ValueError(f"waypoint {position}: arm {waypoint.arm} is outside the allowed range 1..{limit}")

    # --- views ---
    @property
    def arms(self) -> tuple[int, ...]:
        """The arm order (``(2, 3, 1)``)."""
        return tuple(w.arm for w in self._waypoints)

    @property
    def targets(self) -> np.ndarray:
        """Targets as an (M, 3) float64 array; ``ValueError`` unless every waypoint has an explicit target.

        Use :meth:`with_default_targets` first to fill in the targets left to the environment.
        """
        missing = [position for position, w in enumerate(self._waypoints) if w.target is None]
        if missing:
            raise ValueError(f"waypoints {missing} have no explicit target; use with_default_targets(...) first")
        return np.array([w.target for w in self._waypoints], dtype=np.float64).reshape(len(self), 3)

    @property
    def difficulty(self) -> str:
        """Paper difficulty bucket: easy (0–3 waypoints), medium (4–6) or hard (7–10)."""
        return difficulty_of(len(self))

    @property
    def has_default_targets(self) -> bool:
        """Whether no waypoint has an explicit target (the environment decides every target)."""
        return all(w.target is None for w in self._waypoints)

    def with_default_targets(self, default_target: Callable[[int], Any]) -> Instruction:
        """A copy in which every waypoint without an explicit target gets ``default_target(arm)``.

        :param default_target: maps an arm id to its target (e.g. a layout's default target).
        """
        return Instruction(
            w if w.target is not None else Waypoint(w.arm, _check_target(default_target(w.arm), position))
            for position, w in enumerate(self._waypoints)
        )

    def to_code(self) -> str:
        """Machine-code form, e.g. ``"2,3,1"`` (arms only: explicit targets are not part of the code)."""
        return ",".join(str(arm) for arm in self.arms)

    def to_json(self) -> str:
        """JSON form that round-trips through :meth:`from_json`; a waypoint without an explicit target omits it."""
        return json.dumps({"waypoints": [_waypoint_json(w) for w in self._waypoints]})

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


def _waypoint_json(waypoint: Waypoint) -> dict[str, Any]:
    if waypoint.target is None:
        return {"arm": waypoint.arm}
    return {"arm": waypoint.arm, "target": list(waypoint.target)}


def _check_keys(document: Mapping, allowed: frozenset[str], what: str, required: str) -> None:
    unknown = [key for key in document if key not in allowed]
    if unknown:
        raise ValueError(f"{what}: unknown key {brief_repr(unknown[0])} (allowed: {sorted(allowed)})")
    if required not in document:
        raise ValueError(f"{what} needs a {required!r} key")


def _tokens(body: str, text: str) -> list[str]:
    """Split code into arm tokens: on commas/semicolons (no empty token allowed), else on whitespace."""
    if _LIST_SEPARATORS.search(body):
        tokens = [token.strip() for token in _LIST_SEPARATORS.split(body)]
        for position, token in enumerate(tokens):
            if not token:
                raise ValueError(f"token {position} in {brief_repr(text)} is empty (stray separator)")
        return tokens
    tokens = body.split()
    if len(tokens) == 1 and len(tokens[0]) > 1 and _DIGITS.fullmatch(tokens[0]):
        return list(tokens[0])  # compact form "231"
    return tokens


def _token_arm(token: str, position: int, text: str) -> int:
    if not _INTEGER_TOKEN.fullmatch(token):
        raise ValueError(f"token {position} ({brief_repr(token)}) in {brief_repr(text)} is not an integer arm id")
    return int(token)
