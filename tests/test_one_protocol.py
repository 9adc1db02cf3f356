"""One evaluation protocol (issue 62): one suite, one seed function, one collision key, one episode runner.

The source check fails when a module outside :data:`STEPPERS` steps an env (a ``.step(...)`` call with arguments,
which optimisers, schedulers and the simulator's own ``step()`` do not take) or calls SB3's ``evaluate_policy``: a
policy is scored by :func:`vafn_gym.run_episode` alone.
"""

from __future__ import annotations

import ast
from collections import Counter
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_gym import InstructionBenchmark, ScriptedController, TaskSampler
from vafn_gym.benchmarks import (
    COLLISION_KEY,
    EVAL_SEED,
    HELDOUT_SIZE,
    HELDOUT_VERSION,
    SUITE_SEED,
    episode_seed,
    run_episode,
)
from vafn_gym.heldout import HELDOUT_ORDERS

torch.set_num_threads(1)
REPO_ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("vafn_gym", "vafn_sb3", "vafn_media", "vafn_app", "zoo", "benchmarks")
#: (file, function) pairs that may step an env, and why; everything else that scores a policy calls the runner.
STEPPERS = {
    ("vafn_gym/benchmarks.py", "run_episode"): "the one episode runner",
    ("vafn_gym/envs/multi_arm.py", "MultiArmEnv._advance"): "env code (the task's own step)",
    ("vafn_gym/wrappers.py", "*"): "env wrappers",
    ("vafn_gym/pettingzoo.py", "*"): "the PettingZoo view of the env",
    ("zoo/enjoy.py", "RecordingWrapper.step"): "an env wrapper (records frames)",
    ("vafn_sb3/online.py", "OnlineController.step"): "the online controller's control loop",
    ("vafn_sb3/common/adaptation.py", "collect_support"): "training data: an adaptation's support set",
    ("vafn_sb3/inference/policies.py", "collect_waypoint_readings"): "training data: the target estimator's readings",
    ("benchmarks/env_throughput.py", "*"): "times env steps, scores nothing",
    ("benchmarks/train_speed.py", "env_block.run"): "times env steps, scores nothing",
}


def _env_steps(path: Path) -> list[tuple[str, int, str]]:
    """(enclosing function, line, call) of every ``X.step(args)`` and ``evaluate_policy`` call in ``path``."""
    found: list[tuple[str, int, str]] = []

    def visit(node: ast.AST, scope: list[str]) -> None:
        for child in ast.iter_child_nodes(node):
            inner = scope + [child.name] if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) \
                else scope
            if isinstance(child, ast.Call):
                func = child.func
                name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
                if (name == "step" and isinstance(func, ast.Attribute) and (child.args or child.keywords)) or \
                        name == "evaluate_policy":
                    found.append((".".join(scope), child.lineno, ast.unparse(child)[:80]))
            visit(child, inner)

    visit(ast.parse(path.read_text(), str(path)), [])
    return found


def _scoring_loops_outside_the_allow_list() -> list[str]:
    offenders = []
    for package in PACKAGES:
        for path in sorted((REPO_ROOT / package).rglob("*.py")):
            relative = path.relative_to(REPO_ROOT).as_posix()
            for scope, line, call in _env_steps(path):
                if (relative, scope) not in STEPPERS and (relative, "*") not in STEPPERS:
                    offenders.append(f"{relative}:{line} ({scope or 'module'}): {call}")
    return offenders


def test_no_module_but_the_runner_steps_an_env_to_score_a_policy():
    offenders = _scoring_loops_outside_the_allow_list()
    assert not offenders, "score policies with vafn_gym.run_episode / evaluate_tasks:\n" + "\n".join(offenders)
    assert len(STEPPERS) <= 11, "keep the allow-list small"


def test_the_source_check_catches_a_scoring_loop(tmp_path):
    loop = tmp_path / "loop.py"
    loop.write_text("def score(env, policy):\n    obs, _ = env.reset()\n    while True:\n"
                    "        obs, r, term, trunc, info = env.step(policy.predict(obs)[0])\n"
                    "def sb3(model, env):\n    return evaluate_policy(model, env)\n"
                    "def train(optimizer, sim):\n    optimizer.step()\n    sim.step()\n")
    assert [(scope, line) for scope, line, _ in _env_steps(loop)] == [("score", 4), ("sb3", 6)]


def test_the_held_out_suite_is_200_distinct_test_orders_of_every_length_and_versioned():
    sampler = TaskSampler("test")
    orders = [tuple(int(a) for a in code.split(",")) for code in HELDOUT_ORDERS]
    assert len(orders) == len(set(orders)) == HELDOUT_SIZE >= 200
    assert {sampler.split_of(order) for order in orders} == {"test"}
    assert sorted(Counter(map(len, orders))) == list(range(1, 11))
    # frozen: a change of the split or of the generator must come with a new HELDOUT_VERSION
    assert orders == sampler.stratified_orders(HELDOUT_SIZE, seed=SUITE_SEED), f"{HELDOUT_VERSION} changed"
    # every prefix is stratified: the first 30 hold every length
    assert sorted(Counter(map(len, orders[:30]))) == list(range(1, 11))


def test_benchmark_test_and_validation_suites_are_disjoint_and_the_seeds_are_one_function():
    benchmark = InstructionBenchmark("VAFN/ThreeArmReach-v1")
    assert [t.to_code() for t in benchmark.test_tasks] == list(HELDOUT_ORDERS)
    validation = {t.arms for t in benchmark.validation_tasks}
    assert len(validation) == len(benchmark.validation_tasks)
    assert {TaskSampler("validation").split_of(o) for o in validation} == {"validation"}
    assert not validation & {t.arms for t in benchmark.test_tasks}
    assert benchmark.episode_seed(3, 2) == episode_seed(benchmark.seed, 3, 2) == EVAL_SEED + benchmark.seed + 302
    with pytest.raises(ValueError):
        episode_seed(0, 0, 100)


def test_adaptation_studies_seed_their_episodes_with_the_one_seed_function(monkeypatch):
    from vafn_sb3.common import adaptation

    seeds = []

    def fake_run_episode(policy, env, seed, deterministic=True):
        seeds.append(seed)
        return {"return": 0.0, "success": 1.0, "collision": 0.0}

    monkeypatch.setattr(adaptation, "run_episode", fake_run_episode)
    env = gym.make("VAFN/ThreeArmReach-v1")
    tasks = InstructionBenchmark("VAFN/ThreeArmReach-v1", 1, 2, n_test=2).test_tasks
    adaptation.evaluate_adaptation(ScriptedController.for_env(env), "VAFN/ThreeArmReach-v1", tasks, 1, [0],
                                   n_eval_episodes=3, seed=7)
    env.close()
    assert seeds == [episode_seed(7, i, e) for i in range(2) for e in range(3)]


def test_the_runner_reads_the_one_collision_key():
    class Contact(gym.Wrapper):
        """Reports a contact from step 3 on through COLLISION_KEY alone."""

        def step(self, action):
            obs, reward, terminated, truncated, info = self.env.step(action)
            info = {**info, "collision": False, COLLISION_KEY: self.env.unwrapped.task.steps >= 3}
            return obs, reward, terminated, truncated, info

    env = Contact(gym.make("VAFN/ThreeArmReach-v1", instruction="1", max_steps=6))

    class Still:
        def predict(self, obs, deterministic=True):
            return np.zeros(9, dtype=np.float32), None

    row = run_episode(Still(), env, seed=0)
    env.close()
    assert (row["collision"], row["outcome"]) == (1.0, "collision")


def test_training_time_evaluation_scores_the_validation_suite(tmp_path):
    from stable_baselines3.common.env_util import make_vec_env

    from vafn_sb3 import SAC
    from vafn_sb3.callbacks import MetaEvalCallback, SuccessCollisionEvalCallback

    env_id = "VAFN/ThreeArmReach-v1"
    model = SAC("MlpPolicy", env_id, learning_starts=10, seed=0)
    callback = SuccessCollisionEvalCallback(make_vec_env(env_id, n_envs=1), n_eval_episodes=2, eval_freq=20,
                                            log_path=str(tmp_path), verbose=0)
    meta = MetaEvalCallback(eval_freq=10_000, k_values=(0,), n_tasks=3, env_id=env_id)
    model.learn(20, callback=[callback, meta])
    validation = TaskSampler("validation")
    assert [validation.split_of(task) for task in callback._tasks] == ["validation"] * 2
    assert {validation.split_of(task) for task in meta.tasks} == {"validation"}
    saved = np.load(tmp_path / "evaluations.npz")
    assert saved["collisions"].shape == saved["successes"].shape == (1, 2)
