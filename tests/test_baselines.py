"""MARL baselines (MAPPO, MADDPG, MAAC) and MTSAC: structure, per-agent losses, learning, save/load, adaptation."""

import copy

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.logger import configure
from stable_baselines3.common.save_util import recursive_getattr

import vafn_gym  # noqa: F401  (registers the env IDs)
from vafn_sb3.common.adaptation import Adaptable, evaluate_adaptation, run_episode
from vafn_sb3.common.agents import (
    AgentLayout,
    SharedAgentSACPolicy,
    frozen,
    nearest_neighbour,
    per_agent_sum,
    shared_actor_for_env,
    substitute_agent_actions,
)
from vafn_sb3.maac import MAAC, MAACPolicy
from vafn_sb3.maddpg import MADDPG, MADDPGPolicy
from vafn_sb3.mappo import MAPPO, MAPPOPolicy
from vafn_sb3.mappo.policies import ValueNorm
from vafn_sb3.mtsac import MTSAC
from vafn_sb3.sac import SAC

ENV_ID = "VAFN/ThreeArmReach-v1"
#: The N-arm env (keyword ``n_arms``) of the tests that need rollouts for several numbers of agents.
MULTI_ENV_ID = "VAFN/MultiArmReach-v1"
#: Numbers of agents the network tests run with.
N_AGENTS = (2, 3, 4, 6)
#: Per-agent block sizes of the VAFN envs: [ee_pos(3), distance, phase] and an end-effector velocity.
OBS_PER_AGENT, ACTION_PER_AGENT = 5, 3
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
    # actors saturate within this budget (seed 0: return -46 vs random -4); see docs/algorithms.md, "Baselines".
    "MADDPG": (lambda env: MADDPG(env=env, policy_delay=2, policy_kwargs=dict(net_arch=TINY), **OFF_POLICY_FAST), 3000),
    "MAAC": (
        lambda env: MAAC(env=env, policy_kwargs=dict(net_arch=dict(pi=TINY, qf=[32])), **SAC_FAST),
        3000,
    ),
    "MTSAC": (lambda env: MTSAC("MlpPolicy", env=env, policy_kwargs=dict(net_arch=TINY), **SAC_FAST), 3000),
}


def make_env(instruction=EASY_INSTRUCTION):
    return gym.make(ENV_ID, instruction=instruction)


def make_multi_env(n_agents):
    return gym.make(MULTI_ENV_ID, n_arms=n_agents, instruction=EASY_INSTRUCTION)


def joint_spaces(n_agents, obs_per_agent=OBS_PER_AGENT):
    """The joint Box spaces of ``n_agents`` arms, without building an env."""
    return (
        spaces.Box(-1.0, 1.0, (n_agents * obs_per_agent,), np.float32),
        spaces.Box(-1.0, 1.0, (n_agents * ACTION_PER_AGENT,), np.float32),
    )


def agent_block(i, per_agent):
    return slice(i * per_agent, (i + 1) * per_agent)


class UniformRandomPolicy:
    """The random baseline: uniform actions in [-1, 1], seeded."""

    def __init__(self, seed, action_dim):
        self.rng = np.random.default_rng(seed)
        self.action_dim = action_dim

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        return self.rng.uniform(-1.0, 1.0, self.action_dim).astype(np.float32), None


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


def lr_schedule(_):
    return 1e-3


def untrained_policies(n_agents, agent_ids=True, neighbours=False):
    """Each decentralised-actor policy, built on ``n_agents``' joint spaces."""
    th.manual_seed(SEED)
    observation_space, action_space = joint_spaces(n_agents)
    kwargs = dict(agent_ids=agent_ids, neighbours=neighbours)
    return {
        "MAPPO": MAPPOPolicy(observation_space, action_space, lr_schedule, net_arch=TINY, **kwargs),
        "MADDPG": MADDPGPolicy(observation_space, action_space, lr_schedule, net_arch=TINY, **kwargs),
        "MAAC": MAACPolicy(observation_space, action_space, lr_schedule, net_arch=dict(pi=TINY, qf=[32]), **kwargs),
        "MTSAC shared": SharedAgentSACPolicy(observation_space, action_space, lr_schedule, net_arch=TINY, **kwargs),
    }


def actor_means(policies):
    """Deterministic joint action as a differentiable function of joint observations, for each decentralised actor."""
    return {
        "MAPPO": lambda o: policies["MAPPO"].get_distribution(o).distribution.mean,
        "MADDPG": lambda o: policies["MADDPG"].actor(o),
        "MAAC mean": lambda o: policies["MAAC"].actor.get_action_dist_params(o)[0],
        "MAAC log_std": lambda o: policies["MAAC"].actor.get_action_dist_params(o)[1],
        "MTSAC shared": lambda o: policies["MTSAC shared"].actor.get_action_dist_params(o)[0],
    }


def actor_parameters(name, policy):
    if name == "MAPPO":
        return policy.actor_parameters()
    return list(policy.actor.parameters())


@pytest.mark.parametrize("agent_ids", [True, False])
@pytest.mark.parametrize("n_agents", N_AGENTS)
def test_actions_have_zero_jacobian_wrt_other_agents_observations(n_agents, agent_ids):
    obs = th.rand(1, n_agents * OBS_PER_AGENT)
    for name, actor in actor_means(untrained_policies(n_agents, agent_ids)).items():
        # (action_dim, obs_dim)
        jacobian = th.autograd.functional.jacobian(lambda o, actor=actor: actor(o)[0], obs)[:, 0, :]
        assert jacobian.shape == (n_agents * ACTION_PER_AGENT, n_agents * OBS_PER_AGENT)
        for i in range(n_agents):
            for j in range(n_agents):
                block = jacobian[agent_block(i, ACTION_PER_AGENT), agent_block(j, OBS_PER_AGENT)]
                if i == j:
                    assert block.abs().sum() > 0, f"{name}: agent {i}'s action ignores its own observation"
                else:
                    assert th.equal(block, th.zeros_like(block)), f"{name}: agent {i}'s action reads agent {j}'s obs"


def test_nearest_neighbour_summary():
    positions = th.tensor([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, -0.1, 0.0]])
    local = th.cat([positions, th.rand(3, 2)], dim=-1).unsqueeze(0)  # one batch row, 3 agents, [p, d, phase]
    summary = nearest_neighbour(local)[0]
    th.testing.assert_close(summary[0], th.tensor([0.0, -0.1, 0.0, 0.1]))  # agent 0's nearest is agent 2
    th.testing.assert_close(summary[1], th.tensor([-0.3, 0.0, 0.0, 0.3]))  # agent 1's nearest is agent 0
    th.testing.assert_close(summary[2], th.tensor([0.0, 0.1, 0.0, 0.1]))
    assert th.equal(nearest_neighbour(local[:, :1]), th.zeros(1, 1, 4))


@pytest.mark.parametrize("n_agents", [3, 4])
def test_neighbour_inputs_read_only_the_nearest_other_agents_position(n_agents):
    """With ``neighbours=True`` agent i also reads the position (and nothing else) of its nearest other agent."""
    obs = th.rand(1, n_agents * OBS_PER_AGENT)
    nearest = nearest_neighbour(obs.view(1, n_agents, OBS_PER_AGENT))[0]
    for name, actor in actor_means(untrained_policies(n_agents, agent_ids=False, neighbours=True)).items():
        jacobian = th.autograd.functional.jacobian(lambda o, actor=actor: actor(o)[0], obs)[:, 0, :]
        for i in range(n_agents):
            positions = obs.view(n_agents, OBS_PER_AGENT)[:, :3]
            distances = (positions - positions[i]).norm(dim=-1)
            distances[i] = float("inf")
            j_near = int(distances.argmin())
            assert th.isclose(nearest[i, 3], distances[j_near])
            for j in range(n_agents):
                block = jacobian[agent_block(i, ACTION_PER_AGENT), agent_block(j, OBS_PER_AGENT)]
                if j == j_near:
                    assert block[:, :3].abs().sum() > 0, f"{name}: agent {i} ignores its nearest neighbour {j}"
                    assert th.equal(block[:, 3:], th.zeros_like(block[:, 3:])), f"{name}: reads more than positions"
                elif j != i:
                    assert th.equal(block, th.zeros_like(block)), f"{name}: agent {i} reads agent {j}'s obs"


def test_neighbours_option_is_saved_with_the_policy():
    policy = untrained_policies(3, neighbours=True)["MTSAC shared"]
    assert policy._get_constructor_parameters()["neighbours"] is True
    first = next(m for m in policy.actor.latent_pi.modules() if isinstance(m, th.nn.Linear))
    assert first.in_features == OBS_PER_AGENT + 3 + 4  # own block, one-hot id of 3 agents, neighbour summary


def test_actor_parameters_do_not_depend_on_the_number_of_agents_without_ids():
    """Parameter sharing: with agent ids only the id inputs grow with N; without them the actor is the same size."""
    for agent_ids in (True, False):
        sizes = {
            n: {name: sum(p.numel() for p in actor_parameters(name, policy))
                for name, policy in untrained_policies(n, agent_ids).items()}
            for n in N_AGENTS
        }
        for name in sizes[2]:
            counts = [sizes[n][name] for n in N_AGENTS]
            if agent_ids:  # one extra input weight per hidden unit of the first layer and per extra agent
                assert len(set(counts)) == len(counts), f"{name}: {counts}"
            else:
                assert len(set(counts)) == 1, f"{name}: actor parameter counts {counts} depend on N"


@pytest.mark.parametrize("name", ["MADDPG", "MAAC", "MTSAC shared"])
def test_actor_without_ids_transfers_to_another_number_of_agents(name):
    """A 3-agent actor's weights load into a 6-agent actor, which then acts on each agent's block exactly like it."""
    small, large = untrained_policies(3, agent_ids=False)[name], untrained_policies(6, agent_ids=False)[name]
    large.actor.load_state_dict(small.actor.state_dict())
    obs = th.rand(4, 3 * OBS_PER_AGENT)

    def mean_action(policy, o):
        return policy.actor(o) if name == "MADDPG" else policy.actor.get_action_dist_params(o)[0]

    th.testing.assert_close(mean_action(large, obs.repeat(1, 2)), mean_action(small, obs).repeat(1, 2))


def test_shared_actor_for_env_runs_a_three_arm_actor_on_six_arms():
    """The public transfer call: same action on every arm's block as the 3-arm model; clear errors otherwise."""
    three, six = (gym.make("VAFN/MultiArmReach-v1", n_arms=n, frame="base") for n in (3, 6))
    model = SAC("SharedAgentPolicy", three, policy_kwargs=dict(net_arch=[16], agent_ids=False), buffer_size=10)
    policy = shared_actor_for_env(model, six)
    obs3, _ = three.reset(seed=0)
    obs6 = np.tile(obs3, 2)
    action6 = policy.predict(obs6, deterministic=True)[0]
    np.testing.assert_allclose(action6, np.tile(model.predict(obs3, deterministic=True)[0], 2), atol=1e-5)
    with pytest.raises(ValueError, match="one-hot ids of 3 agents"):
        shared_actor_for_env(SAC("SharedAgentPolicy", three, buffer_size=10), six)
    with pytest.raises(ValueError, match="no shared per-agent actor"):
        shared_actor_for_env(SAC("MlpPolicy", three, buffer_size=10), six)
    with pytest.raises(ValueError, match="do not split"):
        shared_actor_for_env(model, gym.make("VAFN/MultiArmReach-v1", n_arms=6, observe_goal=True))


def test_agent_ids_are_checked_against_the_number_of_agents():
    policy = untrained_policies(3)["MADDPG"]
    with pytest.raises(ValueError, match="one-hot ids of 3 agents but got 6"):
        policy.actor(th.rand(1, 6 * OBS_PER_AGENT))


def test_actor_has_one_head_for_all_agents():
    """Parameter sharing: the output layer maps one agent's latent to one agent's action block."""
    policy = untrained_policies(3)["MADDPG"]
    head = [m for m in policy.actor.mu.modules() if isinstance(m, th.nn.Linear)][-1]
    assert head.out_features == ACTION_PER_AGENT  # one head for all agents, not one per agent


@pytest.mark.parametrize("n_agents", N_AGENTS)
def test_substitution_routes_gradient_to_own_block_only(n_agents):
    action_dim = n_agents * ACTION_PER_AGENT
    own = th.randn(4, action_dim, requires_grad=True)
    others = th.randn(4, action_dim, requires_grad=True)
    joint = substitute_agent_actions(others, own, ACTION_PER_AGENT).view(n_agents, 4, action_dim)
    for i in range(n_agents):
        copy_i, block = joint[i], agent_block(i, ACTION_PER_AGENT)
        assert th.equal(copy_i[:, block], own[:, block])
        grad = th.autograd.grad(copy_i.sum(), own, retain_graph=True)[0]
        assert grad[:, block].eq(1).all() and grad.sum() == grad[:, block].sum()
        rest = [d for d in range(action_dim) if d not in range(*block.indices(action_dim))]
        assert th.equal(copy_i[:, rest], others[:, rest])
    assert th.autograd.grad(joint.sum(), others, allow_unused=True)[0] is None  # other agents' actions are detached


@pytest.mark.parametrize("n_agents", [2, 4])
def test_maddpg_actor_loss_uses_buffered_actions_of_other_agents(monkeypatch, n_agents):
    """In agent i's actor term the critic sees mu_i(o_i) in block i and the *replay-buffer* actions elsewhere."""
    env = make_multi_env(n_agents)
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
    data, joint = seen["data"], seen["joint"].detach().view(n_agents, batch, n_agents * ACTION_PER_AGENT)
    for i in range(n_agents):
        for j in range(n_agents):
            if j != i:
                block = agent_block(j, ACTION_PER_AGENT)
                th.testing.assert_close(joint[i][:, block], data.actions[:, block])
    block = agent_block(0, ACTION_PER_AGENT)
    assert not th.allclose(joint[0][:, block], data.actions[:, block])


@pytest.mark.parametrize("n_agents", N_AGENTS)
def test_squashed_per_agent_log_probs_sum_to_sb3_joint_log_prob(n_agents):
    actor = untrained_policies(n_agents)["MAAC"].actor
    obs = th.rand(16, n_agents * OBS_PER_AGENT)
    th.manual_seed(1)
    actions, agent_log_prob = actor.agent_action_log_prob(obs)
    th.manual_seed(1)
    sb3_actions, sb3_log_prob = actor.action_log_prob(obs)
    assert agent_log_prob.shape == (16, n_agents)
    th.testing.assert_close(actions, sb3_actions)
    th.testing.assert_close(agent_log_prob.sum(-1), sb3_log_prob, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("n_agents", N_AGENTS)
def test_maac_critic_gives_one_q_per_agent_and_reads_only_own_action_directly(n_agents):
    critic = untrained_policies(n_agents)["MAAC"].critic
    obs, actions = th.rand(5, n_agents * OBS_PER_AGENT), th.rand(5, n_agents * ACTION_PER_AGENT)
    q_values = critic(obs, actions)
    assert len(q_values) == 2 and all(q.shape == (5, n_agents) for q in q_values)
    q, logits = critic.forward_with_logits(obs, actions)[0]
    assert logits.shape[-2:] == (n_agents, n_agents - 1)  # each agent attends over the others only


@pytest.mark.parametrize("n_agents", N_AGENTS)
def test_maac_attention_q_equals_per_agent_per_head_loop(n_agents):
    """The batched critic computes MAAC's attention one agent and one head at a time (``utils/critics.py``)."""
    q_net = untrained_policies(n_agents)["MAAC"].critic.q_networks[0]
    obs, actions = th.rand(7, n_agents * OBS_PER_AGENT), th.rand(7, n_agents * ACTION_PER_AGENT)
    q, logits = q_net(obs, actions)
    heads, width = q_net.attend_heads, q_net.head_dim
    with th.no_grad():
        local_obs = obs.view(7, n_agents, OBS_PER_AGENT)
        sa = q_net.sa_encoder(th.cat([local_obs, actions.view(7, n_agents, ACTION_PER_AGENT)], dim=-1))
        s = q_net.state_encoder(local_obs)
        for i in range(n_agents):
            attended = []
            for h in range(heads):
                rows = slice(h * width, (h + 1) * width)
                query = s[:, i] @ q_net.selector_extractor.weight[rows].T
                others = [j for j in range(n_agents) if j != i]
                keys = th.stack([sa[:, j] @ q_net.key_extractor.weight[rows].T for j in others], dim=1)
                values = th.stack([q_net.value_extractor(sa[:, j])[:, rows] for j in others], dim=1)
                head_logits = (keys @ query.unsqueeze(-1)).squeeze(-1)
                th.testing.assert_close(logits[:, h, i], head_logits)
                weights = th.softmax(head_logits / width**0.5, dim=1)
                attended.append((weights.unsqueeze(-1) * values).sum(1))
            head_in = th.cat([sa[:, i], *attended], dim=-1)
            hidden = th.nn.functional.leaky_relu(head_in @ q_net.head[0].weight[i] + q_net.head[0].bias[i])
            th.testing.assert_close(q[:, i], (hidden @ q_net.head[2].weight[i] + q_net.head[2].bias[i]).squeeze(-1))


@pytest.mark.parametrize("n_agents", N_AGENTS)
def test_maac_own_action_q_equals_per_agent_substitution(n_agents):
    """The one-pass actor-loss Q_i (others detached) has the values and action gradients of N substituted copies."""
    critic = untrained_policies(n_agents)["MAAC"].critic
    obs = th.rand(6, n_agents * OBS_PER_AGENT)
    actions = (th.rand(6, n_agents * ACTION_PER_AGENT) * 2 - 1).requires_grad_(True)
    own_q = critic.own_action_q(obs, actions)[0]
    own_grad = th.autograd.grad(own_q.sum(), actions)[0]
    copies = critic(obs.repeat(n_agents, 1), substitute_agent_actions(actions, actions, ACTION_PER_AGENT))[0]
    substituted = copies.view(n_agents, 6, n_agents).diagonal(dim1=0, dim2=2)  # Q_i from copy i
    substituted_grad = th.autograd.grad(substituted.sum(), actions)[0]
    th.testing.assert_close(own_q, substituted)
    th.testing.assert_close(own_q, critic(obs, actions)[0])
    th.testing.assert_close(own_grad, substituted_grad)


@pytest.mark.parametrize("n_agents", [2, 4])
def test_mappo_per_agent_ratios_start_at_one_and_sum_to_joint_log_prob(n_agents):
    env = make_multi_env(n_agents)
    model = MAPPO(env=env, n_steps=64, policy_kwargs=dict(net_arch=TINY), seed=SEED)
    _, callback = model._setup_learn(64)
    model.collect_rollouts(model.env, callback, model.rollout_buffer, n_rollout_steps=64)
    model._prepare_rollout()
    env.close()
    data = next(model.rollout_buffer.get(model.batch_size))
    with th.no_grad():
        _, agent_log_prob, entropy = model.policy.evaluate_agent_actions(data.observations, data.actions)
    assert agent_log_prob.shape == entropy.shape == (64, n_agents)
    th.testing.assert_close(th.exp(agent_log_prob - data.old_agent_log_prob), th.ones(64, n_agents))
    th.testing.assert_close(data.old_agent_log_prob.sum(-1), data.old_log_prob)  # SB3's stored joint log-prob
    ones = th.ones(1, n_agents * ACTION_PER_AGENT)
    assert per_agent_sum(ones, ACTION_PER_AGENT).tolist() == [[float(ACTION_PER_AGENT)] * n_agents]


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


@pytest.mark.parametrize("n_agents", N_AGENTS)
def test_layout_is_inferred_from_the_spaces(n_agents):
    assert AgentLayout.from_spaces(*joint_spaces(n_agents)) == AgentLayout(n_agents, OBS_PER_AGENT, ACTION_PER_AGENT)
    goal_visible = AgentLayout.from_spaces(*joint_spaces(n_agents, obs_per_agent=8))
    assert goal_visible == AgentLayout(n_agents, 8, ACTION_PER_AGENT)
    explicit = AgentLayout.from_spaces(*joint_spaces(n_agents), n_agents=n_agents, obs_per_agent=OBS_PER_AGENT)
    assert explicit.obs_dim == n_agents * OBS_PER_AGENT and explicit.action_dim == n_agents * ACTION_PER_AGENT


@pytest.mark.parametrize(
    ("obs_dim", "action_dim", "kwargs"),
    [
        (16, 9, {}),  # 16 observation numbers do not split into 3 agents
        (15, 10, {}),  # 10 action numbers are not blocks of 3
        (15, 9, {"n_agents": 5}),  # 9 actions do not split into 5 agents
        (15, 9, {"obs_per_agent": 8}),  # 3 agents x 8 != 15
        (20, 12, {"action_per_agent": 2}),  # 6 agents, but 20 observation numbers do not split into 6
    ],
)
def test_inconsistent_layouts_are_rejected_with_the_sizes(obs_dim, action_dim, kwargs):
    observation_space = spaces.Box(-1.0, 1.0, (obs_dim,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (action_dim,), np.float32)
    with pytest.raises(ValueError, match=rf"\({obs_dim} numbers\).*\({action_dim} numbers\)"):
        AgentLayout.from_spaces(observation_space, action_space, **kwargs)
    for policy_class in (MAPPOPolicy, MADDPGPolicy, MAACPolicy, SharedAgentSACPolicy):
        with pytest.raises(ValueError, match="do not split"):
            policy_class(observation_space, action_space, lr_schedule, **kwargs)


def test_algorithms_read_the_layout_from_policy_kwargs():
    env = make_env()
    for make_model in (
        lambda kwargs: MAPPO(env=env, n_steps=64, policy_kwargs=kwargs),
        lambda kwargs: MADDPG(env=env, policy_kwargs=kwargs),
        lambda kwargs: MAAC(env=env, policy_kwargs=kwargs),
        lambda kwargs: MTSAC("SharedAgentPolicy", env=env, policy_kwargs=kwargs),
    ):
        assert make_model(dict(n_agents=3)).policy.agent_layout == AgentLayout(3, OBS_PER_AGENT, ACTION_PER_AGENT)
        with pytest.raises(ValueError, match="into 4 agents"):
            make_model(dict(n_agents=4))
    env.close()
    with pytest.raises(ValueError, match="num_mini_batch"):
        MAPPO(env=make_env(), batch_size=64, num_mini_batch=4)
    with pytest.raises(ValueError, match="at least 2 agents"):
        MAACPolicy(*joint_spaces(1), lr_schedule)


# --- learning, save/load, adaptation (one training run per algorithm) ------------------------------------------------


def test_short_run_beats_random_policy(trained):
    name, model, env = trained
    learned = mean_return(model, env)
    random = mean_return(UniformRandomPolicy(SEED, env.action_space.shape[0]), env)
    assert learned > random, f"{name}: deterministic return {learned:.2f} does not beat random {random:.2f}"


def test_save_load_predict(trained, tmp_path):
    name, model, env = trained
    model.save(tmp_path / name)
    loaded = type(model).load(tmp_path / name, env=env)
    obs = np.stack([env.reset(seed=seed)[0] for seed in EVAL_SEEDS])
    np.testing.assert_allclose(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    assert loaded.predict(obs[0], deterministic=False)[0].shape == env.action_space.shape


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
                after = after_state["state"][param_id][key]
                assert th.equal(th.as_tensor(value), th.as_tensor(after)), f"{name} changed"
    assert all(model.__dict__.get(name) is buffer for name, buffer in buffers.items())
    changed = [key for key in before if not th.equal(before[key], adapted.state_dict()[key])]
    assert changed, f"{name}: k=2 fine-tuning steps changed no parameter"
    for key, value in adapted.state_dict().items():
        th.testing.assert_close(value, again.state_dict()[key], msg=f"{name}: adapt is not reproducible from its seed")
    obs = env.reset(seed=0)[0]
    assert adapted.predict(obs, deterministic=True)[0].shape == env.action_space.shape


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
    assert 0.0 <= rows[1]["support_arms"] <= 1.0  # the fine-tuned copy keeps its support set


def test_frozen_backpropagates_through_a_module_without_its_weight_gradients():
    """An actor loss through a frozen critic: the action gets its gradient, the critic none; flags come back."""
    critic = th.nn.Sequential(th.nn.Linear(3, 4), th.nn.ReLU(), th.nn.Linear(4, 1))
    critic[2].bias.requires_grad_(False)  # a parameter frozen before stays frozen after
    actions = th.rand(5, 3, requires_grad=True)
    with frozen(critic):
        critic(actions).sum().backward()
    assert actions.grad is not None and actions.grad.abs().sum() > 0
    assert all(parameter.grad is None for parameter in critic.parameters())
    assert [parameter.requires_grad for parameter in critic.parameters()] == [True, True, True, False]
    with pytest.raises(RuntimeError, match="inside"), frozen(critic):
        raise RuntimeError("inside")
    assert [parameter.requires_grad for parameter in critic.parameters()] == [True, True, True, False]
