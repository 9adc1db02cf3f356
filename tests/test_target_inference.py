"""TargetInferencePolicy: a goal-observing policy acting on hidden targets through probes and trilateration."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import torch

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_gym import InstructionBenchmark, ScriptedController, run_episode, trilaterate
from vafn_gym.controllers import PROBE_DIRECTIONS
from vafn_sb3.common.adaptation import evaluate_adaptation
from vafn_sb3.inference.estimators.gradient import BASELINE_STEP_SIZES, GradientTargetEstimator
from vafn_sb3.inference import (
    ESTIMATOR_READINGS,
    REFINE_SOLVER,
    REFINE_STEPS,
    GradientInferencePolicy,
    LearnedTargetEstimator,
    TargetInferencePolicy,
    collect_waypoint_readings,
    inference_policy_for_env,
    load_estimator,
)

HIDDEN = "VAFN/ThreeArmReachHidden-v1"
GOAL = "VAFN/ThreeArmReachGoal-v1"


def test_trilaterate_recovers_a_point_and_refuses_coplanar_readings():
    rng = np.random.default_rng(0)
    target = rng.uniform(-0.3, 0.3, 3)
    points = rng.uniform(-0.5, 0.5, (6, 3))
    distances = np.linalg.norm(points - target, axis=1)
    assert np.allclose(trilaterate(points, distances), target, atol=1e-9)
    flat = points.copy()
    flat[:, 2] = 0.1
    assert trilaterate(flat, np.linalg.norm(flat - target, axis=1)) is None
    assert trilaterate(points[:3], distances[:3]) is None


@pytest.fixture(scope="module")
def goal_oracle():
    """The scripted controller on observed targets: a goal-observing 'model' that never fails to reach a goal."""
    env = gym.make(GOAL)
    oracle = ScriptedController.for_env(env)
    oracle.observation_space = env.observation_space
    env.close()
    return oracle


def success_rate(policy, env: gym.Env, tasks: list, oracle: ScriptedController) -> float:
    outcomes = []
    for index, task in enumerate(tasks):
        env.unwrapped.set_task(task)
        oracle.reset()
        outcomes.append(run_episode(policy, env, seed=100 + index)["success"])
    return float(np.mean(outcomes))


def test_probes_make_a_goal_observing_policy_solve_hidden_targets(goal_oracle):
    env = gym.make(HIDDEN)
    tasks = InstructionBenchmark(HIDDEN, 3, 4, n_test=4).test_tasks
    probing = TargetInferencePolicy.for_env(goal_oracle, env)
    passive = TargetInferencePolicy.for_env(goal_oracle, env, inference="passive")
    blind = TargetInferencePolicy.for_env(goal_oracle, env, inference="none")
    assert success_rate(probing, env, tasks, goal_oracle) == 1.0
    assert success_rate(blind, env, tasks, goal_oracle) == 0.0
    # Without probes the readings of a near-straight approach barely constrain the target around its line: a long
    # instruction almost always has a waypoint that fails.
    assert success_rate(passive, env, tasks, goal_oracle) < 0.5
    env.close()


def test_the_estimate_is_the_hidden_target_after_the_probes(goal_oracle):
    env = gym.make(HIDDEN)
    policy = TargetInferencePolicy.for_env(goal_oracle, env)
    env.unwrapped.set_task([2])
    policy.reset()
    obs, _ = env.reset(seed=3)
    for _ in range(30):
        obs, *_ = env.step(policy.predict(obs)[0])
        if policy.estimate is not None:
            break
    base = env.unwrapped
    assert policy.estimate is not None
    assert np.allclose(policy.estimate, base.observed_point(2, base.task.current_target(2)), atol=1e-3)
    goal_obs = policy.goal_observation(obs)
    assert goal_obs.shape == goal_oracle.observation_space.shape
    env.close()


def test_bad_models_envs_and_batches_fail_clearly(goal_oracle):
    hidden = gym.make(HIDDEN)
    blind = ScriptedController.for_env(hidden)
    blind.observation_space = hidden.observation_space
    with pytest.raises(ValueError, match="observe_goal=True"):
        TargetInferencePolicy.for_env(blind, hidden)
    with pytest.raises(ValueError, match="history=1"):
        TargetInferencePolicy.for_env(goal_oracle, gym.make(HIDDEN, history=2))
    with pytest.raises(ValueError, match="history=1"):
        TargetInferencePolicy.for_env(goal_oracle, gym.make(GOAL))
    policy = TargetInferencePolicy.for_env(goal_oracle, hidden)
    obs, _ = hidden.reset(seed=0)
    with pytest.raises(ValueError, match="one observation"):
        policy.predict(np.stack([obs, obs]))
    with pytest.raises(ValueError, match="inference must be one of"):
        TargetInferencePolicy.for_env(goal_oracle, hidden, inference="guess")
    with pytest.raises(ValueError, match="arm ids"):
        TargetInferencePolicy(goal_oracle, {1: np.zeros(3)}, {2: np.zeros(3)})
    hidden.close()


def test_a_waiting_arm_gets_the_goal_the_env_would_have_shown(goal_oracle):
    for waiting_goal in ("target", "home"):
        env = gym.make(HIDDEN, waiting_goal=waiting_goal)
        policy = TargetInferencePolicy.for_env(goal_oracle, env)
        env.unwrapped.set_task([1, 2])
        obs, _ = env.reset(seed=0)
        goal = policy.goal_observation(obs)[8 + 5:8 + 8]  # arm 2 waits
        expected = policy.homes[2] if waiting_goal == "home" else policy.priors[2]
        assert np.allclose(goal, expected, atol=1e-6), waiting_goal
        env.close()


def synthetic_readings(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Four readings per row: a random start, then three noisy 1-3 cm probe moves; targets anywhere in a 60 cm box."""
    rng = np.random.default_rng(seed)
    steps = PROBE_DIRECTIONS[None] * rng.uniform(0.01, 0.03, (n, 3, 1)) + rng.normal(0.0, 0.002, (n, 3, 3))
    starts = rng.uniform(-0.3, 0.3, (n, 1, 3))
    points = np.concatenate([starts, starts + np.cumsum(steps, axis=1)], axis=1)
    targets = rng.uniform(-0.3, 0.3, (n, 3))
    return points, np.linalg.norm(points - targets[:, None], axis=2), targets


def test_learned_estimator_learns_targets_from_readings():
    points, distances, targets = synthetic_readings(3000, seed=0)
    estimator = LearnedTargetEstimator(n_readings=4, hidden=(64, 64), seed=0)
    losses = estimator.fit(points[:2500], distances[:2500], targets[:2500], epochs=150, progress=False)
    assert losses[-1] < 0.5 * losses[0]
    errors = np.linalg.norm(estimator.predict(points[2500:], distances[2500:]) - targets[2500:], axis=1)
    guess = np.linalg.norm(targets[:2500].mean(0) - targets[2500:], axis=1)  # the mean target, ignoring the readings
    assert np.median(errors) < 0.3 * np.median(guess), (np.median(errors), np.median(guess))
    assert estimator(list(points[0, :3]), list(distances[0, :3])) is None  # fewer readings than it reads


@pytest.mark.parametrize("estimator_class, kwargs",
                         [(LearnedTargetEstimator, {}), (GradientTargetEstimator, {"steps": 5})])
def test_estimators_round_trip_and_refuse_files_that_are_not_theirs(estimator_class, kwargs, tmp_path):
    points, distances, targets = synthetic_readings(300, seed=1)
    estimator = estimator_class(n_readings=4, hidden=(16,), **kwargs)
    estimator.fit(points, distances, targets, epochs=2, progress=False)
    path = tmp_path / "estimator.pt"
    estimator.save(path)
    loaded = estimator_class.load(path)
    assert loaded.n_readings == 4 and np.allclose(loaded(points[0], distances[0]), estimator(points[0], distances[0]))
    assert getattr(loaded, "steps", None) == kwargs.get("steps")
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=f"{estimator_class.__name__}.save"):
        estimator_class.load(path)

    class Payload:  # a pickle that would run code when loaded without weights_only
        def __reduce__(self):
            return (exec, ("raise SystemExit('code ran')",))

    torch.save({"n_readings": 4, "hidden": [8], "state_dict": {}, "stats": Payload()}, path)
    with pytest.raises(ValueError, match=f"{estimator_class.__name__}.save"):
        estimator_class.load(path)
    with pytest.raises(ValueError, match="at least 4"):
        estimator_class(n_readings=3)


def test_learned_inference_moves_as_probe_inference_and_collects_labelled_readings(goal_oracle):
    env = gym.make(HIDDEN)
    tasks = InstructionBenchmark(HIDDEN, 3, 4, n_test=4).test_tasks
    with pytest.raises(ValueError, match="takes an estimator"):
        TargetInferencePolicy.for_env(goal_oracle, env, estimator=trilaterate)

    class Exact:  # the estimator a perfect network would be: trilateration of its first 6 readings
        n_readings = 6

        def __call__(self, points, distances):
            return trilaterate(points[:6], distances[:6]) if len(points) >= 6 else None

    learned = TargetInferencePolicy.for_env(goal_oracle, env, inference="learned", estimator=Exact())
    assert success_rate(learned, env, tasks, goal_oracle) == 1.0
    readings = collect_waypoint_readings(goal_oracle, env, tasks[:2], seed=0, n_readings=6, progress=False)
    n = sum(len(task) for task in tasks[:2])
    assert readings["points"].shape == (n, 6, 3) and readings["distances"].shape == (n, 6)
    for points, distances, target in zip(readings["points"], readings["distances"], readings["targets"]):
        assert np.allclose(np.linalg.norm(points - target, axis=1), distances, atol=1e-4)  # the label is the target
    # heading for the target after the first four readings (as an adapted arm does) instead of the prior goal
    prior, heading = (collect_waypoint_readings(goal_oracle, env, tasks[:2], seed=0, n_readings=10, progress=False,
                                                heading_after=after) for after in (None, 4))
    assert len(heading["points"]) == len(prior["points"]) > 0
    assert np.allclose(heading["points"][0, :4], prior["points"][0, :4])  # the episode's first readings, the same
    assert not np.allclose(heading["points"][:, 4:], prior["points"][:, 4:])  # then the arm moves elsewhere
    with pytest.raises(ValueError, match="heading_after must be in"):
        collect_waypoint_readings(goal_oracle, env, tasks[:1], seed=0, n_readings=10, heading_after=3)
    env.close()


def test_target_estimator_benchmark_writes_estimators_and_errors(load_benchmark, tmp_path):
    module = load_benchmark("target_estimator")
    report = module.main(["--train-tasks", "3", "--test-tasks", "2", "--max-length", "3", "--epochs", "2",
                          "--hidden", "8", "--n-readings", "8", "--seeds", "0", "1", "--out", str(tmp_path)])
    assert report["train_readings"] >= 3 and report["test_readings"] >= 2
    # the labels are the targets the readings measure: trilateration of the same eight readings finds every one
    assert report["trilateration"]["test"]["within_1cm"] == 1.0
    assert set(report["learned"]) == {"0", "1"}
    saved = json.loads((tmp_path / "target_estimator.json").read_text())
    assert saved["learned"]["1"]["test"] == report["learned"]["1"]["test"]
    estimator = LearnedTargetEstimator.load(tmp_path / "target_estimator_seed1.pt")
    assert estimator.n_readings == report["n_readings"]
    for bad in (["--model", str(tmp_path / "none.zip")], ["--n-readings", "3"]):  # fail before collecting
        with pytest.raises(SystemExit):
            module.main([*bad, "--out", str(tmp_path)])
    # the gradient estimators train on the saved readings without collecting again, and report every K
    # (the eight readings per waypoint also fit the refinement model, whose refined error is reported)
    gradient = module.main(["--estimator", "gradient", "--readings", str(tmp_path / "readings.npz"), "--steps", "2",
                            "--report-k", "0", "2", "--epochs", "2", "--hidden", "8", "--out", str(tmp_path / "g"),
                            "--refine-readings", str(tmp_path / "readings.npz"), str(tmp_path / "readings.npz")])
    assert gradient["collect_cpu_s"] is None and gradient["train_readings"] == report["train_readings"]
    assert set(gradient["learned"]["0"]["test_by_k"]) == {"0", "2"}
    assert set(gradient["learned"]["0"]["test_refined"]) == {"first", "refined_gauss-newton", "refined_gradient"}
    assert gradient["refinement"]["readings_per_waypoint"] == 8
    assert gradient["refinement"]["train_readings"] == 2 * report["train_readings"]  # two files, joined
    loaded = GradientTargetEstimator.load(tmp_path / "g" / "gradient_estimator_seed0.pt")
    assert loaded.steps == 2 and loaded.reading_net is not None
    with pytest.raises(SystemExit):  # only the gradient estimator has a refinement model
        module.main(["--readings", str(tmp_path / "readings.npz"), "--refine-readings", str(tmp_path / "readings.npz"),
                     "--out", str(tmp_path / "r")])
    collected = module.main(["--train-tasks", "1", "--test-tasks", "1", "--max-length", "2", "--seeds",
                             "--out", str(tmp_path / "c")])  # no seed: collect the readings only
    assert collected["learned"] == {} and (tmp_path / "c" / "readings.npz").is_file()
    (tmp_path / "bad.npz").write_bytes(b"not readings")
    with pytest.raises(SystemExit, match="--readings"):
        module.main(["--estimator", "gradient", "--readings", str(tmp_path / "bad.npz"), "--out", str(tmp_path / "b")])


def test_the_packaged_estimator_finds_held_out_targets_from_four_readings(goal_oracle):
    from vafn_gym.constants import SUCCESS_TOLERANCE
    from vafn_sb3.pretrained import PRETRAINED_ESTIMATOR

    env = gym.make(HIDDEN)
    tasks = InstructionBenchmark(HIDDEN, 1, 10, n_test=6).test_tasks
    readings = collect_waypoint_readings(goal_oracle, env, tasks, seed=0, n_readings=4, progress=False)
    packaged = TargetInferencePolicy.for_env(goal_oracle, env, inference="learned").estimator  # the default
    metadata = json.loads(PRETRAINED_ESTIMATOR.with_suffix(".json").read_text())
    assert packaged.n_readings == metadata["n_readings"] == 4

    def within_tolerance(estimator: LearnedTargetEstimator) -> float:
        estimates = estimator.predict(readings["points"], readings["distances"])
        return float(np.mean(np.linalg.norm(estimates - readings["targets"], axis=1) < SUCCESS_TOLERANCE))

    assert within_tolerance(LearnedTargetEstimator.load()) >= 0.9
    assert within_tolerance(LearnedTargetEstimator()) < 0.5  # an untrained network does not pass this test
    env.close()


def test_gradient_estimator_meta_learns_steps_that_find_targets():
    points, distances, targets = synthetic_readings(3000, seed=0)
    train, test = slice(0, 2500), slice(2500, None)

    def median_error(estimator: GradientTargetEstimator, steps: int) -> float:
        estimates = estimator.predict(points[test], distances[test], steps=steps)
        return float(np.median(np.linalg.norm(estimates - targets[test], axis=1)))

    meta = GradientTargetEstimator(hidden=(64, 64), steps=5, seed=0)
    meta.fit(points[train], distances[train], targets[train], epochs=60, progress=False)
    plain = GradientTargetEstimator(hidden=(64, 64), steps=5, seed=0)
    plain.fit(points[train], distances[train], targets[train], meta=False, epochs=60, progress=False)
    # K = 0 ignores the readings: every estimate is the first position plus the same learned offset
    offsets = meta.predict(points[test], distances[test], steps=0) - points[test, 0]
    assert np.allclose(offsets, offsets[0], atol=1e-6)
    assert median_error(meta, 5) < 0.5 * median_error(meta, 0), (median_error(meta, 5), median_error(meta, 0))
    assert median_error(meta, 5) < median_error(plain, 5)  # what meta-learning the start and the steps adds
    assert plain.start.abs().max().item() == 0.0 and not plain.meta and meta.meta
    assert any(np.isclose(plain.log_step.exp().detach().numpy(), step).all() for step in BASELINE_STEP_SIZES)
    fewer = meta.with_steps(2)
    assert fewer.steps == 2 and meta.steps == 5 and fewer.net is meta.net
    assert np.allclose(fewer(points[0], distances[0]), meta.predict(points[:1], distances[:1], steps=2)[0])
    assert meta(list(points[0, :3]), list(distances[0, :3])) is None
    with pytest.raises(ValueError, match="steps must be >= 0"):
        GradientTargetEstimator(steps=-1)
    with pytest.raises(ValueError, match="steps must be >= 0"):
        meta.with_steps(-1)


def test_gradient_inference_adapts_over_k_with_the_packaged_estimator(goal_oracle):
    from vafn_sb3.pretrained import PRETRAINED_GRADIENT_ESTIMATOR

    env = gym.make(HIDDEN)
    policy = GradientInferencePolicy.for_env(goal_oracle, env)  # the packaged estimator, unadapted: K = 0
    assert policy.estimator.steps == 0 and policy.probes
    metadata = json.loads(PRETRAINED_GRADIENT_ESTIMATOR.with_suffix(".json").read_text())
    assert metadata["kind"] == "GradientTargetEstimator" and metadata["meta"] is True
    adapted = policy.adapt(env, k=10)
    assert adapted.estimator.steps == 10 and policy.estimator.steps == 0 and adapted.support is None
    # the packaged estimator refines at every later reading once adapted; K = 0 adapts nothing, refinement included
    assert adapted.refines and not policy.refines and adapted.refine_solver == REFINE_SOLVER
    assert adapted.refine_steps == REFINE_STEPS[REFINE_SOLVER]
    plain = GradientInferencePolicy.for_env(goal_oracle, env, refine_solver="gradient")
    assert plain.refine_steps == REFINE_STEPS["gradient"] and plain.adapt(env, k=10).refine_solver == "gradient"
    with pytest.raises(ValueError, match="refine_solver must be one of"):
        GradientInferencePolicy.for_env(goal_oracle, env, refine_solver="newton")
    assert not GradientInferencePolicy.for_env(goal_oracle, env, steps=10, refine_steps=0).refines
    with pytest.raises(ValueError, match="refine_steps must be >= 0"):
        GradientInferencePolicy.for_env(goal_oracle, env, refine_steps=-1)
    tasks = InstructionBenchmark(HIDDEN, 1, 2, n_test=4).test_tasks
    rows = evaluate_adaptation(policy, HIDDEN, tasks, n_support=0, k_values=[0, 10])
    success = {k: np.mean([row["success_rate"] for row in rows if row["k"] == k]) for k in (0, 10)}
    assert success[0] == 0.0 and success[10] == 1.0, success
    with pytest.raises(ValueError, match="gradient steps"):
        GradientInferencePolicy.for_env(goal_oracle, env, inference="probe")
    with pytest.raises(ValueError, match="needs a GradientTargetEstimator"):
        GradientInferencePolicy.for_env(goal_oracle, env, estimator=LearnedTargetEstimator())
    assert isinstance(load_estimator("gradient"), GradientTargetEstimator)  # the one mode -> estimator mapping
    # the one mode -> policy mapping: gradient takes its estimator's own steps unless told, and refines
    online = inference_policy_for_env(goal_oracle, env, "gradient")
    assert isinstance(online, GradientInferencePolicy) and online.refines
    assert online.estimator.steps == metadata["steps"]
    assert inference_policy_for_env(goal_oracle, env, "gradient", steps=0, refine_steps=0).estimator.steps == 0
    assert type(inference_policy_for_env(goal_oracle, env, "probe")) is TargetInferencePolicy
    assert isinstance(load_estimator("learned"), LearnedTargetEstimator)
    with pytest.raises(ValueError, match="reads an estimator"):
        load_estimator("probe")
    env.close()


def synthetic_approaches(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Twelve readings per row: a random start, then 2 cm moves toward the target with 3 cm of sideways noise."""
    rng = np.random.default_rng(seed)
    targets = rng.uniform(-0.3, 0.3, (n, 3))
    points = [rng.uniform(-0.3, 0.3, (n, 3))]
    for _ in range(11):
        heading = targets - points[-1]
        heading /= np.linalg.norm(heading, axis=1, keepdims=True) + 1e-9
        points.append(points[-1] + 0.02 * heading + rng.normal(0.0, 0.03, (n, 3)))
    points = np.stack(points, axis=1)
    return points, np.linalg.norm(points - targets[:, None], axis=2), targets


def test_gradient_estimator_refines_an_estimate_on_later_readings(tmp_path):
    points, distances, targets = synthetic_approaches(1600, seed=0)
    estimator = GradientTargetEstimator(hidden=(8,), steps=2)
    with pytest.raises(ValueError, match="no refinement model"):
        estimator.refine(points[0], distances[0], targets[0], steps=1)
    estimator.save(tmp_path / "without.pt")  # a file without refinement (as saved before it existed) loads as such
    assert GradientTargetEstimator.load(tmp_path / "without.pt").reading_net is None
    losses = estimator.fit_refinement(points[:1500], distances[:1500], targets[:1500], hidden=(64, 64), epochs=60,
                                      progress=False)
    assert losses[-1] < 0.1 * losses[0]
    rng = np.random.default_rng(1)
    starts = targets[1500:] + rng.normal(0.0, 0.05, (100, 3))  # first estimates about 8 cm off
    before = np.median(np.linalg.norm(starts - targets[1500:], axis=1))
    for solver, steps in (("gradient", 200), ("gauss-newton", 3)):  # Gauss-Newton: a few steps do it
        refined = np.array([estimator.refine(p, d, start, steps=steps, solver=solver)
                            for p, d, start in zip(points[1500:], distances[1500:], starts)])
        after = np.median(np.linalg.norm(refined - targets[1500:], axis=1))
        assert after < 0.5 * before, (solver, before, after)
    # a start far off (a wild first estimate) loses to a restart whose result explains the readings better
    wild = targets[1500:1520] + 1.0
    kept = [estimator.refine(p, d, w, steps=3, restarts=(start,))
            for p, d, w, start in zip(points[1500:1520], distances[1500:1520], wild, starts[:20])]
    alone = [estimator.refine(p, d, w, steps=3) for p, d, w in zip(points[1500:1520], distances[1500:1520], wild)]
    assert np.median(np.linalg.norm(np.array(kept) - targets[1500:1520], axis=1)) < 0.5 * before
    assert np.median(np.linalg.norm(np.array(alone) - targets[1500:1520], axis=1)) > 0.5
    with pytest.raises(ValueError, match="solver must be one of"):
        estimator.refine(points[1500], distances[1500], starts[0], steps=1, solver="newton")
    # readings that leave directions undetermined (all at one point): a finite, shortened minimum-norm step
    still = estimator.refine(np.repeat(points[1500, :1], 5, axis=0), np.repeat(distances[1500, :1], 5), starts[0],
                             steps=3)
    assert np.isfinite(still).all() and np.linalg.norm(still - starts[0]) <= 3 * 0.05 + 1e-6
    assert np.allclose(estimator.refine(points[1500], distances[1500], starts[0], steps=0), starts[0])
    estimator.save(tmp_path / "with.pt")
    loaded = GradientTargetEstimator.load(tmp_path / "with.pt")
    assert np.allclose(loaded.refine(points[1500], distances[1500], starts[0], steps=5),
                       estimator.refine(points[1500], distances[1500], starts[0], steps=5))
    with pytest.raises(ValueError, match="need points"):
        estimator.fit_refinement(points[:, 0], distances, targets)
    # readings far from any it was fitted on (an arm that wandered off) move the estimate at most 5 cm a step
    far = points[1500] * 50.0
    for solver in ("gradient", "gauss-newton"):
        moved = estimator.refine(far, distances[1500] * 50.0, starts[0], steps=10, solver=solver)
        assert np.isfinite(moved).all() and np.linalg.norm(moved - starts[0]) <= 10 * 0.05 + 1e-6


class RecordingEstimator:
    """A stand-in GradientTargetEstimator that records how the policy asks it to refine."""

    reading_net = object()

    def __init__(self, steps: int = 0) -> None:
        self.steps, self.calls = steps, []

    def with_steps(self, steps: int) -> RecordingEstimator:
        adapted = RecordingEstimator(steps)
        adapted.calls = self.calls
        return adapted

    def __call__(self, points, distances):
        # somewhere 10 cm away, so that the arm moves on and makes new readings
        return np.asarray(points[0]) + np.array([0.0, 0.0, -0.1]) if len(points) >= ESTIMATOR_READINGS else None

    def refine(self, points, distances, estimate, steps, solver, restarts=()):
        self.calls.append((steps, solver, [np.asarray(r).copy() for r in restarts]))
        return estimate


@pytest.mark.parametrize("solver", ["gauss-newton", "gradient"])
def test_gradient_inference_refines_with_its_solver_and_restarts_from_the_prior(goal_oracle, solver):
    env = gym.make(HIDDEN, max_length=1)
    estimator = RecordingEstimator()
    policy = GradientInferencePolicy.for_env(goal_oracle, env, estimator=estimator, refine_solver=solver)
    policy = policy.adapt(env, k=3)
    obs, _ = env.reset(seed=0)
    policy.reset()
    for _ in range(15):
        obs, *_ = env.step(policy.predict(obs)[0])
    assert estimator.calls, "later readings refine the estimate"
    active = policy.readings[0] or 1
    for steps, used, restarts in estimator.calls:
        assert (steps, used) == (REFINE_STEPS[solver], solver)
        # Gauss-Newton also starts from the prior, the plain gradient steps (the earlier results) do not
        assert len(restarts) == (solver == "gauss-newton")
        assert all(np.allclose(r, policy.priors[active]) for r in restarts)
    env.close()
