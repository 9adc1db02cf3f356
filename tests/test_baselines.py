"""MARL baselines (MAPPO, MADDPG, MAAC) and MTSAC: structure, per-agent losses, learning, save/load, adaptation."""

import copy

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import configure
from stable_baselines3.common.save_util import recursive_getattr

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_gym.constants import ACTION_DIM, NUM_ARMS, OBS_DIM, action_slice, obs_slice
from vafn_sb3.common.adaptation import Adaptable, evaluate_adaptation, run_episode
from vafn_sb3.common.agents import per_agent_sum, substitute_agent_actions
from vafn_sb3.maac import MAAC
from vafn_sb3.maddpg import MADDPG
from vafn_sb3.mappo import MAPPO
from vafn_sb3.mappo.policies import ValueNorm
from vafn_sb3.mtsac import MTSAC

ENV_ID = "VAFN/ThreeArmReach-v0"
#: An easy fixed instruction: arm 1 reaches its default target while arms 2 and 3 hold still.
EASY_INSTRUCTION = "1"
SEED = 0
EVAL_SEEDS = (100, 101, 102)
TINY = [32, 32]
OFF_POLICY_FAST = dict(learning_starts=500, batch_size=128, train_freq=4, gradient_steps=2, seed=SEED)
#: SAC-family CI runs: a larger step size and a lower initial temperature than SB3's defaults (3e-4, "auto" from 1.0).
SAC_FAST = dict(OFF_POLICY_FAST, learning_rate=1e-3, ent_coef="auto_0.1")

#: Constructors of the CI-sized runs, with the number of env steps each trains for.
ALGORITHMS = {
    "MAPPO": (
        lambda env: MAPPO(env=env, n_steps=512, learning_rate=1e-3, policy_kwargs=dict(net_arch=TINY), seed=SEED),
        3072,
    ),
    # Two critic updates per actor update (TD3's delayed policy update): with MADDPG's 1:1 schedule the deterministic
    # actors saturate within this budget (seed 0: return -46 vs random -4); see the README, "Baselines".
    "MADDPG": (lambda env: MADDPG(env=env, policy_delay=2, policy_kwargs=dict(net_arch=TINY), **OFF_POLICY_FAST), 3000),
    "MAAC": (
        lambda env: MAAC(env=env, policy_kwargs=dict(net_arch=dict(pi=TINY, qf=[32])), **SAC_FAST),
        3000,
    ),
    "MTSAC": (lambda env: MTSAC("MlpPolicy", env=env, policy_kwargs=dict(net_arch=TINY), **SAC_FAST), 3000),
}


def make_env(instruction=EASY_INSTRUCTION):
    return gym.make(ENV_ID, instruction=instruction)


class UniformRandomPolicy:
    """The random baseline: uniform actions in [-1, 1], seeded."""

    def __init__(self, seed):
        self.rng = np.random.default_rng(seed)

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        return self.rng.uniform(-1.0, 1.0, ACTION_DIM).astype(np.float32), None


def mean_return(policy, env):
    return float(np.mean([run_episode(policy, env, seed=seed)["return"] for seed in EVAL_SEEDS]))


@pytest.fixture(scope="module", params=list(ALGORITHMS))
def trained(request):
    """One CI-sized training run per algorithm on the easy instruction, shared by the tests below."""
    make_model, steps = ALGORITHMS[request.param]
    env = make_env()
    model = make_model(env)
    model.learn(steps)
    yield request.param, model, env
    env.close()


# --- structure -------------------------------------------------------------------------------------------------------


def untrained_actor_means():
    """Deterministic joint action as a differentiable function of one joint observation, for each decentralised actor."""
    env = make_env()
    mappo = MAPPO(env=env, n_steps=64, policy_kwargs=dict(net_arch=TINY), seed=SEED)
    maddpg = MADDPG(env=env, policy_kwargs=dict(net_arch=TINY), seed=SEED)
    maac = MAAC(env=env, policy_kwargs=dict(net_arch=dict(pi=TINY, qf=[32])), seed=SEED)
    mtsac = MTSAC("SharedAgentPolicy", env=env, policy_kwargs=dict(net_arch=TINY), seed=SEED)
    env.close()
    return {
        "MAPPO": lambda o: mappo.policy.get_distribution(o).distribution.mean,
        "MADDPG": lambda o: maddpg.actor(o),
        "MAAC mean": lambda o: maac.actor.get_action_dist_params(o)[0],
        "MAAC log_std": lambda o: maac.actor.get_action_dist_params(o)[1],
        "MTSAC shared": lambda o: mtsac.actor.get_action_dist_params(o)[0],
    }


def test_actions_have_zero_jacobian_wrt_other_agents_observations():
    obs = th.rand(1, OBS_DIM)
    for name, actor in untrained_actor_means().items():
        jacobian = th.autograd.functional.jacobian(lambda o: actor(o)[0], obs)[:, 0, :]  # (ACTION_DIM, OBS_DIM)
        for i in range(1, NUM_ARMS + 1):
            for j in range(1, NUM_ARMS + 1):
                block = jacobian[action_slice(i), obs_slice(j)]
                if i == j:
                    assert block.abs().sum() > 0, f"{name}: agent {i}'s action ignores its own observation"
                else:
                    assert th.equal(block, th.zeros_like(block)), f"{name}: agent {i}'s action reads agent {j}'s obs"


def test_actor_has_one_head_for_all_agents():
    """Parameter sharing: the output layer maps one agent's latent to one agent's action block."""
    env = make_env()
    model = MADDPG(env=env, policy_kwargs=dict(net_arch=TINY), seed=SEED)
    env.close()
    head = [m for m in model.actor.mu.modules() if isinstance(m, th.nn.Linear)][-1]
    assert head.out_features == ACTION_DIM // NUM_ARMS  # one head for all agents, not one per agent


def test_substitution_routes_gradient_to_own_block_only():
    own = th.randn(4, ACTION_DIM, requires_grad=True)
    others = th.randn(4, ACTION_DIM, requires_grad=True)
    joint = substitute_agent_actions(others, own).view(NUM_ARMS, 4, ACTION_DIM)
    for i in range(1, NUM_ARMS + 1):
        copy_i = joint[i - 1]
        assert th.equal(copy_i[:, action_slice(i)], own[:, action_slice(i)])
        grad = th.autograd.grad(copy_i.sum(), own, retain_graph=True)[0]
        assert grad[:, action_slice(i)].eq(1).all() and grad.sum() == grad[:, action_slice(i)].sum()
        rest = [d for d in range(ACTION_DIM) if d not in range(*action_slice(i).indices(ACTION_DIM))]
        assert th.equal(copy_i[:, rest], others[:, rest])
    assert th.autograd.grad(joint.sum(), others, allow_unused=True)[0] is None  # other agents' actions are detached


def test_maddpg_actor_loss_uses_buffered_actions_of_other_agents(monkeypatch):
    """In agent i's actor term the critic sees mu_i(o_i) in block i and the *replay-buffer* actions elsewhere."""
    env = make_env()
    model = MADDPG(env=env, policy_kwargs=dict(net_arch=TINY), learning_starts=50, seed=SEED)
    model.learn(50)  # fills the buffer, no update yet
    env.close()
    seen = {}
    sample, q1_forward = model.replay_buffer.sample, model.critic.q1_forward
    monkeypatch.setattr(model.replay_buffer, "sample", lambda *a, **k: seen.setdefault("data", sample(*a, **k)))

    def spy_q1_forward(obs, actions):
        seen["joint"] = actions
        return q1_forward(obs, actions)

    monkeypatch.setattr(model.critic, "q1_forward", spy_q1_forward)
    batch = 16
    model.set_logger(configure(folder=None, format_strings=[]))
    model.train(gradient_steps=1, batch_size=batch)
    data, joint = seen["data"], seen["joint"].detach().view(NUM_ARMS, batch, ACTION_DIM)
    for i in range(1, NUM_ARMS + 1):
        for j in range(1, NUM_ARMS + 1):
            if j != i:
                th.testing.assert_close(joint[i - 1][:, action_slice(j)], data.actions[:, action_slice(j)])
    assert not th.allclose(joint[0][:, action_slice(1)], data.actions[:, action_slice(1)])


def test_squashed_per_agent_log_probs_sum_to_sb3_joint_log_prob():
    env = make_env()
    model = MAAC(env=env, policy_kwargs=dict(net_arch=dict(pi=TINY, qf=[32])), seed=SEED)
    env.close()
    obs = th.rand(16, OBS_DIM)
    th.manual_seed(1)
    actions, agent_log_prob = model.actor.agent_action_log_prob(obs)
    th.manual_seed(1)
    sb3_actions, sb3_log_prob = model.actor.action_log_prob(obs)
    assert agent_log_prob.shape == (16, NUM_ARMS)
    th.testing.assert_close(actions, sb3_actions)
    th.testing.assert_close(agent_log_prob.sum(-1), sb3_log_prob, rtol=1e-4, atol=1e-4)


def test_maac_critic_gives_one_q_per_agent_and_reads_only_own_action_directly():
    env = make_env()
    model = MAAC(env=env, policy_kwargs=dict(net_arch=dict(pi=TINY, qf=[32])), seed=SEED)
    env.close()
    obs, actions = th.rand(5, OBS_DIM), th.rand(5, ACTION_DIM)
    q_values = model.critic(obs, actions)
    assert len(q_values) == 2 and all(q.shape == (5, NUM_ARMS) for q in q_values)
    q, logits = model.critic.forward_with_logits(obs, actions)[0]
    assert logits.shape[-2:] == (NUM_ARMS, NUM_ARMS - 1)  # each agent attends over the others only


def test_maac_own_action_q_equals_per_agent_substitution():
    """The one-pass actor-loss Q_i (others detached) has the values and action gradients of N substituted copies."""
    env = make_env()
    model = MAAC(env=env, policy_kwargs=dict(net_arch=dict(pi=TINY, qf=[32])), seed=SEED)
    env.close()
    obs = th.rand(6, OBS_DIM)
    actions = (th.rand(6, ACTION_DIM) * 2 - 1).requires_grad_(True)
    own_q = model.critic.own_action_q(obs, actions)[0]
    own_grad = th.autograd.grad(own_q.sum(), actions)[0]
    copies = model.critic(obs.repeat(NUM_ARMS, 1), substitute_agent_actions(actions, actions))[0]
    substituted = copies.view(NUM_ARMS, 6, NUM_ARMS).diagonal(dim1=0, dim2=2)  # Q_i from copy i
    substituted_grad = th.autograd.grad(substituted.sum(), actions)[0]
    th.testing.assert_close(own_q, substituted)
    th.testing.assert_close(own_q, model.critic(obs, actions)[0])
    th.testing.assert_close(own_grad, substituted_grad)


def test_mappo_per_agent_ratios_start_at_one_and_sum_to_joint_log_prob():
    env = make_env()
    model = MAPPO(env=env, n_steps=64, policy_kwargs=dict(net_arch=TINY), seed=SEED)
    _, callback = model._setup_learn(64)
    model.collect_rollouts(model.env, callback, model.rollout_buffer, n_rollout_steps=64)
    model._prepare_rollout()
    env.close()
    data = next(model.rollout_buffer.get(model.batch_size))
    with th.no_grad():
        _, agent_log_prob, entropy = model.policy.evaluate_agent_actions(data.observations, data.actions)
    assert agent_log_prob.shape == entropy.shape == (64, NUM_ARMS)
    th.testing.assert_close(th.exp(agent_log_prob - data.old_agent_log_prob), th.ones(64, NUM_ARMS))
    th.testing.assert_close(data.old_agent_log_prob.sum(-1), data.old_log_prob)  # SB3's stored joint log-prob
    assert per_agent_sum(th.ones(1, ACTION_DIM)).tolist() == [[ACTION_DIM / NUM_ARMS] * NUM_ARMS]


def test_value_norm_matches_on_policy_statistics():
    """One update gives the batch mean/variance exactly (debiased EMA); normalise and denormalise are inverses."""
    value_norm = ValueNorm()
    returns = th.randn(500) * 2.0 + 5.0
    value_norm.update(returns)
    mean, var = value_norm.mean_var()
    th.testing.assert_close(mean, returns.mean(), rtol=1e-3, atol=1e-3)
    th.testing.assert_close(var, returns.var(unbiased=False), rtol=1e-3, atol=1e-3)
    th.testing.assert_close(value_norm.denormalize(value_norm.normalize(returns)), returns)
    value_norm.update(th.full((500,), 5.0))
    assert value_norm.mean_var()[1] > 0  # variance floored, never zero


def test_spaces_without_the_per_agent_layout_are_rejected():
    env = gym.make("VAFN/ThreeArmReachGoal-v0")
    for make_model in (lambda: MAPPO(env=env, n_steps=64), lambda: MADDPG(env=env), lambda: MAAC(env=env)):
        with pytest.raises(ValueError, match="joint observation"):
            make_model()
    env.close()
    with pytest.raises(ValueError, match="num_mini_batch"):
        MAPPO(env=make_env(), batch_size=64, num_mini_batch=4)


# --- learning, save/load, adaptation (one training run per algorithm) ------------------------------------------------


def test_short_run_beats_random_policy(trained):
    name, model, env = trained
    learned = mean_return(model, env)
    random = mean_return(UniformRandomPolicy(SEED), env)
    assert learned > random, f"{name}: deterministic return {learned:.2f} does not beat random {random:.2f}"


def test_save_load_predict(trained, tmp_path):
    name, model, env = trained
    model.save(tmp_path / name)
    loaded = type(model).load(tmp_path / name, env=env)
    obs = np.stack([env.reset(seed=seed)[0] for seed in EVAL_SEEDS])
    np.testing.assert_allclose(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    assert loaded.predict(obs[0], deterministic=False)[0].shape == (ACTION_DIM,)


def test_adapt_fine_tunes_a_copy_and_leaves_the_model_unchanged(trained):
    name, model, env = trained
    assert isinstance(model, Adaptable)
    before = {key: value.clone() for key, value in model.policy.state_dict().items()}
    optimizer_names = [name for name in model._get_torch_save_params()[0] if name != "policy"]
    optimizers_before = {name: copy.deepcopy(recursive_getattr(model, name).state_dict()) for name in optimizer_names}
    variables_before = {name: recursive_getattr(model, name).clone() for name in model._get_torch_save_params()[1]}
    buffers = {name: model.__dict__.get(name) for name in ("replay_buffer", "rollout_buffer")}
    n_updates = model._n_updates
    adapted = model.adapt(env, task="2,1", n_support=40, k=2, seed=SEED)
    again = model.adapt(env, task="2,1", n_support=40, k=2, seed=SEED)
    after = model.policy.state_dict()
    assert all(th.equal(before[key], after[key]) for key in before), f"{name}: adapt changed the model"
    assert model._n_updates == n_updates
    assert all(th.equal(value, recursive_getattr(model, name)) for name, value in variables_before.items())
    for name, state in optimizers_before.items():
        after_state = recursive_getattr(model, name).state_dict()
        for param_id, param_state in state["state"].items():
            for key, value in param_state.items():
                assert th.equal(th.as_tensor(value), th.as_tensor(after_state["state"][param_id][key])), f"{name} changed"
    assert all(model.__dict__.get(name) is buffer for name, buffer in buffers.items())
    changed = [key for key in before if not th.equal(before[key], adapted.state_dict()[key])]
    assert changed, f"{name}: k=2 fine-tuning steps changed no parameter"
    for key, value in adapted.state_dict().items():
        th.testing.assert_close(value, again.state_dict()[key], msg=f"{name}: adapt is not reproducible from its seed")
    obs = env.reset(seed=0)[0]
    assert adapted.predict(obs, deterministic=True)[0].shape == (ACTION_DIM,)


def test_sgd_fine_tuning_variant_swaps_optimisers_only_during_adapt(trained, monkeypatch):
    name, model, env = trained
    before = {key: value.clone() for key, value in model.policy.state_dict().items()}
    optimizers = {n: recursive_getattr(model, n) for n in model._optimizer_names()}
    schedule = model.lr_schedule
    adam = model.adapt(env, task="2,1", n_support=40, k=2, seed=SEED)
    monkeypatch.setattr(model, "finetune_sgd_lr", 1e-2, raising=False)
    sgd = model.adapt(env, task="2,1", n_support=40, k=2, seed=SEED)
    assert all(th.equal(before[key], value) for key, value in model.policy.state_dict().items())
    assert all(recursive_getattr(model, n) is optimizer for n, optimizer in optimizers.items())
    assert model.lr_schedule is schedule
    changed = [k for k in before if not th.equal(before[k], sgd.state_dict()[k])]
    assert changed, f"{name}: SGD fine-tuning changed no parameter"
    assert any(not th.equal(adam.state_dict()[k], sgd.state_dict()[k]) for k in changed), f"{name}: SGD == Adam"


def test_shared_adaptation_protocol_runs_for_every_baseline(trained):
    name, model, _ = trained
    rows = evaluate_adaptation(
        model, ENV_ID, tasks=["2,1"], n_support=20, k_values=[0, 1], n_eval_episodes=1, seed=SEED,
        env_kwargs=dict(max_episode_steps=20),
    )
    assert [row["k"] for row in rows] == [0, 1]
    assert all(np.isfinite(row["return_mean"]) for row in rows)
