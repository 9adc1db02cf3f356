"""A PettingZoo ``ParallelEnv`` view of :class:`ThreeArmEnv`: one agent per arm, a shared team reward.

Optional: needs the ``[pettingzoo]`` extra, and is imported only when used (``from vafn_gym.pettingzoo import ...``).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from vafn_gym.constants import ACTION_PER_ARM, ARM_IDS, action_slice
from vafn_gym.envs.three_arm import ThreeArmEnv

AGENT_NAMES = tuple(f"arm_{arm}" for arm in ARM_IDS)


class ThreeArmParallelEnv(ParallelEnv):
    """Each arm is an agent with a 3-D velocity action; every agent observes the 15-D global observation.

    All agents stay alive until the instruction ends (arms recur in an order, and PettingZoo forbids revival).
    ``state()`` is the 15-D global observation.

    :param kwargs: everything :class:`ThreeArmEnv` accepts.
    """

    metadata = {"name": "vafn_three_arm_v0", "render_modes": ThreeArmEnv.metadata["render_modes"], "is_parallelizable": True}

    def __init__(self, **kwargs: Any) -> None:
        self.env = ThreeArmEnv(**kwargs)
        self.possible_agents = list(AGENT_NAMES)
        self.agents: list[str] = []
        self.render_mode = self.env.render_mode
        self._state = np.zeros(self.env.observation_space.shape, dtype=np.float32)

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent: str) -> spaces.Box:
        """The (shared) observation space of ``agent``."""
        return self.env.observation_space

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent: str) -> spaces.Box:
        """The 3-D end-effector velocity space of ``agent``."""
        return spaces.Box(-1.0, 1.0, shape=(ACTION_PER_ARM,), dtype=np.float32)

    def state(self) -> np.ndarray:
        """The global 15-D observation."""
        return self._state.copy()

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Reset the underlying env; every agent gets the global observation."""
        obs, info = self.env.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        self._state = obs
        return {a: obs.copy() for a in self.agents}, {a: dict(info) for a in self.agents}

    def step(self, actions: dict[str, np.ndarray]) -> tuple[dict, dict, dict, dict, dict]:
        """Assemble the joint 9-D action (a missing agent's action is zero), step, and share the team reward."""
        unknown = set(actions) - set(self.agents)
        if unknown:
            raise ValueError(f"actions for agents that are not alive: {sorted(unknown)}")
        joint = np.zeros(self.env.action_space.shape, dtype=np.float32)
        for arm, agent in zip(ARM_IDS, self.possible_agents):
            if agent in actions:
                joint[action_slice(arm)] = np.asarray(actions[agent], dtype=np.float32).reshape(ACTION_PER_ARM)
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


def parallel_env(**kwargs: Any) -> ThreeArmParallelEnv:
    """PettingZoo-style constructor."""
    return ThreeArmParallelEnv(**kwargs)
