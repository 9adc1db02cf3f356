"""MAAC policy: decentralised shared SAC actors and a continuous-action attention critic (Iqbal & Sha, ICML 2019).

The critic follows ``shariqiqbal2810/MAAC:utils/critics.py`` (``AttentionCritic``):

- per-agent observation-action encoders ``e_i = g_i(o_i, a_i)`` (``critic_encoders``) and per-agent observation encoders
  ``s_i = h_i(o_i)`` (``state_encoders``), one hidden layer with LeakyReLU;
- multi-head attention shared by all agents: the query of agent ``i`` is ``W_q s_i`` (``selector_extractors``), keys and
  values of agent ``j != i`` are ``W_k e_j`` and ``LeakyReLU(W_v e_j)`` (``key_extractors``, ``value_extractors``);
  logits are scaled by ``1/sqrt(d_head)`` and softmaxed over the *other* agents only;
- a per-agent head ``Q_i = f_i([., x_i])`` (``critics``) on the agent's encoding and its attention output ``x_i``.

Continuous actions (MAAC's official code is discrete-only): the reference head reads the *state* encoding ``s_i``
and outputs a Q per discrete action; here the head reads ``e_i``, so agent ``i``'s own action enters ``Q_i`` and
``Q_i`` is a scalar. Per-agent weights are batched in
:class:`~vafn_sb3.common.agents.AgentwiseLinear` (identical to MAAC's ``nn.ModuleList`` per agent). MAAC's
``BatchNorm1d(affine=False)`` input normalisation is omitted (target-network BN-statistics pitfall, SB3 #996). Several
attention critics (``n_critics``, twin by default, as in SB3's SAC) replace MAAC's single critic: an improvement over
the paper, stated as such.
"""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel
from torch import nn

from vafn_sb3.common.agents import AgentLayout, AgentwiseLinear, SharedAgentSACPolicy, split_agents

#: MAAC's default number of attention heads (``main.py``: ``--attend_heads 4``).
DEFAULT_ATTEND_HEADS = 4
#: MAAC's hidden widths (``main.py``: ``pol_hidden_dim=128``, ``critic_hidden_dim=128``).
DEFAULT_NET_ARCH = {"pi": [128, 128], "qf": [128]}


class AttentionQ(nn.Module):
    """One attention critic returning every agent's ``Q_i(o, a)`` and the attention logits.

    :param layout: the per-agent layout (at least two agents: each attends over the others).
    :param hidden_dim: width of the encoders, of the attention (all heads together) and of the head's hidden layer.
    :param attend_heads: number of attention heads (must divide ``hidden_dim``).
    """

    def __init__(self, layout: AgentLayout, hidden_dim: int, attend_heads: int) -> None:
        super().__init__()
        if hidden_dim % attend_heads != 0:
            raise ValueError(f"hidden_dim ({hidden_dim}) must be divisible by attend_heads ({attend_heads})")
        if layout.n_agents < 2:
            raise ValueError(f"the attention critic needs at least 2 agents, got {layout.n_agents}")
        self.layout = layout
        self.attend_heads = attend_heads
        self.head_dim = hidden_dim // attend_heads
        n_agents, obs_per_agent = layout.n_agents, layout.obs_per_agent
        self.sa_encoder = nn.Sequential(
            AgentwiseLinear(n_agents, obs_per_agent + layout.action_per_agent, hidden_dim), nn.LeakyReLU()
        )
        self.state_encoder = nn.Sequential(AgentwiseLinear(n_agents, obs_per_agent, hidden_dim), nn.LeakyReLU())
        # All heads stacked in one matrix: identical to MAAC's per-head nn.Linear(hidden_dim, attend_dim) lists.
        self.key_extractor = nn.Linear(hidden_dim, hidden_dim, bias=False)
        self.selector_extractor = nn.Linear(hidden_dim, hidden_dim, bias=False)
        self.value_extractor = nn.Sequential(nn.Linear(hidden_dim, hidden_dim), nn.LeakyReLU())
        self.head = nn.Sequential(
            AgentwiseLinear(n_agents, 2 * hidden_dim, hidden_dim),
            nn.LeakyReLU(),
            AgentwiseLinear(n_agents, hidden_dim, 1),
        )
        # Row i lists the agents j != i in increasing order (the order of MAAC's per-agent attention).
        others_index = th.arange(n_agents).expand(n_agents, n_agents)[~th.eye(n_agents, dtype=th.bool)]
        self.register_buffer("others_index", others_index, persistent=False)

    def shared_parameters(self) -> list[nn.Parameter]:
        """Parameters whose gradients MAAC scales by ``1/n_agents`` (``AttentionCritic.shared_modules``)."""
        modules = (self.key_extractor, self.selector_extractor, self.value_extractor, self.sa_encoder)
        return [p for module in modules for p in module.parameters()]

    def forward(
        self, obs: th.Tensor, actions: th.Tensor, detach_others: bool = False
    ) -> tuple[th.Tensor, th.Tensor]:
        """Per-agent ``Q (B, N)`` and attention logits ``(B, heads, N, N - 1)``.

        :param obs: joint observations ``(B, N * obs_per_agent)``.
        :param actions: joint actions ``(B, N * action_per_agent)``; agent ``i``'s block enters ``Q_i`` through its own
            encoding.
        :param detach_others: compute the keys and values (what agent ``i`` reads of the agents ``j != i``) from
            detached encodings. This gives every ``Q_i`` a gradient w.r.t. ``a_i`` only, in one forward pass (``Q_i``
            attends over ``j != i`` only, so its sole path to ``a_i`` is ``e_i``).
        """
        n_agents = self.layout.n_agents
        local_obs = split_agents(obs, self.layout.obs_per_agent)
        sa = self.sa_encoder(th.cat([local_obs, split_agents(actions, self.layout.action_per_agent)], dim=-1))
        sa_others = sa.detach() if detach_others else sa
        s = self.state_encoder(local_obs)
        batch = obs.shape[0]
        shape = (batch, n_agents, self.attend_heads, self.head_dim)
        keys = self.key_extractor(sa_others).view(shape)
        values = self.value_extractor(sa_others).view(shape)
        queries = self.selector_extractor(s).view(shape)
        # Agent i's keys and values are those of the agents j != i, gathered once; products and sums replace einsum
        # because with a few agents the per-head matrices are far too small for batched matmul to pay off.
        others = (batch, n_agents, n_agents - 1, self.attend_heads, self.head_dim)
        other_keys = keys.index_select(1, self.others_index).view(others)
        other_values = values.index_select(1, self.others_index).view(others)
        logits = (queries.unsqueeze(2) * other_keys).sum(-1)  # (B, i, j != i, heads)
        weights = th.softmax(logits / self.head_dim**0.5, dim=2)
        attended = (weights.unsqueeze(-1) * other_values).sum(2).reshape(batch, n_agents, -1)
        q = self.head(th.cat([sa, attended], dim=-1)).squeeze(-1)
        return q, logits.permute(0, 3, 1, 2)


class AttentionCritic(BaseModel):
    """``n_critics`` independent :class:`AttentionQ` networks behind SB3's critic interface (``make_critic``).

    :param observation_space: the joint observation space (``N`` blocks of ``obs_per_agent``).
    :param action_space: the joint action space (``N`` blocks of ``action_per_agent``).
    :param net_arch: ``[hidden_dim]`` (MAAC's encoders and heads have one hidden width).
    :param features_extractor: SB3's features extractor (unused: the critic splits the raw joint observation).
    :param features_dim: SB3's features dimension (unused, kept for the ``make_critic`` signature).
    :param activation_fn: SB3's activation argument (unused: MAAC uses LeakyReLU throughout).
    :param normalize_images: SB3 flag (no images here).
    :param n_critics: number of attention critics (twin by default).
    :param share_features_extractor: SB3 flag (the critic has no trainable features extractor).
    :param attend_heads: number of attention heads.
    :param layout: the per-agent layout (inferred from the spaces when None).
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        net_arch: list[int],
        features_extractor: nn.Module,
        features_dim: int,
        activation_fn: type[nn.Module] = nn.LeakyReLU,
        normalize_images: bool = True,
        n_critics: int = 2,
        share_features_extractor: bool = False,
        attend_heads: int = DEFAULT_ATTEND_HEADS,
        layout: AgentLayout | None = None,
    ) -> None:
        super().__init__(observation_space, action_space, features_extractor=features_extractor,
                         normalize_images=normalize_images)
        self.layout = layout or AgentLayout.from_spaces(observation_space, action_space)
        if len(net_arch) != 1:
            raise ValueError(f"the attention critic takes net_arch qf=[hidden_dim] (one width), got {net_arch}")
        self.net_arch = net_arch
        self.n_critics = n_critics
        self.attend_heads = attend_heads
        self.q_networks = nn.ModuleList(AttentionQ(self.layout, net_arch[0], attend_heads) for _ in range(n_critics))

    def forward(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        """Per-agent Q-values ``(B, N)`` of every critic."""
        return tuple(q_net(obs, actions)[0] for q_net in self.q_networks)

    def own_action_q(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, ...]:
        """Per-agent Q-values of every critic, differentiable w.r.t. each agent's *own* action only (actor losses)."""
        return tuple(q_net(obs, actions, detach_others=True)[0] for q_net in self.q_networks)

    def forward_with_logits(self, obs: th.Tensor, actions: th.Tensor) -> list[tuple[th.Tensor, th.Tensor]]:
        """``(Q, attention logits)`` of every critic (the logits feed MAAC's attention regulariser)."""
        return [q_net(obs, actions) for q_net in self.q_networks]

    def shared_parameters(self) -> list[nn.Parameter]:
        """Shared-across-agents parameters of every critic (their gradients are scaled by ``1/N``)."""
        return [p for q_net in self.q_networks for p in q_net.shared_parameters()]


class MAACPolicy(SharedAgentSACPolicy):
    """SAC policy with decentralised shared actors and :class:`AttentionCritic` critics.

    Parameters are SB3's ``SACPolicy``'s, the per-agent keywords of
    :class:`~vafn_sb3.common.agents.AgentLayoutPolicyMixin`, plus:

    :param attend_heads: number of attention heads of the critic.
    """

    def __init__(self, *args: Any, attend_heads: int = DEFAULT_ATTEND_HEADS, **kwargs: Any) -> None:
        kwargs.setdefault("net_arch", DEFAULT_NET_ARCH)
        # Read by make_critic, which SACPolicy.__init__ calls through _build.
        self.attend_heads = attend_heads
        super().__init__(*args, **kwargs)

    def make_critic(self, features_extractor: nn.Module | None = None) -> AttentionCritic:
        """Build an attention critic."""
        critic_kwargs = self._update_features_extractor(self.critic_kwargs, features_extractor)
        critic = AttentionCritic(**critic_kwargs, attend_heads=self.attend_heads, layout=self.agent_layout)
        return critic.to(self.device)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data["attend_heads"] = self.attend_heads
        return data


MlpPolicy = MAACPolicy
