"""Instruction parsing, validation and difficulty."""

import json

import numpy as np
import pytest

from vafn_gym import Instruction, Waypoint
from vafn_gym.constants import MAX_INSTRUCTION_LENGTH, WORKSPACE_HIGH, default_target


@pytest.mark.parametrize("text", ["2,3,1", "2 3 1", "[2, 3, 1]", "231", " 2;3;1 ", "<2,3,1>", "[2,3,1]"])
def test_parse_forms(text):
    assert Instruction.parse(text).arms == (2, 3, 1)


def test_from_list_json_and_round_trip():
    instruction = Instruction.from_arms([2, 3, 1, 3])
    assert instruction.arms == (2, 3, 1, 3)
    assert np.allclose(instruction.targets[0], default_target(2))
    assert Instruction.from_json(instruction.to_json()) == instruction
    assert Instruction.from_json("[1, 2]").arms == (1, 2)
    assert Instruction.parse(instruction.to_code()) == instruction


def test_explicit_targets():
    targets = [[0.0, 0.0, 0.3], [0.1, 0.0, 0.25]]
    instruction = Instruction.from_arms([1, 2], targets)
    assert np.allclose(instruction.targets, targets)
    assert not instruction.has_default_targets
    document = json.dumps({"waypoints": [{"arm": 3, "target": [0.0, 0.1, 0.3]}, {"arm": 1}]})
    parsed = Instruction.from_json(document)
    assert parsed.arms == (3, 1) and np.allclose(parsed.targets[1], default_target(1))


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("2,4", "waypoint 1: arm 4"),
        ("0,1", "waypoint 0: arm 0"),
        ("1,a", "token 1 ('a')"),
        ("1.5", "token 0 ('1.5')"),
        ("[1,2", "unbalanced"),
        (",".join(["1", "2"] * 6), "at most 10"),
        ("{bad json", "invalid instruction JSON"),
    ],
)
def test_bad_strings_name_the_problem(text, fragment):
    with pytest.raises(ValueError, match=None) as error:
        Instruction.parse(text)
    assert fragment in str(error.value)


def test_empty_string_policy():
    assert len(Instruction.parse("")) == 0
    assert len(Instruction.parse("[]")) == 0
    with pytest.raises(ValueError, match="empty"):
        Instruction.parse("  ", allow_empty=False)


@pytest.mark.parametrize(
    "target, fragment",
    [([np.nan, 0, 0.3], "not finite"), ([0, np.inf, 0.3], "not finite"), ([5.0, 0, 0.3], "outside the workspace"),
     ([0, 0], "3 coordinates"), (["x", 0, 0], "not numeric")],
)
def test_bad_targets(target, fragment):
    with pytest.raises(ValueError) as error:
        Instruction.from_arms([1], [target])
    assert fragment in str(error.value)


def test_bad_list_items():
    with pytest.raises(ValueError, match="waypoint 1: arm 2.5"):
        Instruction.from_arms([1, 2.5])
    with pytest.raises(ValueError, match="waypoint 0"):
        Instruction.from_arms([True])
    with pytest.raises(ValueError, match="2 arms but 1 targets"):
        Instruction.from_arms([1, 2], [[0, 0, 0.3]])
    assert Instruction.from_arms([1.0, 2.0]).arms == (1, 2)


@pytest.mark.parametrize("length, difficulty", [(0, "easy"), (3, "easy"), (4, "medium"), (6, "medium"), (7, "hard"), (10, "hard")])
def test_difficulty(length, difficulty):
    assert Instruction.from_arms([1 + i % 3 for i in range(length)]).difficulty == difficulty


def test_immutable_and_hashable():
    instruction = Instruction.parse("1,2,3")
    with pytest.raises(AttributeError):
        instruction[0].arm = 3  # type: ignore[misc]
    assert len({instruction, Instruction.parse("[1, 2, 3]")}) == 1
    assert instruction[1:].arms == (2, 3)
    assert isinstance(instruction[0], Waypoint)
    assert len(Instruction.from_arms([1] * MAX_INSTRUCTION_LENGTH)) == MAX_INSTRUCTION_LENGTH
    with pytest.raises(ValueError):
        Waypoint(1, tuple(WORKSPACE_HIGH + 1))


@pytest.mark.parametrize("value", [None, 5, 2.5])
def test_coerce_rejects_non_instructions_with_value_error(value):
    with pytest.raises(ValueError, match="cannot interpret"):
        Instruction.coerce(value)
    with pytest.raises(ValueError, match="not a sequence of 3-D points"):
        Instruction.from_arms([1], targets=7)


def test_coerce():
    instruction = Instruction.parse("3,2")
    assert Instruction.coerce(instruction) is instruction
    assert Instruction.coerce("3 2") == instruction == Instruction.coerce([3, 2]) == Instruction.coerce(b"3,2")
