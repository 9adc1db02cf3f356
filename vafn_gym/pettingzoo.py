"""A PettingZoo ``ParallelEnv`` view of :class:`MultiArmEnv`: one agent per arm, a shared team reward.

Optional: needs the ``[pettingzoo]`` extra, and is imported only when used (``from vafn_gym.pettingzoo import ...``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from vafn_gym.constants import ACTION_PER_ARM
from vafn_gym.envs.multi_arm import MultiArmEnv


class MultiArmParallelEnv(ParallelEnv):
    """Each arm is an agent (``arm_1`` .. ``arm_N``) with a 3-D velocity action.

    Every agent sees the global observation.

    All agents stay alive until the instruction ends (arms recur in an order, and PettingZoo forbids revival).
    ``state()`` is the global observation.

    :param kwargs: everything :class:`MultiArmEnv` accepts
        (use ``inactive_arms="policy"`` for a true multi-agent task).
    """

    metadata = {
        "name": "vafn_multi_arm_v1",
        "render_modes": MultiArmEnv.metadata["render_modes"],
        "is_parallelizable": True,
    }

    def __init__(self, **kwargs: Any) -> None:
        self.env = MultiArmEnv(**kwargs)
        self.possible_agents = [f"arm_{arm}" for arm in self.env.layout.arm_ids]
        self.agents: list[str] = []
        self.render_mode = self.env.render_mode
        self._state = np.zeros(self.env.observation_space.shape, dtype=np.float32)
        self._action_space = spaces.Box(-1.0, 1.0, shape=(ACTION_PER_ARM,), dtype=np.float32)

    def observation_space(self, agent: str) -> spaces.Box:
        """The (shared) observation space of ``agent``."""
        return self.env.observation_space

    def action_space(self, agent: str) -> spaces.Box:
        """The 3-D end-effector velocity space of ``agent`` (the same object on every call)."""
        return self._action_space

    def state(self) -> np.ndarray:
        """The global observation."""
        return self._state.copy()

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Reset the underlying env; every agent gets the global observation."""
        obs, info = self.env.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        self._state = obs
        return {a: obs.copy() for a in self.agents}, {a: dict(info) for a in self.agents}

    def step(self, actions: dict[str, np.ndarray]) -> tuple[dict, dict, dict, dict, dict]:
        """Assemble the joint action (a missing agent's action is zero), step, and share the team reward."""
        unknown = set(actions) - set(self.agents)
        if unknown:
            raise ValueError(f"actions for agents that are not alive: {sorted(unknown)}")
        joint = np.zeros(self.env.action_space.shape, dtype=np.float32)
        for arm, agent in zip(self.env.layout.arm_ids, self.possible_agents):
            if agent in actions:
                joint[self.env.layout.action_slice(arm)] = np.asarray(
                    actions[agent], dtype=np.float32
                ).reshape(ACTION_PER_ARM)
        obs, reward, terminated, truncated, info = self.env.step(joint)
        self._state = obs
        agents = self.agents
        if terminated or truncated:
            self.agents = []
        return (
            {a: obs.copy() for a in agents},
            {a: float(reward) for a in agents},
            {a: bool(terminated) for a in agents},
            {a: bool(truncated) for a in agents},
            {a: dict(info) for a in agents},
        )

    def render(self) -> np.ndarray | None:
        """Render the underlying env."""
        return self.env.render()

    def close(self) -> None:
        """Close the underlying env."""
        self.env.close()


def parallel_env(**kwargs: Any) -> MultiArmParallelEnv:
    """PettingZoo-style constructor."""
    return MultiArmParallelEnv(**kwargs)
