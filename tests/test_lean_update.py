"""The lean SAC update (vafn_sb3/sac/lean.py) takes the same step as SB3's ``SAC.train``, for every SAC-family class."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.logger import configure

from vafn_sb3 import MAMLSAC, MTSAC, SAC
from vafn_sb3.sac.lean import supports_lean_update

#: Largest allowed difference of any parameter after the steps (float32 rounding of reordered sums and fused Adam;
#: measured: <= 5e-8; one Adam step moves a parameter by up to the learning rate, 1e-3 here).
TOLERANCE = 1e-6
N_AGENTS, OBS_PER_AGENT, ACTION_PER_AGENT = 3, 5, 3


class BlocksEnv(gym.Env):
    """A tiny env with the per-agent block layout of the arms (3 agents x 5 obs, 3 x 3 actions), random dynamics."""

    def __init__(self) -> None:
        self.observation_space = spaces.Box(-1.0, 1.0, (N_AGENTS * OBS_PER_AGENT,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (N_AGENTS * ACTION_PER_AGENT,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        return self._observation(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        return self._observation(), float(-np.abs(action).sum()), bool(self.np_random.random() < 0.05), False, {}

    def set_task(self, task: Any) -> None:
        """MAML-SAC's task hook (one task here)."""

    def _observation(self) -> np.ndarray:
        return self.np_random.uniform(-1, 1, self.observation_space.shape).astype(np.float32)


def filled_model(cls: type, lean_update: bool, **kwargs: Any) -> Any:
    """A model with 300 random transitions stored, critics apart from their targets (as after training; the same for
    any ``lean_update``) and a logger."""
    model = cls("SharedAgentPolicy", BlocksEnv(), learning_rate=1e-3, batch_size=64, learning_starts=10_000,
                ent_coef="auto_0.1", seed=3, lean_update=lean_update, policy_kwargs=dict(net_arch=[32, 32]), **kwargs)
    model.learn(300)
    generator = th.Generator().manual_seed(0)
    with th.no_grad():
        for parameter in model.critic.parameters():
            parameter.add_(0.1 * th.randn(parameter.shape, generator=generator))
    model.set_logger(configure(None, ["csv"]))
    return model


def step_both(cls: type, gradient_steps: int, **kwargs: Any) -> tuple[Any, Any, dict, dict]:
    """Stock and lean models after ``gradient_steps`` updates from the same state, minibatches and noise."""
    results = []
    for lean in (False, True):
        model = filled_model(cls, lean, **kwargs)
        np.random.seed(7)
        th.manual_seed(7)
        model.train(gradient_steps=gradient_steps, batch_size=64)
        results.append((model, dict(model.logger.name_to_value)))
    (stock, stock_log), (lean, lean_log) = results
    return stock, lean, stock_log, lean_log


def assert_same_state(stock: Any, lean: Any) -> None:
    """Every policy tensor and the log of the entropy coefficient agree within :data:`TOLERANCE`."""
    stock_state, lean_state = stock.policy.state_dict(), lean.policy.state_dict()
    assert stock_state.keys() == lean_state.keys()
    for name, value in stock_state.items():
        th.testing.assert_close(lean_state[name], value, atol=TOLERANCE, rtol=0, msg=name)
    th.testing.assert_close(lean.log_ent_coef, stock.log_ent_coef, atol=TOLERANCE, rtol=0)


@pytest.mark.parametrize("cls", [SAC, MTSAC, MAMLSAC])
def test_lean_steps_equal_sb3_steps(cls):
    kwargs = dict(warmup_steps=10_000) if cls is MAMLSAC else {}  # MAML-SAC: plain SAC collection, its train()
    stock, lean, stock_log, lean_log = step_both(cls, gradient_steps=3, **kwargs)
    assert supports_lean_update(lean) and lean.lean_update and not stock.lean_update
    before = filled_model(cls, False, **kwargs).policy.state_dict().values()
    moved = max((a - b).abs().max().item() for a, b in zip(stock.policy.state_dict().values(), before))
    assert moved > 100 * TOLERANCE  # the steps changed the parameters: the comparison below can fail
    assert_same_state(stock, lean)
    assert stock_log.keys() == lean_log.keys()
    for key in ("train/actor_loss", "train/critic_loss", "train/ent_coef", "train/ent_coef_loss"):
        assert lean_log[key] == pytest.approx(stock_log[key], rel=1e-4, abs=1e-5), key
    assert lean_log["train/n_updates"] == stock_log["train/n_updates"] == 3


def test_lean_update_with_a_fixed_entropy_coefficient_and_target_interval():
    results = []
    for lean in (False, True):
        model = SAC("MlpPolicy", BlocksEnv(), learning_rate=1e-3, batch_size=64, learning_starts=10_000, ent_coef=0.05,
                    seed=5, lean_update=lean, policy_kwargs=dict(net_arch=[16], n_critics=3), target_update_interval=2)
        model.learn(200)
        model.set_logger(configure(None, ["csv"]))
        np.random.seed(1)
        th.manual_seed(1)
        model.train(gradient_steps=3, batch_size=32)
        results.append(model)
    assert_same_state(*results)


def test_unsupported_models_fall_back_to_sb3():
    model = SAC("MlpPolicy", BlocksEnv(), use_sde=True, learning_starts=10_000, seed=0)
    assert not supports_lean_update(model)
    model.learn(100)
    model.set_logger(configure(None, ["csv"]))
    model.train(gradient_steps=1, batch_size=16)  # SB3's update, with gSDE noise


def test_lean_update_round_trips_through_save_and_load(tmp_path):
    model = SAC("SharedAgentPolicy", BlocksEnv(), lean_update=False, learning_starts=50, seed=0)
    model.learn(60)
    model.save(tmp_path / "model.zip")
    loaded = SAC.load(tmp_path / "model.zip", env=BlocksEnv())
    assert loaded.lean_update is False
    loaded.learn(20)
    assert all(group["fused"] is None for group in loaded.actor.optimizer.param_groups)  # stock Adam afterwards


@pytest.mark.parametrize("lean_update", [False, True])
def test_the_zoo_sets_lean_update_from_the_hyperparameters(lean_update, tmp_path):
    from zoo.train import main as train_main  # the RL-Zoo front end (rl_zoo3.train with the vafn algorithms)

    train_main([
        "--algo", "sac", "--env", "VAFN/ThreeArmReach-v1", "-n", "260", "-f", str(tmp_path), "--seed", "0",
        "--eval-freq", "-1", "-params", "learning_starts:200", "batch_size:32", f"lean_update:{lean_update}",
        "--env-kwargs", "max_length:1",
    ])
    model = SAC.load(tmp_path / "sac" / "VAFN-ThreeArmReach-v1_1" / "VAFN-ThreeArmReach-v1.zip")
    assert model.lean_update is lean_update and model._n_updates > 0
