"""Instruction parsing, validation and difficulty."""

import json

import numpy as np
import pytest

from vafn_gym import Instruction, Waypoint
from vafn_gym.constants import MAX_INSTRUCTION_LENGTH, WORKSPACE_HIGH


@pytest.mark.parametrize("text", ["2,3,1", "2 3 1", "[2, 3, 1]", "231", " 2;3;1 ", "<2,3,1>", "[2,3,1]"])
def test_parse_forms(text):
    assert Instruction.parse(text).arms == (2, 3, 1)


def test_from_list_json_and_round_trip():
    instruction = Instruction.from_arms([2, 3, 1, 3])
    assert instruction.arms == (2, 3, 1, 3)
    assert instruction.has_default_targets and all(w.target is None and not w.has_target for w in instruction)
    assert json.loads(instruction.to_json()) == {"waypoints": [{"arm": a} for a in (2, 3, 1, 3)]}
    assert Instruction.from_json(instruction.to_json()) == instruction
    assert Instruction.from_json("[1, 2]").arms == (1, 2)
    assert Instruction.parse(instruction.to_code()) == instruction


def test_explicit_targets():
    targets = [[0.0, 0.0, 0.3], [0.1, 0.0, 0.25]]
    instruction = Instruction.from_arms([1, 2], targets)
    assert np.allclose(instruction.targets, targets)
    assert not instruction.has_default_targets
    assert Instruction.from_json(instruction.to_json()) == instruction
    document = json.dumps({"waypoints": [{"arm": 3, "target": [0.0, 0.1, 0.3]}, {"arm": 1, "target": None}]})
    parsed = Instruction.from_json(document)
    assert parsed.arms == (3, 1) and parsed[0].has_target and parsed[1].target is None
    assert not parsed.has_default_targets
    assert Instruction.from_json(parsed.to_json()) == parsed
    assert "target" not in json.loads(parsed.to_json())["waypoints"][1]
    assert repr(parsed).startswith("Instruction({") and repr(Instruction.parse("2,1")) == "Instruction([2,1])"
    mixed = Instruction.from_arms([1, 2, 3], [[0.0, 0.0, 0.3], None, (0.1, 0.0, 0.25)])
    assert [w.has_target for w in mixed] == [True, False, True]


def test_targets_left_to_the_environment():
    instruction = Instruction.parse("2,3")
    with pytest.raises(ValueError, match="no explicit target"):
        _ = instruction[0].target_array
    with pytest.raises(ValueError, match=r"waypoints \[0, 1\] have no explicit target"):
        _ = instruction.targets
    assert Instruction().targets.shape == (0, 3)
    resolved = instruction.with_default_targets(lambda arm: [0.0, 0.1 * arm, 0.3])
    assert np.allclose(resolved.targets, [[0.0, 0.2, 0.3], [0.0, 0.3, 0.3]])
    assert resolved.arms == instruction.arms and resolved != instruction
    assert np.allclose(resolved[1].target_array, [0.0, 0.3, 0.3])
    with pytest.raises(ValueError, match="outside the workspace"):
        instruction.with_default_targets(lambda arm: [9.0, 0.0, 0.3])
    assert Waypoint(2) == Waypoint(2, None) != Waypoint(2, (0.0, 0.0, 0.3))
    assert len({Waypoint(2), Waypoint(2, None)}) == 1


def test_arm_count_comes_from_the_caller():
    assert Instruction.parse("2,6,1").arms == (2, 6, 1)  # no global arm count
    for build in (lambda: Instruction.parse("2,4", n_arms=3), lambda: Instruction.from_arms([2, 4], n_arms=3),
                  lambda: Instruction.from_json("[2, 4]", n_arms=3), lambda: Instruction.coerce("2 4", n_arms=3),
                  lambda: Instruction.coerce(Instruction.parse("2,4"), n_arms=3),
                  lambda: Instruction.from_json({"waypoints": [{"arm": 2}, {"arm": 4}]}, n_arms=3)):
        with pytest.raises(ValueError, match=r"waypoint 1: arm 4 is outside the allowed range 1\.\.3"):
            build()
    assert Instruction.parse("2,4", n_arms=4).arms == (2, 4)
    Instruction.parse("6,1").check_arms(6)
    with pytest.raises(ValueError, match=r"waypoint 0: arm 6 .*1\.\.5"):
        Instruction.parse("6,1").check_arms(5)
    for bad in (0, -1, True, 2.0, "3", None):
        with pytest.raises(ValueError, match="n_arms"):
            Instruction.parse("1", n_arms=bad) if bad is not None else Instruction.parse("1").check_arms(bad)


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("0,1", "waypoint 0: arm 0"),
        ("1,-2", "waypoint 1: arm -2"),
        ("1,2000", "waypoint 1: arm 2000"),
        ("2,,,3", "token 1 in '2,,,3' is empty"),
        ("2,3,", "token 2"),
        (",1", "token 0"),
        ("２,３,１", "non-ASCII"),
        ("2 3,1", "token 0 ('2 3')"),
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
     ([0, 0], "3 coordinates"), (["x", 0, 0], "not a real number"), (["0", 0, 0.3], "not a real number"),
     ([True, 0, 0.3], "not a real number"), ([0, 0, 10**400], "not finite"), ({0, 0.1, 0.3}, "not a list"),
     ("0,0,0.3", "not a list"), (np.zeros((1, 3)), "shape (1, 3)"), ([[0, 0, 0.3]], "3 coordinates")],
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
    with pytest.raises(ValueError, match="waypoint 1: arm '2'"):
        Instruction.from_arms([1, "2"])
    with pytest.raises(ValueError, match="ordered"):
        Instruction.from_arms({1, 2})
    with pytest.raises(ValueError, match="ordered"):
        Instruction.from_arms({1: 0, 2: 0}.keys())
    assert Instruction.from_arms(iter([3, 1])).arms == (3, 1) == Instruction.from_arms(np.array([3, 1])).arms
    with pytest.raises(ValueError, match="2 arms but 1 targets"):
        Instruction.from_arms([1, 2], [[0, 0, 0.3]])
    assert Instruction.from_arms([1.0, 2.0]).arms == (1, 2)


@pytest.mark.parametrize(
    "length, difficulty", [(0, "easy"), (3, "easy"), (4, "medium"), (6, "medium"), (7, "hard"), (10, "hard")]
)
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
    with pytest.raises(ValueError, match="arm 0"):
        Waypoint(0)


@pytest.mark.parametrize("value", [None, 5, 2.5, {1, 2, 3}, frozenset([1]), {2: 1}.values(), object()])
def test_coerce_rejects_non_instructions_with_value_error(value):
    with pytest.raises(ValueError, match="cannot interpret"):
        Instruction.coerce(value)
    with pytest.raises(ValueError, match="not a sequence of 3-D points"):
        Instruction.from_arms([1], targets=7)


def test_coerce():
    instruction = Instruction.parse("3,2")
    assert Instruction.coerce(instruction) is instruction
    assert Instruction.coerce("3 2") == instruction == Instruction.coerce([3, 2]) == Instruction.coerce(b"3,2")
    assert Instruction.coerce({"waypoints": [{"arm": 3}, {"arm": 2}]}) == instruction


@pytest.mark.parametrize(
    "document, fragment",
    [('[{"arm": 2, "targt": [0, 0, 0.3]}]', "waypoint 0: unknown key 'targt'"),
     ('{"waypoints": [2], "extra": 1}', "unknown key 'extra'"),
     ('{"waypionts": [2]}', "unknown key 'waypionts'"),
     ('[{"arm": 1}, {"target": [0, 0, 0.3]}]', "waypoint 1 needs a 'arm' key"),
     ('[{"arm": 1}, 2]', "waypoint 1: expected an object"),
     ('[{"arm": true}]', "waypoint 0: arm True"),
     ('[{"arm": "2"}]', "waypoint 0: arm '2'"),
     ('[{"arm": 2, "target": [0, "0", 0.3]}]', "not a real number"),
     ('[{"arm": 2, "target": [0, 0, 1e400]}]', "not finite"),
     ('[{"arm": 2, "target": [0, 0, NaN]}]', "not finite"),
     ('"2,3"', "must be a list or an object"),
     ('[1, 2', "invalid instruction JSON")],
)
def test_bad_json_names_the_problem(document, fragment):
    with pytest.raises(ValueError) as error:
        Instruction.from_json(document)
    assert fragment in str(error.value)


def test_issue_13_payloads_raise_short_value_errors():
    overflow = '[{"arm":2,"target":[0,0,1' + "0" * 310 + "]}]"
    deep = "[" * 1000 + "]" * 1000
    for payload in (overflow, deep, overflow.encode(), b"\xff\xfe2,3", "9" * 5000, "1," * 40_000, [10**5000]):
        with pytest.raises(ValueError) as error:
            Instruction.coerce(payload)
        assert type(error.value) is ValueError and len(str(error.value)) < 200, str(error.value)
    with pytest.raises(ValueError, match="nested too deeply"):
        Instruction.from_json(deep)
