"""Parameter-sharing building blocks for the MARL baselines: the 3 agents live inside one 15-D / 9-D gymnasium env.

The joint observation is ``NUM_ARMS`` local blocks of ``OBS_PER_ARM`` numbers (``vafn_gym.constants.obs_slice``) and the
joint action is ``NUM_ARMS`` blocks of ``ACTION_PER_ARM`` numbers. A *decentralised* actor reshapes ``(B, OBS_DIM)`` to
``(B, NUM_ARMS, OBS_PER_ARM)``, appends a one-hot agent id, runs one shared MLP on every agent independently and maps each
agent's latent to that agent's action block with one shared head. Agent ``i``'s action therefore depends on agent ``i``'s
local observation only (the Jacobian block ``d a_i / d o_j`` is exactly zero for ``j != i``; ``tests/test_baselines.py``
checks it), and the number of parameters does not grow with the number of agents. This is the parameter sharing with
agent ids used by ``marlbenchmark/on-policy`` (``share_policy=True``) and ``oxwhirl/facmac`` (``agent_id`` inputs).
"""

from __future__ import annotations

import math
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.sac.policies import Actor as SACActor
from stable_baselines3.sac.policies import SACPolicy
from stable_baselines3.td3.policies import Actor as TD3Actor
from torch import nn

from vafn_gym.constants import ACTION_DIM, ACTION_PER_ARM, NUM_ARMS, OBS_DIM, OBS_PER_ARM

#: Numerical guard of the tanh log-det correction; the same constant as SB3's ``TanhBijector.log_prob_correction``.
TANH_EPS = 1e-6


def check_joint_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> None:
    """Raise a clear error unless the spaces are the 15-D joint observation and 9-D joint action of the VAFN envs.

    :param observation_space: the env's observation space.
    :param action_space: the env's action space.
    """
    if not isinstance(observation_space, spaces.Box) or observation_space.shape != (OBS_DIM,):
        raise ValueError(
            f"per-agent policies need the {OBS_DIM}-D joint observation ({NUM_ARMS} agents x {OBS_PER_ARM}), "
            f"got {observation_space}; the goal-visible env (18-D) has no per-agent layout"
        )
    if not isinstance(action_space, spaces.Box) or action_space.shape != (ACTION_DIM,):
        raise ValueError(
            f"per-agent policies need the {ACTION_DIM}-D joint action ({NUM_ARMS} agents x {ACTION_PER_ARM}), "
            f"got {action_space}"
        )


def split_agents(joint: th.Tensor, per_agent: int) -> th.Tensor:
    """Reshape a joint tensor ``(B, NUM_ARMS * per_agent)`` to ``(B, NUM_ARMS, per_agent)``.

    :param joint: joint observations or actions.
    :param per_agent: size of one agent's block (``OBS_PER_ARM`` or ``ACTION_PER_ARM``).
    """
    if joint.shape[-1] != NUM_ARMS * per_agent:
        raise ValueError(f"expected last dimension {NUM_ARMS * per_agent}, got shape {tuple(joint.shape)}")
    return joint.reshape(*joint.shape[:-1], NUM_ARMS, per_agent)


def merge_agents(per_agent: th.Tensor) -> th.Tensor:
    """Inverse of :func:`split_agents`: ``(B, NUM_ARMS, d)`` to ``(B, NUM_ARMS * d)``."""
    return per_agent.flatten(-2)


def per_agent_sum(joint: th.Tensor) -> th.Tensor:
    """Sum a per-action-dimension quantity ``(B, ACTION_DIM)`` within each agent's block, giving ``(B, NUM_ARMS)``."""
    return split_agents(joint, ACTION_PER_ARM).sum(-1)


def with_agent_ids(local: th.Tensor) -> th.Tensor:
    """Append a one-hot agent id to per-agent inputs: ``(B, NUM_ARMS, d)`` to ``(B, NUM_ARMS, d + NUM_ARMS)``."""
    ids = th.eye(NUM_ARMS, dtype=local.dtype, device=local.device).expand(*local.shape[:-1], NUM_ARMS)
    return th.cat([local, ids], dim=-1)


def substitute_agent_actions(others: th.Tensor, own: th.Tensor) -> th.Tensor:
    """Joint actions for the per-agent actor losses: copy ``i`` takes agent ``i``'s block from ``own``, the rest from ``others``.

    Gradients flow through ``own``'s block ``i`` in copy ``i`` only; ``others`` is detached. This is the substitution of
    ``oxwhirl/facmac:src/learners/maddpg_learner.py`` (``tem_joint_act[:, idx] = agent_outs[:, idx]``) and of
    ``openai/maddpg:maddpg/trainer/maddpg.py`` (``act_input_n[p_index] = act_pd.sample()``).

    :param others: ``(B, ACTION_DIM)`` actions of the other agents (e.g. from the replay buffer).
    :param own: ``(B, ACTION_DIM)`` actions of the current policy.
    :return: ``(NUM_ARMS * B, ACTION_DIM)``, agent-major (rows ``i*B : (i+1)*B`` are copy ``i``).
    """
    batch = own.shape[0]
    # mask[i, 0, d] = 1 where action dimension d belongs to agent i
    mask = th.eye(NUM_ARMS, dtype=own.dtype, device=own.device).repeat_interleave(ACTION_PER_ARM, 1).unsqueeze(1)
    joint = mask * own.unsqueeze(0) + (1.0 - mask) * others.detach().unsqueeze(0)
    return joint.reshape(NUM_ARMS * batch, ACTION_DIM)


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
    """One MLP applied to every agent's (local observation, one-hot id): ``(B, OBS_DIM)`` to ``(B, NUM_ARMS, h)``.

    :param net_arch: hidden layer widths (``h`` is the last one).
    :param activation_fn: activation class.
    :param layer_norm: on-policy-style LayerNorms (see :func:`mlp_layers`).
    """

    def __init__(self, net_arch: list[int], activation_fn: type[nn.Module] = nn.ReLU, layer_norm: bool = False) -> None:
        super().__init__()
        if not net_arch:
            raise ValueError("a shared agent MLP needs at least one hidden layer")
        self.net, self.latent_dim = mlp_layers(OBS_PER_ARM + NUM_ARMS, net_arch, activation_fn, layer_norm)

    def forward(self, obs: th.Tensor) -> th.Tensor:
        """Per-agent latents ``(B, NUM_ARMS, h)`` of joint observations ``(B, OBS_DIM)``."""
        return self.net(with_agent_ids(split_agents(obs, OBS_PER_ARM)))


class AgentHead(nn.Module):
    """One linear head shared by all agents: latents ``(B, NUM_ARMS, h)`` to a joint vector ``(B, NUM_ARMS * out)``.

    :param latent_dim: per-agent latent width ``h``.
    :param out_per_agent: output width per agent.
    """

    def __init__(self, latent_dim: int, out_per_agent: int = ACTION_PER_ARM) -> None:
        super().__init__()
        self.linear = nn.Linear(latent_dim, out_per_agent)

    def forward(self, latent: th.Tensor) -> th.Tensor:
        """Joint output ``(B, NUM_ARMS * out)`` from per-agent latents ``(B, NUM_ARMS, h)``."""
        return merge_agents(self.linear(latent))


class AgentwiseLinear(nn.Module):
    """A linear layer with separate weights per agent: ``(B, NUM_ARMS, d_in)`` to ``(B, NUM_ARMS, d_out)``.

    Equivalent to ``NUM_ARMS`` independent ``nn.Linear`` modules (MAAC's per-agent ``nn.ModuleList`` encoders and
    critic heads) computed in one batched einsum, initialised like ``nn.Linear``.

    :param in_features: input width per agent.
    :param out_features: output width per agent.
    """

    def __init__(self, in_features: int, out_features: int) -> None:
        super().__init__()
        bound = 1.0 / math.sqrt(in_features)
        self.weight = nn.Parameter(th.empty(NUM_ARMS, in_features, out_features).uniform_(-bound, bound))
        self.bias = nn.Parameter(th.empty(NUM_ARMS, out_features).uniform_(-bound, bound))

    def forward(self, x: th.Tensor) -> th.Tensor:
        """Apply agent ``i``'s weights to ``x[:, i]``."""
        return th.einsum("bni,nio->bno", x, self.weight) + self.bias


def _require_flat_features(features_extractor: nn.Module, use_sde: bool = False) -> None:
    if not isinstance(features_extractor, FlattenExtractor):
        raise ValueError(
            "decentralised actors read each agent's slice of the raw observation; use the default FlattenExtractor, "
            f"got {type(features_extractor).__name__}"
        )
    if use_sde:
        raise ValueError("gSDE exploration is not supported by the per-agent actors (its noise matrix mixes agents)")


class SquashedAgentActor(SACActor):
    """Decentralised, parameter-shared SAC actor: each agent's tanh-Gaussian depends on its own local obs + id only.

    Built by SB3's ``Actor`` constructor, then ``latent_pi``/``mu``/``log_std`` are replaced by the shared per-agent
    network, so SB3's ``forward``, ``action_log_prob``, SAC training and save/load work unchanged. Constructor
    parameters are SB3's ``sac.policies.Actor``'s.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _require_flat_features(self.features_extractor, self.use_sde)
        check_joint_spaces(self.observation_space, self.action_space)
        self.latent_pi = SharedAgentMLP(self.net_arch, self.activation_fn)
        self.mu = AgentHead(self.latent_pi.latent_dim)
        self.log_std = AgentHead(self.latent_pi.latent_dim)  # type: ignore[assignment]

    def agent_action_log_prob(self, obs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Reparameterised joint actions ``(B, ACTION_DIM)`` and each agent's own log-probability ``(B, NUM_ARMS)``.

        SB3's squashed Gaussian returns only the joint log-probability; this applies the same tanh correction per
        agent block, so ``log_prob.sum(-1)`` equals SB3's ``action_log_prob``.
        """
        mean_actions, log_std, _ = self.get_action_dist_params(obs)
        distribution = self.action_dist.proba_distribution(mean_actions, log_std).distribution
        gaussian_actions = distribution.rsample()
        actions = th.tanh(gaussian_actions)
        log_prob = distribution.log_prob(gaussian_actions) - th.log(1.0 - actions**2 + TANH_EPS)
        return actions, per_agent_sum(log_prob)


class DeterministicAgentActor(TD3Actor):
    """Decentralised, parameter-shared deterministic actor (MADDPG): ``a_i = tanh(head(mlp(o_i, id_i)))``.

    Constructor parameters are SB3's ``td3.policies.Actor``'s.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _require_flat_features(self.features_extractor)
        check_joint_spaces(self.observation_space, self.action_space)
        latent = SharedAgentMLP(self.net_arch, self.activation_fn)
        self.mu = nn.Sequential(latent, AgentHead(latent.latent_dim), nn.Tanh())


class SharedAgentSACPolicy(SACPolicy):
    """SB3 ``SACPolicy`` whose actor is the decentralised :class:`SquashedAgentActor`; the critic stays SB3's.

    Constructor parameters are SB3's ``SACPolicy``'s.
    """

    actor: SquashedAgentActor

    def make_actor(self, features_extractor: nn.Module | None = None) -> SquashedAgentActor:
        """Build the shared per-agent actor."""
        actor_kwargs = self._update_features_extractor(self.actor_kwargs, features_extractor)
        return SquashedAgentActor(**actor_kwargs).to(self.device)



def clipped_step(loss: th.Tensor, optimizer: th.optim.Optimizer, parameters: list[nn.Parameter], max_norm: float) -> None:
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
