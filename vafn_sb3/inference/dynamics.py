"""Adapting to changed dynamics by identification: fit how the active arm's motion turns from its commands, undo it.

A policy trained on the nominal robot commands end-effector velocities. On a variant whose commands are turned
(:class:`vafn_gym.Dynamics` ``action_rotation``), the arm's horizontal motion points ``rotation`` degrees away from the
command (after a lag of a few steps). :func:`fit_response` estimates that angle from (command, motion) pairs;
:class:`DynamicsCompensation` fits it on a support set (``adapt``) or on the episode's own last steps (``online=True``)
and turns every command by ``-rotation``, so the unchanged policy moves as it learned to. Gains, delays, speed limits
and payloads are left alone: they did not stop the nominal policy, and dividing by a measured gain made delayed arms
oscillate (docs/results.md, "Adapting to changed dynamics").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from vafn_gym.constants import CONTROL_DT, PHASE_EXECUTING, PHASE_INDEX, POS_SLICE, V_MAX
from vafn_gym.dynamics import turn_about_z
from vafn_sb3.common.adaptation import SupportSet, collect_support

__all__ = ["DynamicsCompensation", "ResponseFit", "executing_arms", "fit_response"]

#: Lags (control steps between a command and the motion it causes) tried by the fit: the arm's own tracking lag plus
#: the variant family's delays.
MAX_LAG = 5
#: Pairs with a commanded horizontal step shorter than this (metres) say nothing about direction and are skipped.
MIN_COMMAND = 1e-3
#: Fewest usable pairs for a fit; with fewer the response stays the identity.
MIN_PAIRS = 8
#: Smallest agreement of the pairs' turning angles (mean resultant length, 1 = all turn alike) for a usable fit.
MIN_CONSISTENCY = 0.5


@dataclass(frozen=True)
class ResponseFit:
    """The horizontal motion turns ``rotation`` degrees (counter-clockwise about z) from the command ``lag`` steps
    earlier.

    :param rotation: the turn (degrees).
    :param lag: control steps between a command and its motion.
    :param consistency: how alike the pairs turn (mean resultant length of their angles, weighted by length).
    :param n_pairs: pairs it was fitted on.
    """

    rotation: float = 0.0
    lag: int = 0
    consistency: float = 0.0
    n_pairs: int = 0

    @property
    def usable(self) -> bool:
        """Whether enough pairs agree on the turn for it to be undone."""
        return self.n_pairs >= MIN_PAIRS and self.consistency >= MIN_CONSISTENCY

    def correct(self, action: np.ndarray, n_arms: int) -> np.ndarray:
        """``action`` (``(..., 3 * n_arms)``) turned by ``-rotation`` per arm (unchanged when the fit is not
        usable)."""
        if not self.usable:
            return action
        blocks = np.asarray(action, dtype=np.float64).reshape(*np.shape(action)[:-1], n_arms, 3)
        turned = turn_about_z(blocks, -self.rotation)
        return np.clip(turned, -1.0, 1.0).reshape(np.shape(action)).astype(np.float32)


def executing_arms(observations: np.ndarray, next_observations: np.ndarray, n_arms: int) -> np.ndarray:
    """Per transition, the index of the one arm executing (phase flag 1) before and after it, or -1."""
    n = len(observations)
    before = np.round(observations.reshape(n, n_arms, -1)[:, :, PHASE_INDEX]) == PHASE_EXECUTING
    both = before & (np.round(next_observations.reshape(n, n_arms, -1)[:, :, PHASE_INDEX]) == PHASE_EXECUTING)
    return np.where(both.sum(axis=1) == 1, both.argmax(axis=1), -1)


def fit_response(
    observations: np.ndarray, actions: np.ndarray, next_observations: np.ndarray, episode_ends: np.ndarray,
    n_arms: int, max_lag: int = MAX_LAG,
) -> ResponseFit:
    """The :class:`ResponseFit` of the most consistent lag in ``0..max_lag`` (the identity if nothing fits).

    Pairs: where one arm executes in both readings of a transition, its measured horizontal displacement (the motion)
    and its horizontal action ``lag`` steps earlier in the same episode, times V_MAX · CONTROL_DT (the command, metres);
    commands shorter than ``MIN_COMMAND`` are skipped. With u, m the command and the motion as complex numbers, the turn
    is ``arg Σ conj(u) m`` (the least-squares angle) and the consistency ``|Σ conj(u) m| / Σ |u| |m|``.
    """
    n = len(actions)
    arms = executing_arms(observations, next_observations, n_arms)
    steps = np.flatnonzero(arms >= 0)
    own = arms[steps]
    moves = (next_observations.reshape(n, n_arms, -1)[steps, own, POS_SLICE]
             - observations.reshape(n, n_arms, -1)[steps, own, POS_SLICE])[:, :2]
    motions = moves[:, 0] + 1j * moves[:, 1]
    ends_before = np.concatenate([[0.0], np.cumsum(episode_ends)])  # episode ends among transitions 0..t-1
    blocks = actions.reshape(n, n_arms, -1)
    best = ResponseFit()
    for lag in range(max_lag + 1):
        keep = (steps >= lag) & (ends_before[steps] == ends_before[np.maximum(steps - lag, 0)])
        commands = blocks[steps[keep] - lag, own[keep], :2] * V_MAX * CONTROL_DT
        long_enough = np.linalg.norm(commands, axis=1) >= MIN_COMMAND
        commands = commands[long_enough]
        if len(commands) < MIN_PAIRS:
            continue
        products = np.conj(commands[:, 0] + 1j * commands[:, 1]) * motions[keep][long_enough]
        weight = float(np.sum(np.abs(products)))
        consistency = float(abs(products.sum())) / weight if weight > 0 else 0.0
        if consistency > best.consistency:
            best = ResponseFit(float(np.degrees(np.angle(products.sum()))), lag, consistency, len(commands))
    return best


def fit_support(support: SupportSet, n_arms: int) -> ResponseFit:
    """:func:`fit_response` on a support set."""
    return fit_response(support.observations, support.actions, support.next_observations, support.episode_ends,
                        n_arms)


class DynamicsCompensation:
    """A nominal policy plus a fitted response that it inverts: adapts to turned or scaled commands without training.

    ``adapt`` collects a support set with the wrapped model's stochastic policy (the same routine and budget as every
    other method) and fits the response on it; ``k`` is not used (no gradient steps). With ``online=True`` the policy
    refits after every step from the episode's own (command, motion) pairs instead, and needs no support set.

    :param model: a policy trained on the nominal dynamics (SB3 ``predict``), acting in the world frame.
    :param n_arms: arms of the env.
    :param response: a fitted response to invert (identity by default).
    :param online: refit from the running episode's steps (call :meth:`reset` at every episode start).
    :param window: online mode: the last this many steps are fitted, so a change of robot mid-episode is followed.
    """

    def __init__(
        self, model: Any, n_arms: int, response: ResponseFit | None = None, online: bool = False, window: int = 40
    ) -> None:
        self.model = model
        self.window = int(window)
        self.n_arms = int(n_arms)
        self.response = response or ResponseFit()
        self.online = online
        self.support: SupportSet | None = None
        self._history: dict[str, list[np.ndarray]] = {"obs": [], "actions": []}

    def reset(self) -> None:
        """Forget the running episode (online mode: the response is refitted from the next steps); resets the wrapped
        policy too where it has a ``reset``."""
        self._history = {"obs": [], "actions": []}
        inner = getattr(self.model, "reset", None)
        if callable(inner):
            inner()
        if self.online:
            self.response = ResponseFit()

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, Any]:
        """The wrapped policy's action for ``observation``, corrected by the response (refitted first if online)."""
        if self.online and np.ndim(observation) == 1:
            self._refit(np.asarray(observation, dtype=np.float32))
        action, state = self.model.predict(observation, state, episode_start, deterministic)
        sent = self.response.correct(action, self.n_arms)
        if self.online and np.ndim(observation) == 1:
            self._history["actions"].append(np.asarray(sent, dtype=np.float32))
        return sent, state

    def _refit(self, observation: np.ndarray) -> None:
        history = self._history
        history["obs"].append(observation)
        del history["obs"][:-self.window - 1], history["actions"][:-self.window]
        if len(history["actions"]) < MIN_PAIRS:
            return
        # Fitted on the commands actually sent (after the current correction): the fit is the arm's true response.
        fit = fit_response(np.stack(history["obs"][:-1]), np.stack(history["actions"]), np.stack(history["obs"][1:]),
                           np.zeros(len(history["actions"])), self.n_arms)
        if fit.usable:
            self.response = fit

    def adapt(
        self, env: gym.Env, task: Any = None, n_support: int = 200, k: int = 0, seed: int | None = None
    ) -> DynamicsCompensation:
        """Fit the response on ``n_support`` stochastic steps on ``env``, in two halves: the wrapped model's own
        steps, then steps with the first fit undone (a large turn makes the first half's motion erratic; the second is
        fitted on the commands actually sent, so it measures the response itself). ``k`` is not used."""
        first = n_support // 2
        halves = [collect_support(self.model, env, task, first, seed)] if first else []
        response = fit_support(halves[0], self.n_arms) if halves else ResponseFit()
        corrected = DynamicsCompensation(self.model, self.n_arms, response)
        halves.append(collect_support(corrected, env, task, n_support - first, None if seed is None else seed + 1))
        second = fit_support(halves[-1], self.n_arms)
        adapted = DynamicsCompensation(self.model, self.n_arms, second if second.usable else response)
        adapted.support = SupportSet(**{name: np.concatenate([getattr(h, name) for h in halves])
                                        for name in SupportSet.__dataclass_fields__})
        return adapted
