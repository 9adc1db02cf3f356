"""MAML-SAC: functional pieces, first- vs second-order meta-gradients, learn/save/load, and the adapt() contract."""

from __future__ import annotations

import glob

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize
from torch.func import functional_call

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_gym import Instruction, InstructionBenchmark
from vafn_sb3.common.adaptation import (
    Adaptable, SupportSet, collect_support, evaluate_adaptation, per_arm_tasks, support_coverage,
)
from vafn_sb3.maml_sac import MAMLSAC
from vafn_sb3.maml_sac.functional import clip_gradients, inner_adapt, query_losses
from vafn_sb3.maml_sac.policies import parameters_of

#: The 3-arm joint spaces (15-D observation, 9-D action).
OBS_DIM, ACTION_DIM = 15, 9
ENV_ID = "VAFN/ThreeArmReachHidden-v1"
#: Short episodes so that CI-sized rollouts contain complete episodes.
ENV_KWARGS = {"max_length": 1, "max_episode_steps": 30}
TINY = {"net_arch": [16, 16]}

torch.set_num_threads(1)


def tiny_model(env=None, **kwargs) -> MAMLSAC:
    """A MAML-SAC with tiny networks and CI-sized budgets."""
    env = env if env is not None else gym.make(ENV_ID, **ENV_KWARGS)
    settings = dict(
        meta_batch_size=2, n_support=32, n_query=32, outer_steps=2, batch_size=16, n_train_tasks=4,
        policy_kwargs=TINY, learning_starts=0, seed=0,
    )
    settings.update(kwargs)
    return MAMLSAC("MlpPolicy", env, **settings)


def random_batch(n: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """Random transitions of the env's shapes."""
    return {
        "observations": torch.randn(n, OBS_DIM, generator=generator),
        "actions": torch.rand(n, ACTION_DIM, generator=generator) * 2 - 1,
        "next_observations": torch.randn(n, OBS_DIM, generator=generator),
        "rewards": torch.randn(n, generator=generator),
        "dones": torch.zeros(n),
        "targets": torch.randn(n, generator=generator),
    }


@pytest.fixture(scope="module")
def model() -> MAMLSAC:
    return tiny_model()


def test_functional_key_sets_equal_modules(model):
    actor_keys = set(parameters_of(model.actor_distribution))
    assert actor_keys == {f"actor.{name}" for name, _ in model.actor.named_parameters()}
    assert set(parameters_of(model.critic)) == {name for name, _ in model.critic.named_parameters()}
    obs = torch.randn(4, OBS_DIM)
    # strict=True fails on any missing or unexpected key
    mean, _ = functional_call(model.actor_distribution, parameters_of(model.actor_distribution), (obs,), strict=True)
    assert torch.allclose(mean, model.actor.get_action_dist_params(obs)[0])


def test_inner_step_changes_every_parameter(model):
    batch = random_batch(32, torch.Generator().manual_seed(0))
    actor0, critic0 = parameters_of(model.actor_distribution, True), parameters_of(model.critic, True)
    args = (batch["observations"], batch["actions"], batch["targets"], torch.tensor(0.1), torch.tensor(0.01),
            torch.tensor(0.01))
    same_actor, same_critic = inner_adapt(model.actor_distribution, model.critic, actor0, critic0, *args, 0, False)
    assert all(torch.equal(same_actor[k], actor0[k]) for k in actor0)
    actor1, critic1 = inner_adapt(model.actor_distribution, model.critic, actor0, critic0, *args, 1, False)
    assert set(actor1) == set(actor0) and set(critic1) == set(critic0)
    assert all(not torch.equal(actor1[k], actor0[k]) for k in actor0)
    assert all(not torch.equal(critic1[k], critic0[k]) for k in critic0)
    # the module itself is not modified
    assert all(torch.equal(p, critic0[k]) for k, p in model.critic.named_parameters())


def meta_gradient(model: MAMLSAC, second_order: bool) -> dict[str, torch.Tensor]:
    """Meta-gradient of one task's query loss w.r.t. the meta-parameters (fixed sampling noise)."""
    generator = torch.Generator().manual_seed(1)
    support, query = random_batch(32, generator), random_batch(16, generator)
    actor_params = parameters_of(model.actor_distribution, True)
    critic_params = parameters_of(model.critic, True)
    leaves = {**actor_params, **critic_params}
    for tensor in leaves.values():
        tensor.requires_grad_(True)
    torch.manual_seed(2)
    critic_loss, actor_loss, _ = query_losses(
        model.actor_distribution, model.critic, actor_params, critic_params, parameters_of(model.critic_target),
        support, query, torch.tensor(0.1), torch.tensor(0.05), torch.tensor(0.05), 1, 0.99, second_order,
    )
    grads = torch.autograd.grad(critic_loss + actor_loss, list(leaves.values()))
    return dict(zip(leaves, grads))


def test_second_order_meta_gradient_differs_from_first_order(model):
    first, second = meta_gradient(model, False), meta_gradient(model, True)
    assert all(torch.isfinite(g).all() and g.abs().sum() > 0 for g in first.values())
    difference = sum(float((first[k] - second[k]).abs().sum()) for k in first)
    assert difference > 1e-4, "second order gave the first-order gradient: the Hessian term is missing"
    # and first order is deterministic given the noise, so the difference is not sampling noise
    again = meta_gradient(model, False)
    assert all(torch.equal(first[k], again[k]) for k in first)


def test_learn_vecenv_tensorboard_save_load(tmp_path):
    venv = make_vec_env(ENV_ID, n_envs=2, env_kwargs=ENV_KWARGS, seed=0)
    model = tiny_model(
        venv, warmup_steps=64, n_support=64, n_query=64, tensorboard_log=str(tmp_path), meta_batch_mode="loop",
        second_order=True,
    )
    model.learn(400, log_interval=1, tb_log_name="MAMLSAC", progress_bar=True)
    assert model.num_timesteps >= 400 and model.meta_iterations >= 2
    assert set(model.query_buffers) <= set(range(len(model.train_tasks)))
    assert all(len(s) == model.n_support for s in model.support_sets.values())
    assert model.inner_lrs != (model.inner_actor_lr, model.inner_critic_lr), "inner step sizes were not meta-learned"
    events = glob.glob(str(tmp_path / "MAMLSAC_1" / "events.*"))
    assert events
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tags = set(EventAccumulator(events[0]).Reload().Tags()["scalars"])
    for prefix in ("pre", "post"):
        for name in ("return", "success_rate", "collision_rate"):
            assert f"meta/{prefix}_adaptation_{name}" in tags

    model.save(tmp_path / "maml_sac.zip")
    loaded = MAMLSAC.load(tmp_path / "maml_sac.zip", env=venv)
    for name in ("meta_batch_size", "n_support", "inner_steps", "second_order", "meta_batch_mode", "meta_iterations"):
        assert getattr(loaded, name) == getattr(model, name)
    assert loaded.train_tasks == model.train_tasks
    assert torch.equal(loaded.log_inner_lrs, model.log_inner_lrs)
    for a, b in zip(model.policy.state_dict().values(), loaded.policy.state_dict().values()):
        assert torch.equal(a, b)
    saved_state = model.inner_lr_optimizer.state_dict()["state"][0]
    loaded_state = loaded.inner_lr_optimizer.state_dict()["state"][0]
    assert torch.equal(saved_state["exp_avg"], loaded_state["exp_avg"])
    loaded.learn(100, reset_num_timesteps=False, log_interval=None)  # continues; None = zoo "--log-interval -2"


class ActingPolicyLog(BaseCallback):
    """Records, at every env step, whether the model acted with an adapted policy."""

    def __init__(self) -> None:
        super().__init__()
        self.adapted: list[bool] = []

    def _on_step(self) -> bool:
        self.adapted.append(self.model.acting_policy is not None)
        return True


def test_meta_iteration_collects_through_sb3_and_stores_original_observations():
    """Support then query rollouts go through SB3's collect_rollouts and _store_transition, so under VecNormalize the
    replay, query and support data hold the env's own observations (the old rollout stored normalised ones)."""
    venv = VecNormalize(make_vec_env(ENV_ID, n_envs=1, env_kwargs=ENV_KWARGS, seed=0), gamma=0.99)
    model = tiny_model(venv, n_support=16, n_query=16)  # one meta-iteration: 2 tasks x (16 support + 16 query)
    log = ActingPolicyLog()
    model.learn(64, callback=log, log_interval=None)
    assert model.meta_iterations == 1 and model.acting_policy is None
    assert log.adapted == [False] * 32 + [True] * 32  # sample tasks -> both supports -> adapt -> both queries
    low, high = venv.observation_space.low - 1e-5, venv.observation_space.high + 1e-5
    stored = model.replay_buffer.observations[: model.replay_buffer.pos, 0]
    queries = [b.observations[: b.pos, 0] for b in model.query_buffers.values()]
    for observations in [stored, *queries, *(s.observations for s in model.support_sets.values())]:
        assert ((observations >= low) & (observations <= high)).all()
    assert any(np.allclose(s.observations, stored[:16]) for s in model.support_sets.values())
    assert any(np.allclose(q, stored[32:48]) for q in queries)


@pytest.mark.parametrize("sac_gradient_steps, expected", [(0, 0), (5, 5), (-1, 64)])
def test_sac_gradient_steps_follow_every_meta_iteration(sac_gradient_steps, expected, monkeypatch):
    model = tiny_model(sac_gradient_steps=sac_gradient_steps, n_support=16, n_query=16)  # 2 x (16 + 16) = 64 steps
    calls = []
    monkeypatch.setattr(model, "train", lambda batch_size, gradient_steps: calls.append(gradient_steps))
    model.learn(128, log_interval=None)
    assert model.meta_iterations == 2
    assert calls == ([expected] * 2 if expected else [])


def snapshot(model: MAMLSAC) -> list[torch.Tensor]:
    """Every tensor adapt() must leave alone: parameters, target net, α, inner step sizes, optimiser moments."""
    tensors = [t.clone() for t in model.policy.state_dict().values()]
    tensors += [model.log_ent_coef.detach().clone(), model.log_inner_lrs.detach().clone()]
    for optimizer in (model.actor.optimizer, model.critic.optimizer, model.ent_coef_optimizer):
        for state in optimizer.state_dict()["state"].values():
            tensors += [v.clone() for v in state.values() if torch.is_tensor(v)]
    return tensors


def test_the_same_seed_trains_bit_identical_weights_and_another_seed_does_not():
    """Warm-up SAC steps and meta-iterations (task draws, supports, inner and outer steps) all follow the seed."""
    def trained(seed: int) -> list[torch.Tensor]:
        model = tiny_model(seed=seed, learning_starts=32, warmup_steps=64)
        model.learn(256, log_interval=None)
        assert model.meta_iterations >= 1
        return snapshot(model)

    first, again, other = trained(0), trained(0), trained(1)
    assert all(torch.equal(a, b) for a, b in zip(first, again, strict=True))
    assert not all(torch.equal(a, b) for a, b in zip(first, other, strict=True))


def test_adapt_leaves_model_bit_identical_and_adapts(model):
    model.learn(64)  # give the optimisers some state
    env = gym.make(ENV_ID, **ENV_KWARGS)
    task = InstructionBenchmark(ENV_ID, 1, 1, n_test=1).test_tasks[0]
    before, buffer_pos = snapshot(model), model.replay_buffer.pos
    assert isinstance(model, Adaptable)
    adapted = model.adapt(env, task=task, n_support=32, k=3, seed=0)
    assert all(torch.equal(a, b) for a, b in zip(before, snapshot(model)))
    assert model.replay_buffer.pos == buffer_pos
    obs, _ = env.reset(seed=0)
    assert not np.allclose(adapted.predict(obs)[0], model.predict(obs, deterministic=True)[0])
    unadapted = model.adapt(env, task=task, n_support=8, k=0, seed=0)
    assert np.allclose(unadapted.predict(obs)[0], model.predict(obs, deterministic=True)[0], atol=1e-6)
    assert adapted.predict(np.stack([obs, obs]))[0].shape == (2, ACTION_DIM)
    # the seed fixes the inner rounds' action samples too: the same seed adapts to the same policy, another does not
    torch.manual_seed(123)  # whatever the caller's stream
    again = model.adapt(env, task=task, n_support=32, k=3, seed=0)
    assert np.array_equal(again.predict(obs)[0], adapted.predict(obs)[0])
    other = model.adapt(env, task=task, n_support=32, k=3, seed=1)
    assert not np.array_equal(other.predict(obs)[0], adapted.predict(obs)[0])


def test_adapt_restores_model_when_it_raises(model, monkeypatch):
    env = gym.make(ENV_ID, **ENV_KWARGS)
    before = snapshot(model)
    original = model.adapted_parameters

    def corrupt_then_fail(supports, steps):
        with torch.no_grad():
            for parameter in model.policy.parameters():
                parameter.add_(1.0)
            model.log_ent_coef.add_(1.0)
        original(supports, steps)
        raise RuntimeError("injected failure")

    monkeypatch.setattr(model, "adapted_parameters", corrupt_then_fail)
    with pytest.raises(RuntimeError, match="injected"):
        model.adapt(env, n_support=8, k=1, seed=0)
    assert all(torch.equal(a, b) for a, b in zip(before, snapshot(model)))


def test_bad_arguments_raise(model):
    env = gym.make(ENV_ID, **ENV_KWARGS)
    with pytest.raises(ValueError, match="meta_batch_mode"):
        tiny_model(meta_batch_mode="parallel")
    with pytest.raises(ValueError, match="sac_gradient_steps"):
        tiny_model(sac_gradient_steps=-2)
    with pytest.raises(ValueError, match="k must be"):
        model.adapt(env, k=-1)
    with pytest.raises(ValueError, match="n_support"):
        collect_support(model, env, None, 0, seed=0)
    with pytest.raises(ValueError, match="observation shape"):
        model.adapt(gym.make("VAFN/ThreeArmReachGoal-v1", **ENV_KWARGS), k=1)


def test_nstep_plan_matches_definition():
    rewards = np.array([1.0, 2.0, 3.0, 4.0, 5.0], dtype=np.float32)
    ends = np.array([0, 1, 0, 0, 1], dtype=np.float32)
    terminated = np.array([0, 1, 0, 0, 0], dtype=np.float32)
    zeros = np.zeros(5, dtype=np.float32)
    support = SupportSet(np.zeros((5, 1)), np.zeros((5, 1)), rewards, np.zeros((5, 1)), terminated, ends, zeros, zeros)
    bootstrap = np.array([10.0, 20.0, 30.0, 40.0, 50.0], dtype=np.float32)
    y = support.discounted_returns(0.5, n_step=2, bootstrap=bootstrap)
    # t=0: 1 + .5*2, episode terminated at 1 -> no bootstrap; t=2: 3 + .5*4 + .25*V(s'_3); t=4: 5 + .5*V(s'_4) (cut)
    assert np.allclose(y, [2.0, 2.0, 3 + 2 + 10, 4 + 2.5 + 12.5, 5 + 25])
    assert np.allclose(support.discounted_returns(0.5, None), [2.0, 2.0, 3 + 2 + 1.25, 4 + 2.5, 5])


def test_evaluate_adaptation_rows(model):
    tasks = InstructionBenchmark(ENV_ID, 1, 1, n_test=2).test_tasks
    rows = evaluate_adaptation(model, ENV_ID, tasks, n_support=16, k_values=[0, 2], n_eval_episodes=1,
                               env_kwargs=ENV_KWARGS)
    assert [(r["task_index"], r["k"]) for r in rows] == [(0, 0), (0, 2), (1, 0), (1, 2)]
    assert all(0.0 <= r["success_rate"] <= 1.0 and np.isfinite(r["return_mean"]) for r in rows)
    # one-waypoint tasks: the support set shows their arm executing; K = 0 collects none
    assert [r["support_arms"] for r in rows if r["k"] == 2] == [1.0, 1.0]
    assert all(np.isnan(r["support_arms"]) for r in rows if r["k"] == 0)
    assert all("episodes" not in r for r in rows)
    # keep_episodes: the same rows, each with its evaluation episodes (where and how each one ended)
    # the episode-end hook is called once per episode, with the env, and its dict joins that episode's row
    calls = iter(range(1, 100))
    kept = evaluate_adaptation(model, ENV_ID, tasks, n_support=16, k_values=[0, 2], n_eval_episodes=1,
                               env_kwargs=ENV_KWARGS, keep_episodes=True,
                               at_episode_end=lambda env: {"call": next(calls), "arms": len(env.unwrapped.arms)})
    assert [row["episodes"][0]["call"] for row in kept] == list(range(1, len(kept) + 1))
    assert all(row["episodes"][0]["arms"] == 3 for row in kept)
    timed = ("episodes", "adapt_time_s", "support_arms")  # support_arms is NaN at K = 0 (checked above)
    assert [{k: v for k, v in r.items() if k not in timed} for r in kept] == [
        {k: v for k, v in r.items() if k not in timed} for r in rows]
    for row in kept:
        (episode,) = row["episodes"]
        assert episode["outcome"] in ("success", "collision", "timeout")
        assert episode["success"] == row["success_rate"] and episode["collision"] == row["collision_rate"]


def test_per_arm_support_shows_every_arm_of_the_task(model):
    task = Instruction.from_arms([2, 3, 2], targets=[(0.05, 0.0, 0.25), (0.0, 0.05, 0.3), (0.05, 0.0, 0.25)])
    parts = per_arm_tasks(task)
    assert [part.to_code() for part in parts] == ["2", "3"]
    assert np.allclose(parts[1].targets, [[0.0, 0.05, 0.3]])
    env = gym.make(ENV_ID, **ENV_KWARGS)
    support = collect_support(model, env, parts, 17, seed=0)
    assert len(support) == 17 and support_coverage(support, task, n_arms=3) == 1.0
    assert support.episode_ends[8] == 1.0  # the first task's share (9 steps) ends its episode
    rows = evaluate_adaptation(model, ENV_ID, [task], n_support=16, k_values=[1], env_kwargs=ENV_KWARGS,
                               support="per-arm")
    assert rows[0]["support_arms"] == 1.0
    with pytest.raises(ValueError, match="support must be one of"):
        evaluate_adaptation(model, ENV_ID, [task], n_support=16, k_values=[1], support="all")
    with pytest.raises(ValueError, match="at least one per task"):
        collect_support(model, env, parts, 1, seed=0)


def test_support_coverage_counts_the_arms_seen_executing():
    def observation(phases):  # three arms, five numbers each: position, distance, phase
        return np.concatenate([[0.0, 0.0, 0.0, 0.3, phase] for phase in phases])

    def support(*phase_rows):
        obs = np.array([observation(phases) for phases in phase_rows], dtype=np.float32)
        zeros = np.zeros(len(obs), dtype=np.float32)
        return SupportSet(obs, np.zeros((len(obs), 9)), zeros, obs, zeros, zeros, zeros, zeros)

    # arm 2 executes the first waypoint and never completes it: arms 3 and 1 of "2,3,1,3" stay unseen
    stuck = support((0, 1, 0), (0, 1, 0))
    assert support_coverage(stuck, "2,3,1,3", n_arms=3) == pytest.approx(1 / 3)
    moving_on = support((0, 1, 0), (0, 2, 1), (1, 2, 2))
    assert support_coverage(moving_on, "2,3,1,3", n_arms=3) == 1.0
    assert support_coverage(stuck, "2", n_arms=3) == 1.0
    assert support_coverage(stuck, "1", n_arms=3) == 0.0


def test_inner_step_is_bounded_when_the_critic_scale_is_off(model):
    """Regression: with targets far from Q, an unclipped, uncentred inner step moved Q by orders of magnitude."""
    batch = random_batch(32, torch.Generator().manual_seed(3))
    targets = 1000.0 + batch["targets"]
    actor0, critic0 = parameters_of(model.actor_distribution, True), parameters_of(model.critic, True)
    lrs = (torch.tensor(0.01), torch.tensor(0.005))

    def q_shift(max_norm, centered):
        _, critic1 = inner_adapt(model.actor_distribution, model.critic, actor0, critic0, batch["observations"],
                                 batch["actions"], targets, torch.tensor(0.1), *lrs, 1, False, max_norm, centered)
        q0 = functional_call(model.critic, critic0, (batch["observations"], batch["actions"]))[0]
        q1 = functional_call(model.critic, critic1, (batch["observations"], batch["actions"]))[0]
        return float((q1 - q0).abs().max())

    assert q_shift(None, False) > 10.0  # the failure mode is real on this net
    assert q_shift(1.0, True) < 1.0
    grads = clip_gradients({"a": torch.full((3,), 10.0), "b": torch.full((4,), -10.0)}, 2.0)
    assert abs(float(torch.sqrt(sum(g.pow(2).sum() for g in grads.values()))) - 2.0) < 1e-4
