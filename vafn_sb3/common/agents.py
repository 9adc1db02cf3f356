"""Parameter-sharing building blocks for the MARL baselines: N agents live inside one flat gymnasium env.

The joint observation is ``N`` equal local blocks of ``obs_per_agent`` numbers and the joint action ``N`` blocks of
``action_per_agent`` numbers; :class:`AgentLayout` reads ``N`` and the block sizes from the spaces (or from explicit
``policy_kwargs``), so nothing here knows the number of arms. A *decentralised* actor reshapes
``(B, N * obs_per_agent)`` to ``(B, N, obs_per_agent)``, optionally appends a one-hot agent id, runs one shared MLP on
every agent independently and maps each agent's latent to that agent's action block with one shared head. Agent
``i``'s action therefore depends on agent ``i``'s local observation only (the Jacobian block ``d a_i / d o_j`` is
exactly zero for ``j != i``; ``tests/test_baselines.py`` checks it), and the number of parameters does not grow with the
number of agents. With
agent ids (the default) this is the parameter sharing of ``marlbenchmark/on-policy`` (``share_policy=True``) and
``oxwhirl/facmac`` (``agent_id`` inputs); without them (``agent_ids=False``) the actor's parameters do not depend on
``N`` at all, so a trained actor runs on a layout with a different number of arms.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.sac.policies import Actor as SACActor
from stable_baselines3.sac.policies import SACPolicy
from stable_baselines3.td3.policies import Actor as TD3Actor
from torch import nn

#: Numerical guard of the tanh log-det correction; the same constant as SB3's ``TanhBijector.log_prob_correction``.
TANH_EPS = 1e-6
#: Action numbers per agent when neither ``action_per_agent`` nor ``n_agents`` is given (an end-effector velocity).
DEFAULT_ACTION_PER_AGENT = 3


@dataclass(frozen=True)
class AgentLayout:
    """How a flat joint observation and joint action split into ``n_agents`` equal per-agent blocks.

    :param n_agents: number of agents ``N``.
    :param obs_per_agent: observation numbers per agent.
    :param action_per_agent: action numbers per agent.
    """

    n_agents: int
    obs_per_agent: int
    action_per_agent: int

    @property
    def obs_dim(self) -> int:
        """Size of the joint observation."""
        return self.n_agents * self.obs_per_agent

    @property
    def action_dim(self) -> int:
        """Size of the joint action."""
        return self.n_agents * self.action_per_agent

    @classmethod
    def from_spaces(
        cls,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        n_agents: int | None = None,
        obs_per_agent: int | None = None,
        action_per_agent: int | None = None,
    ) -> AgentLayout:
        """The layout of flat Box spaces: missing sizes inferred, given ones checked (``ValueError`` if inconsistent).

        ``n_agents`` defaults to ``action_dim // action_per_agent`` (``action_per_agent`` defaults to
        :data:`DEFAULT_ACTION_PER_AGENT`, or to ``action_dim // n_agents`` when ``n_agents`` is given) and
        ``obs_per_agent`` to ``obs_dim // n_agents``.

        :param observation_space: the env's joint observation space.
        :param action_space: the env's joint action space.
        :param n_agents: number of agents, inferred when None.
        :param obs_per_agent: observation numbers per agent, inferred when None.
        :param action_per_agent: action numbers per agent, inferred when None.
        """
        for name, space in (("observation", observation_space), ("action", action_space)):
            if not isinstance(space, spaces.Box) or len(space.shape) != 1:
                raise ValueError(f"per-agent policies need a flat Box joint {name} space, got {space}")
        obs_dim, action_dim = observation_space.shape[0], action_space.shape[0]
        for name, value in (("n_agents", n_agents), ("obs_per_agent", obs_per_agent),
                            ("action_per_agent", action_per_agent)):
            if value is not None and (not isinstance(value, int) or value < 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if action_per_agent is None:
            action_per_agent = DEFAULT_ACTION_PER_AGENT if n_agents is None else max(action_dim // n_agents, 1)
        if n_agents is None:
            n_agents = max(action_dim // action_per_agent, 1)
        if obs_per_agent is None:
            obs_per_agent = max(obs_dim // n_agents, 1)
        layout = cls(n_agents, obs_per_agent, action_per_agent)
        if layout.obs_dim != obs_dim or layout.action_dim != action_dim:
            raise ValueError(
                f"the joint observation ({obs_dim} numbers) and joint action ({action_dim} numbers) do not split into "
                f"{n_agents} agents x {obs_per_agent} observation numbers and {n_agents} agents x {action_per_agent} "
                "action numbers; pass n_agents / obs_per_agent / action_per_agent in policy_kwargs"
            )
        return layout


def split_agents(joint: th.Tensor, per_agent: int) -> th.Tensor:
    """Reshape a joint tensor ``(B, N * per_agent)`` to ``(B, N, per_agent)``.

    :param joint: joint observations or actions.
    :param per_agent: size of one agent's block.
    """
    if joint.shape[-1] % per_agent != 0:
        raise ValueError(f"last dimension of shape {tuple(joint.shape)} is not a multiple of {per_agent}")
    return joint.reshape(*joint.shape[:-1], joint.shape[-1] // per_agent, per_agent)


def merge_agents(per_agent: th.Tensor) -> th.Tensor:
    """Inverse of :func:`split_agents`: ``(B, N, d)`` to ``(B, N * d)``."""
    return per_agent.flatten(-2)


def per_agent_sum(joint: th.Tensor, per_agent: int) -> th.Tensor:
    """Sum a per-action-dimension quantity ``(B, N * per_agent)`` within each agent's block, giving ``(B, N)``."""
    return split_agents(joint, per_agent).sum(-1)


def with_agent_ids(local: th.Tensor) -> th.Tensor:
    """Append a one-hot agent id to per-agent inputs: ``(B, N, d)`` to ``(B, N, d + N)``."""
    n_agents = local.shape[-2]
    ids = th.eye(n_agents, dtype=local.dtype, device=local.device).expand(*local.shape[:-1], n_agents)
    return th.cat([local, ids], dim=-1)


#: Observation numbers at the start of every agent's block that are its position (the end-effector's x, y, z).
POSITION_DIMS = 3
#: Numbers :func:`nearest_neighbour` appends per agent: the nearest other agent's relative position and its distance.
NEIGHBOUR_DIMS = POSITION_DIMS + 1


def nearest_neighbour(local: th.Tensor) -> th.Tensor:
    """Per-agent summary of the other agents: ``(B, N, d)`` to ``(B, N, 4)``.

    For agent ``i``: the position of the nearest other agent relative to ``i``'s own (the first
    :data:`POSITION_DIMS` numbers of each block) and its distance. It does not depend on the number of agents, so an
    actor that uses it still runs on other arm counts; with a single agent it is all zeros.
    """
    if local.shape[-2] < 2:
        return local.new_zeros(*local.shape[:-1], NEIGHBOUR_DIMS)
    position = local[..., :POSITION_DIMS]
    offsets = position.unsqueeze(-3) - position.unsqueeze(-2)  # [..., i, j, :] = p_j - p_i
    distance = offsets.norm(dim=-1)
    n_agents = local.shape[-2]
    distance = distance + th.eye(n_agents, dtype=local.dtype, device=local.device) * th.finfo(local.dtype).max
    nearest = distance.argmin(dim=-1, keepdim=True)  # [..., i, 1]
    offset = th.gather(offsets, -2, nearest.unsqueeze(-1).expand(*nearest.shape, POSITION_DIMS)).squeeze(-2)
    return th.cat([offset, offset.norm(dim=-1, keepdim=True)], dim=-1)


def substitute_agent_actions(others: th.Tensor, own: th.Tensor, action_per_agent: int) -> th.Tensor:
    """Joint actions for the per-agent actor losses: copy ``i`` has ``own``'s block ``i`` and ``others``' other blocks.

    Gradients flow through ``own``'s block ``i`` in copy ``i`` only; ``others`` is detached. This is the substitution of
    ``oxwhirl/facmac:src/learners/maddpg_learner.py`` (``tem_joint_act[:, idx] = agent_outs[:, idx]``) and of
    ``openai/maddpg:maddpg/trainer/maddpg.py`` (``act_input_n[p_index] = act_pd.sample()``).

    :param others: ``(B, N * action_per_agent)`` actions of the other agents (e.g. from the replay buffer).
    :param own: ``(B, N * action_per_agent)`` actions of the current policy.
    :param action_per_agent: action numbers per agent.
    :return: ``(N * B, N * action_per_agent)``, agent-major (rows ``i*B : (i+1)*B`` are copy ``i``).
    """
    batch, action_dim = own.shape
    n_agents = split_agents(own, action_per_agent).shape[-2]
    # mask[i, 0, d] = 1 where action dimension d belongs to agent i
    mask = th.eye(n_agents, dtype=own.dtype, device=own.device).repeat_interleave(action_per_agent, 1).unsqueeze(1)
    joint = mask * own.unsqueeze(0) + (1.0 - mask) * others.detach().unsqueeze(0)
    return joint.reshape(n_agents * batch, action_dim)


def mlp_layers(
    input_dim: int, net_arch: list[int], activation_fn: type[nn.Module], layer_norm: bool = False
) -> tuple[nn.Sequential, int]:
    """A plain MLP (Linear + activation [+ LayerNorm] per hidden layer); returns the module and its output width.

    :param input_dim: input width.
    :param net_arch: hidden layer widths.
    :param activation_fn: activation class.
    :param layer_norm: LayerNorm on the input and after every hidden activation, as in ``marlbenchmark/on-policy``
        (``onpolicy/algorithms/utils/mlp.py``: ``feature_norm`` + ``MLPLayer``).
    """
    layers: list[nn.Module] = [nn.LayerNorm(input_dim)] if layer_norm else []
    width = input_dim
    for hidden in net_arch:
        layers += [nn.Linear(width, hidden), activation_fn()]
        if layer_norm:
            layers.append(nn.LayerNorm(hidden))
        width = hidden
    return nn.Sequential(*layers), width


class SharedAgentMLP(nn.Module):
    """One MLP applied to every agent's local observation (plus its one-hot id): ``(B, N * d)`` to ``(B, N, h)``.

    :param obs_per_agent: observation numbers per agent ``d``.
    :param net_arch: hidden layer widths (``h`` is the last one).
    :param activation_fn: activation class.
    :param layer_norm: on-policy-style LayerNorms (see :func:`mlp_layers`).
    :param n_agent_ids: number of agents whose one-hot id is appended to every agent's input; 0 appends none, and then
        the parameters do not depend on the number of agents.
    :param neighbours: append :func:`nearest_neighbour` (where the nearest other agent is) to every agent's input.
    """

    def __init__(
        self,
        obs_per_agent: int,
        net_arch: list[int],
        activation_fn: type[nn.Module] = nn.ReLU,
        layer_norm: bool = False,
        n_agent_ids: int = 0,
        neighbours: bool = False,
    ) -> None:
        super().__init__()
        if not net_arch:
            raise ValueError("a shared agent MLP needs at least one hidden layer")
        if neighbours and obs_per_agent < POSITION_DIMS:
            raise ValueError(f"neighbours=True needs each agent's position in its first {POSITION_DIMS} observations")
        self.obs_per_agent = obs_per_agent
        self.n_agent_ids = n_agent_ids
        self.neighbours = neighbours
        in_features = obs_per_agent + n_agent_ids + (NEIGHBOUR_DIMS if neighbours else 0)
        self.net, self.latent_dim = mlp_layers(in_features, net_arch, activation_fn, layer_norm)

    def forward(self, obs: th.Tensor) -> th.Tensor:
        """Per-agent latents ``(B, N, h)`` of joint observations ``(B, N * d)``."""
        local = split_agents(obs, self.obs_per_agent)
        if self.n_agent_ids:
            if local.shape[-2] != self.n_agent_ids:
                raise ValueError(
                    f"this actor appends one-hot ids of {self.n_agent_ids} agents but got {local.shape[-2]} agents; "
                    "build it with agent_ids=False to run it on another number of agents"
                )
            local = with_agent_ids(local)
        if self.neighbours:
            local = th.cat([local, nearest_neighbour(local)], dim=-1)
        return self.net(local)


class AgentHead(nn.Module):
    """One linear head shared by all agents: latents ``(B, N, h)`` to a joint vector ``(B, N * out)``.

    :param latent_dim: per-agent latent width ``h``.
    :param out_per_agent: output width per agent.
    """

    def __init__(self, latent_dim: int, out_per_agent: int) -> None:
        super().__init__()
        self.linear = nn.Linear(latent_dim, out_per_agent)

    def forward(self, latent: th.Tensor) -> th.Tensor:
        """Joint output ``(B, N * out)`` from per-agent latents ``(B, N, h)``."""
        return merge_agents(self.linear(latent))


class AgentwiseLinear(nn.Module):
    """A linear layer with separate weights per agent: ``(B, N, d_in)`` to ``(B, N, d_out)``.

    Equivalent to ``N`` independent ``nn.Linear`` modules (MAAC's per-agent ``nn.ModuleList`` encoders and critic heads)
    computed in one batched matrix product, initialised like ``nn.Linear``.

    :param n_agents: number of agents ``N``.
    :param in_features: input width per agent.
    :param out_features: output width per agent.
    """

    def __init__(self, n_agents: int, in_features: int, out_features: int) -> None:
        super().__init__()
        bound = 1.0 / math.sqrt(in_features)
        self.weight = nn.Parameter(th.empty(n_agents, in_features, out_features).uniform_(-bound, bound))
        self.bias = nn.Parameter(th.empty(n_agents, out_features).uniform_(-bound, bound))

    def forward(self, x: th.Tensor) -> th.Tensor:
        """Apply agent ``i``'s weights to ``x[:, i]``."""
        return th.baddbmm(self.bias.unsqueeze(1), x.transpose(0, 1), self.weight).transpose(0, 1)


def _require_flat_features(features_extractor: nn.Module, use_sde: bool = False) -> None:
    if not isinstance(features_extractor, FlattenExtractor):
        raise ValueError(
            "decentralised actors read each agent's slice of the raw observation; use the default FlattenExtractor, "
            f"got {type(features_extractor).__name__}"
        )
    if use_sde:
        raise ValueError("gSDE exploration is not supported by the per-agent actors (its noise matrix mixes agents)")


class _SharedAgentActorMixin:
    """Builds the per-agent layout and the shared MLP of a decentralised actor after SB3's actor constructor."""

    observation_space: spaces.Box
    action_space: spaces.Box
    net_arch: list[int]
    activation_fn: type[nn.Module]

    def _build_agent_mlp(self, layout: AgentLayout | None, agent_ids: bool, neighbours: bool) -> SharedAgentMLP:
        self.layout = layout or AgentLayout.from_spaces(self.observation_space, self.action_space)
        self.agent_ids = agent_ids
        self.neighbours = neighbours
        n_agent_ids = self.layout.n_agents if agent_ids else 0
        return SharedAgentMLP(
            self.layout.obs_per_agent, self.net_arch, self.activation_fn, n_agent_ids=n_agent_ids, neighbours=neighbours
        )


class SquashedAgentActor(_SharedAgentActorMixin, SACActor):
    """Decentralised, parameter-shared SAC actor: each agent's tanh-Gaussian depends on its own local obs (+ id) only.

    Built by SB3's ``Actor`` constructor, then ``latent_pi``/``mu``/``log_std`` are replaced by the shared per-agent
    network, so SB3's ``forward``, ``action_log_prob``, SAC training and save/load work unchanged. Positional and other
    keyword parameters are SB3's ``sac.policies.Actor``'s, plus:

    :param layout: the per-agent layout (inferred from the spaces when None).
    :param agent_ids: append a one-hot agent id to every agent's input.
    :param neighbours: append where the nearest other agent is (:func:`nearest_neighbour`) to every agent's input.
    """

    def __init__(
        self, *args: Any, layout: AgentLayout | None = None, agent_ids: bool = True, neighbours: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        _require_flat_features(self.features_extractor, self.use_sde)
        self.latent_pi = self._build_agent_mlp(layout, agent_ids, neighbours)
        self.mu = AgentHead(self.latent_pi.latent_dim, self.layout.action_per_agent)
        self.log_std = AgentHead(self.latent_pi.latent_dim, self.layout.action_per_agent)  # type: ignore[assignment]

    def agent_action_log_prob(self, obs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Reparameterised joint actions ``(B, N * action_per_agent)`` and each agent's own log-probability ``(B, N)``.

        SB3's squashed Gaussian returns only the joint log-probability; this applies the same tanh correction per
        agent block, so ``log_prob.sum(-1)`` equals SB3's ``action_log_prob``.
        """
        mean_actions, log_std, _ = self.get_action_dist_params(obs)
        distribution = self.action_dist.proba_distribution(mean_actions, log_std).distribution
        gaussian_actions = distribution.rsample()
        actions = th.tanh(gaussian_actions)
        log_prob = distribution.log_prob(gaussian_actions) - th.log(1.0 - actions**2 + TANH_EPS)
        return actions, per_agent_sum(log_prob, self.layout.action_per_agent)


class DeterministicAgentActor(_SharedAgentActorMixin, TD3Actor):
    """Decentralised, parameter-shared deterministic actor (MADDPG): ``a_i = tanh(head(mlp(o_i[, id_i])))``.

    Positional and other keyword parameters are SB3's ``td3.policies.Actor``'s, plus:

    :param layout: the per-agent layout (inferred from the spaces when None).
    :param agent_ids: append a one-hot agent id to every agent's input.
    :param neighbours: append where the nearest other agent is (:func:`nearest_neighbour`) to every agent's input.
    """

    def __init__(
        self, *args: Any, layout: AgentLayout | None = None, agent_ids: bool = True, neighbours: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        _require_flat_features(self.features_extractor)
        latent = self._build_agent_mlp(layout, agent_ids, neighbours)
        self.mu = nn.Sequential(latent, AgentHead(latent.latent_dim, self.layout.action_per_agent), nn.Tanh())


class AgentLayoutPolicyMixin:
    """Policy mixin taking the per-agent ``policy_kwargs`` and resolving them against the spaces before the build.

    Put it before the SB3 policy class in the bases. Positional and other keyword parameters are the SB3 policy's, plus:

    :param n_agents: number of agents (default: ``action_dim // action_per_agent``).
    :param obs_per_agent: observation numbers per agent (default: ``obs_dim // n_agents``).
    :param action_per_agent: action numbers per agent (default: 3, or ``action_dim // n_agents`` given ``n_agents``).
    :param agent_ids: append a one-hot agent id to the shared actor's input; False makes the actor's parameters
        independent of the number of agents.
    :param neighbours: append where the nearest other agent is (:func:`nearest_neighbour`) to the shared actor's
        input, so each arm can see another coming close (the arms move themselves in ``inactive_arms="policy"``).
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        *args: Any,
        n_agents: int | None = None,
        obs_per_agent: int | None = None,
        action_per_agent: int | None = None,
        agent_ids: bool = True,
        neighbours: bool = False,
        **kwargs: Any,
    ) -> None:
        # Set before the SB3 constructor, whose _build creates the actor from them.
        self.agent_layout = AgentLayout.from_spaces(
            observation_space, action_space, n_agents, obs_per_agent, action_per_agent
        )
        self.agent_ids = bool(agent_ids)
        self.neighbours = bool(neighbours)
        super().__init__(observation_space, action_space, *args, **kwargs)  # type: ignore[call-arg]

    @property
    def n_agent_ids(self) -> int:
        """Width of the one-hot agent id appended to each agent's input (0 without ids)."""
        return self.agent_layout.n_agents if self.agent_ids else 0

    def _agent_actor_kwargs(self, actor_kwargs: dict[str, Any]) -> dict[str, Any]:
        return {**actor_kwargs, "layout": self.agent_layout, "agent_ids": self.agent_ids, "neighbours": self.neighbours}

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()  # type: ignore[misc]
        layout = self.agent_layout
        data.update(n_agents=layout.n_agents, obs_per_agent=layout.obs_per_agent,
                    action_per_agent=layout.action_per_agent, agent_ids=self.agent_ids, neighbours=self.neighbours)
        return data


def shared_actor_for_env(model: Any, env: gym.Env) -> BasePolicy:
    """``model``'s policy rebuilt for ``env``'s number of agents, with the trained shared actor (zero-shot transfer).

    The actor must have been trained without one-hot ids (``agent_ids=False``) on blocks of the same size as
    ``env``'s; its weights are copied unchanged, the critics are fresh (untrained: evaluate, do not fine-tune, the
    result). Returns an SB3 policy in evaluation mode, with SB3's ``predict``.

    :param model: an SB3 model or policy with a per-agent actor (SAC, MTSAC, MAML-SAC, MADDPG, MAAC).
    :param env: the env to run on (its spaces decide the number of agents).
    """
    policy = getattr(model, "policy", model)
    if not isinstance(policy, AgentLayoutPolicyMixin) or not isinstance(getattr(policy, "actor", None), nn.Module):
        raise ValueError(f"{type(policy).__name__} has no shared per-agent actor; only per-agent policies (e.g. "
                         "SharedAgentPolicy) run on another number of agents")
    if policy.agent_ids:
        raise ValueError(f"this actor appends one-hot ids of {policy.agent_layout.n_agents} agents, so it only runs on "
                         f"{policy.agent_layout.n_agents}; train it with policy_kwargs agent_ids=False to transfer it")
    data = policy._get_constructor_parameters()
    # The block sizes stay: from_spaces raises ValueError naming them when env's observation does not split into them.
    data.update(observation_space=env.observation_space, action_space=env.action_space, n_agents=None)
    transferred = type(policy)(**data).to(policy.device)
    transferred.actor.load_state_dict(policy.actor.state_dict())
    transferred.set_training_mode(False)
    return transferred


class SharedAgentSACPolicy(AgentLayoutPolicyMixin, SACPolicy):
    """SB3 ``SACPolicy`` whose actor is the decentralised :class:`SquashedAgentActor`; the critic stays SB3's.

    Parameters are SB3's ``SACPolicy``'s plus the per-agent keywords of :class:`AgentLayoutPolicyMixin`.
    """

    actor: SquashedAgentActor

    def make_actor(self, features_extractor: nn.Module | None = None) -> SquashedAgentActor:
        """Build the shared per-agent actor."""
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return SquashedAgentActor(**self._agent_actor_kwargs(actor_kwargs)).to(self.device)


@contextmanager
def frozen(module: nn.Module) -> Iterator[None]:
    """Within the block ``module``'s parameters take no gradient: a loss built inside backpropagates *through* it.

    An actor loss reads the critic; its weight gradients would be thrown away (the critic's optimiser zeroes them
    before its own step), so not computing them leaves every update unchanged and saves their matrix products.
    """
    flags = [(parameter, parameter.requires_grad) for parameter in module.parameters()]
    for parameter, _ in flags:
        parameter.requires_grad_(False)
    try:
        yield
    finally:
        for parameter, flag in flags:
            parameter.requires_grad_(flag)


def clipped_step(
    loss: th.Tensor, optimizer: th.optim.Optimizer, parameters: list[nn.Parameter], max_norm: float
) -> None:
    """Backpropagate ``loss``, clip the gradient norm of ``parameters`` to ``max_norm`` and take an optimiser step.

    :param loss: scalar loss.
    :param optimizer: optimiser of ``parameters``.
    :param parameters: the parameters whose gradient norm is clipped.
    :param max_norm: largest allowed global gradient norm.
    """
    optimizer.zero_grad()
    loss.backward()
    th.nn.utils.clip_grad_norm_(parameters, max_norm)
    optimizer.step()
