"""Robot specs and arm layouts: geometry, slices, feasibility checks, and every robot standing where its layout says."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from vafn_gym import (
    KUKA_IIWA,
    PANDA,
    ROBOTS,
    XARM6,
    ArmLayout,
    InstructionBenchmark,
    RobotSpec,
    ScriptedController,
)
from vafn_gym.constants import WORKSPACE_HIGH, WORKSPACE_LOW
from vafn_gym.robots import get_robot


def test_robot_registry_and_lookup():
    assert set(ROBOTS) == {"kuka", "panda", "xarm"}
    assert get_robot("panda") is PANDA and get_robot(XARM6) is XARM6
    with pytest.raises(ValueError, match="robot must be one of"):
        get_robot("ur5")
    assert len(KUKA_IIWA.joints) == 7 and len(XARM6.joints) == 6
    assert KUKA_IIWA.joint_forces.shape == (7,)


def test_robot_spec_rejects_a_rest_pose_of_the_wrong_length():
    with pytest.raises(ValueError, match="rest_pose has 2 angles for 3 joints"):
        RobotSpec(name="toy", urdf="toy.urdf", joints=(0, 1, 2), ee_link=2, joint_force=1.0, rest_pose=(0.0, 0.0))


@pytest.mark.parametrize("n_arms", [2, 3, 4, 6, 8])
def test_layout_geometry(n_arms):
    layout = ArmLayout(n_arms=n_arms)
    assert layout.arm_ids == tuple(range(1, n_arms + 1))
    assert len(layout.arm_pairs) == n_arms * (n_arms - 1) // 2
    assert layout.action_dim == 3 * n_arms
    covered = np.concatenate([np.arange(3 * n_arms)[layout.action_slice(arm)] for arm in layout.arm_ids])
    assert np.array_equal(covered, np.arange(3 * n_arms))
    for arm in layout.arm_ids:
        base, home, target = layout.base_position(arm), layout.home_point(arm), layout.default_target(arm)
        assert np.isclose(np.linalg.norm(base[:2]), layout.base_radius) and base[2] == 0.0
        # The home point and the default target lie on the ray from the centre toward the base.
        for point in (home, target):
            assert np.isclose(base[0] * point[1] - base[1] * point[0], 0.0, atol=1e-12)
            assert np.dot(base[:2], point[:2]) > 0
        assert np.linalg.norm(home[:2]) > layout.shared_radius  # clear of the shared region
    yaws = [layout.base_yaw(arm) for arm in layout.arm_ids]
    assert np.allclose(np.diff(yaws), 2 * np.pi / n_arms)


def test_shared_targets_stay_in_the_shared_region():
    layout = ArmLayout(n_arms=4, shared_radius=0.1, shared_z_range=(0.25, 0.3))
    rng = np.random.default_rng(0)
    points = np.array([layout.sample_shared_target(rng) for _ in range(500)])
    assert np.all(np.linalg.norm(points[:, :2], axis=1) <= 0.1 + 1e-12)
    assert np.all((points[:, 2] >= 0.25) & (points[:, 2] <= 0.3))
    assert np.all(points >= WORKSPACE_LOW) and np.all(points <= WORKSPACE_HIGH)


@pytest.mark.parametrize(
    "kwargs, error, fragment",
    [
        (dict(n_arms=1), ValueError, "n_arms must be between 2 and 8"),
        (dict(n_arms=9), ValueError, "n_arms must be between 2 and 8"),
        (dict(n_arms=True), TypeError, "n_arms must be an integer"),
        (dict(n_arms=3.0), TypeError, "n_arms must be an integer"),
        (dict(base_radius=float("nan")), ValueError, "base_radius"),
        (dict(home_height=-0.1), ValueError, "home_height"),
        (dict(shared_z_range=(0.5, 0.2)), ValueError, "shared_z_range"),
    ],
)
def test_layout_rejects_bad_arguments(kwargs, error, fragment):
    with pytest.raises(error, match=fragment):
        ArmLayout(**kwargs)


@pytest.mark.parametrize(
    "layout, robot, fragment",
    [
        (ArmLayout(n_arms=8, base_radius=0.3), KUKA_IIWA, "stand 0.23 m apart"),
        (ArmLayout(n_arms=3, base_radius=0.6), XARM6, "xarm reaches 0.68 m"),
        (ArmLayout(n_arms=3, base_radius=0.75), KUKA_IIWA, "kuka reaches 0.8 m"),
        (ArmLayout(n_arms=6, base_radius=0.4), PANDA, "home points 0.15 m apart"),
    ],
)
def test_infeasible_layouts_are_refused_clearly(layout, robot, fragment):
    with pytest.raises(ValueError, match=fragment):
        layout.check_feasible(robot)
    with pytest.raises(ValueError, match=fragment):
        gym.make("VAFN/MultiArmReach-v1", layout=layout, robot=robot.name)


def test_every_robots_default_layout_is_feasible_up_to_seven_arms():
    for robot in ROBOTS.values():
        for n_arms in range(2, 8):
            ArmLayout(n_arms=n_arms, base_radius=robot.base_radius).check_feasible(robot)


def test_layout_must_be_an_arm_layout():
    with pytest.raises(TypeError, match="layout must be an ArmLayout"):
        gym.make("VAFN/MultiArmReach-v1", layout={"n_arms": 3})


@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_arms_stand_on_their_layout_and_rest_near_home(robot):
    layout = ArmLayout(n_arms=4, base_radius=ROBOTS[robot].base_radius, base_yaw0=0.3)
    env = gym.make("VAFN/MultiArmReach-v1", layout=layout, robot=robot)
    base = env.unwrapped
    try:
        assert base.n_arms == 4 and base.robot is ROBOTS[robot]
        for arm_id, arm in base.arms.items():
            assert np.allclose(arm.base_position, layout.base_position(arm_id))
            assert np.linalg.norm(arm.home - layout.home_point(arm_id)) < 0.02  # IK leaves ~1 cm at most
            assert np.allclose(arm.ee_position, arm.home, atol=1e-9)
    finally:
        env.close()


@pytest.mark.filterwarnings("error::UserWarning")  # the checkers' warnings ("not equal although similar") count
@pytest.mark.parametrize("robot", sorted(ROBOTS))
@pytest.mark.parametrize("n_arms", [2, 4, 6])
def test_check_env_for_every_robot_and_arm_count(n_arms, robot):
    env = gym.make("VAFN/MultiArmReach-v1", n_arms=n_arms, robot=robot)
    gym_check_env(env.unwrapped, skip_render_check=True)  # includes the seeded-determinism check
    sb3_check_env(env.unwrapped)
    assert env.observation_space.shape == (5 * n_arms,) and env.action_space.shape == (3 * n_arms,)
    env.close()
    goal = gym.make("VAFN/MultiArmReach-v1", n_arms=n_arms, robot=robot, observe_goal=True)
    assert goal.observation_space.shape == (8 * n_arms,)
    goal.close()


@pytest.mark.parametrize(
    "env_kwargs", [{"n_arms": 4}, {"robot": "panda"}, {"robot": "xarm"}, {"n_arms": 4, "observe_goal": True},
                   {"n_arms": 6, "frame": "base"}, {"n_arms": 3, "frame": "base", "observe_goal": True}]
)
def test_scripted_controller_solves_other_layouts_and_robots(env_kwargs):
    """A few held-out tasks each (200 each: benchmarks/scripted_ceiling.py)."""
    benchmark = InstructionBenchmark(
        "VAFN/MultiArmReach-v1", min_length=2, max_length=5, n_test=3, env_kwargs=env_kwargs
    )
    env = benchmark.make_env()
    controller = ScriptedController.for_env(env)
    env.close()
    for row in benchmark.evaluate(controller):
        assert row["success"] == 1.0 and row["collision"] == 0.0, row


@pytest.mark.parametrize("n_arms", [3, 6])
def test_base_frame_is_each_arms_own_frame(n_arms):
    """frame="base": a point toward the centre has +x, every arm sees the same numbers at home and the same goal."""
    layout = ArmLayout(n_arms=n_arms)
    for arm in layout.arm_ids:
        np.testing.assert_allclose(layout.to_base_frame(arm, layout.base_position(arm)), 0.0, atol=1e-12)
        np.testing.assert_allclose(layout.to_base_frame(arm, np.zeros(3)), [layout.base_radius, 0, 0], atol=1e-12)
        np.testing.assert_allclose(layout.base_to_world_vector(arm, [1.0, 0, 0]),
                                   -layout.base_position(arm) / layout.base_radius, atol=1e-12)
    env = gym.make("VAFN/MultiArmReach-v1", n_arms=n_arms, frame="base", observe_goal=True, instruction="1")
    obs, _ = env.reset(seed=0)
    blocks = obs.reshape(n_arms, 8)
    np.testing.assert_allclose(blocks[:, :3], blocks[:1, :3].repeat(n_arms, 0), atol=2e-3)  # same home, every arm
    np.testing.assert_allclose(blocks[0, 5:], layout.to_base_frame(1, layout.default_target(1)), atol=1e-6)
    assert env.observation_space.contains(obs)
    assert env.unwrapped.world_kwargs["frame"] == "base"
    env.close()


def test_base_frame_action_is_a_velocity_in_the_arms_frame():
    """+x in arm k's block moves arm k toward the table centre, for every arm (a world-frame +x would not)."""
    for arm in (1, 2, 3):
        env = gym.make("VAFN/MultiArmReach-v1", frame="base", instruction=str(arm))
        env.reset(seed=0)
        base = env.unwrapped
        start = base.arms[arm].ee_position[:2].copy()
        action = np.zeros(9, dtype=np.float32)
        action[3 * (arm - 1)] = 1.0
        for _ in range(5):
            env.step(action)
        moved = base.arms[arm].ee_position[:2] - start
        toward_centre = -start / np.linalg.norm(start)
        sideways = toward_centre[0] * moved[1] - toward_centre[1] * moved[0]
        assert moved @ toward_centre > 0.05 and abs(sideways) < 0.02, (arm, moved)
        env.close()


def test_base_frame_spaces_match_across_robots_and_arm_counts():
    """A base-frame model saved with one robot loads with another's env (SB3 compares the spaces' bounds too)."""
    spaces = [gym.make("VAFN/MultiArmReach-v1", robot=robot, frame="base").observation_space
              for robot in ("kuka", "panda", "xarm")]
    assert spaces[0] == spaces[1] == spaces[2]


def test_frame_is_checked():
    with pytest.raises(ValueError, match="frame"):
        gym.make("VAFN/MultiArmReach-v1", frame="tool")
