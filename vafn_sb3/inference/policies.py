"""Target inference: run a policy trained with observed targets where the targets are hidden.

A policy trained on ``observe_goal=True`` (e.g. ``VAFN/ThreeArmReachGoal-v1``) reads each arm's target; on the
hidden-target env (``VAFN/ThreeArmReachHidden-v1``) only the distance to it is observed. :class:`TargetInferencePolicy`
fills the gap inside the episode, with no gradient step: when an arm starts a waypoint it makes three one-step probe
moves (the scripted controller's), trilaterates the target from its own (position, distance) readings, and from then
on gives the learned policy the observation it was trained on, with the estimate as the goal (refined at every step).
Two ablations: ``inference="passive"`` drops the probe moves (the policy heads for the centre of the shared region
until its own readings span a volume), ``inference="none"`` never estimates (the goal stays the centre: the
goal-observing policy with nothing inferred, this method's K = 0). ``inference="learned"`` makes the probe moves but
replaces trilateration by a :class:`LearnedTargetEstimator`: a network that maps the waypoint's first readings to
the target, trained by regression on targets the training env knows (the privileged-information adaptation module of
RMA), never told that the reading is ``|p - t|``. ``inference="gradient"`` (:class:`GradientInferencePolicy`) makes the
probe moves, then infers the target by ``K`` meta-learned gradient steps on a 3-number context
(:class:`~vafn_sb3.inference.GradientTargetEstimator`), refined by a Gauss-Newton step at every later
reading; its ``adapt(k=K)`` sets ``K``, so it has an adaptation curve like the gradient-adapting learners.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
from tqdm.auto import tqdm

from vafn_gym.constants import (
    ACTION_PER_ARM,
    CONTROL_DT,
    DIST_INDEX,
    GOAL_SLICE,
    OBS_PER_ARM,
    OBS_PER_ARM_WITH_GOAL,
    PHASE_COMPLETED,
    PHASE_EXECUTING,
    PHASE_INDEX,
    PHASE_WAITING,
    POS_SLICE,
    V_MAX,
)
from vafn_gym.controllers import PROBE_DIRECTIONS, trilaterate
from vafn_gym.instructions import Instruction
from vafn_gym.layout import ArmLayout
from vafn_sb3.common.adaptation import AdaptedPolicy
from vafn_sb3.inference.estimators.base import (
    ESTIMATOR_READINGS,
    REFINE_SOLVER,
    REFINE_SOLVERS,
    REFINE_STEPS,
    Estimator,
    FirstReadingsEstimator,
)
from vafn_sb3.inference.estimators.gradient import GradientTargetEstimator
from vafn_sb3.inference.estimators.learned import LearnedTargetEstimator

if TYPE_CHECKING:
    from vafn_gym.envs import MultiArmEnv

__all__ = ["ESTIMATOR_MODES", "INFERENCE_MODES", "GradientInferencePolicy", "TargetInferencePolicy",
           "collect_waypoint_readings", "inference_policy_for_env", "load_estimator"]

#: ``inference`` settings: probe moves then trilateration, trilateration of passive readings only, probe moves then
#: a :class:`LearnedTargetEstimator`, probe moves then gradient steps of a ``GradientTargetEstimator``, no inference.
INFERENCE_MODES = ("probe", "passive", "learned", "gradient", "none")
#: Settings that make the probe moves and estimate once, from a waypoint's first readings, with an estimator.
ESTIMATOR_MODES = ("learned", "gradient")
#: Readings of one waypoint closer than this (metres) to the previous one are not recorded.
MIN_SEPARATION = 1e-3


class TargetInferencePolicy:
    """A goal-observing SB3 model acting on hidden-target observations through in-episode trilateration.

    :param model: anything with SB3's ``predict`` whose observation has 8 numbers per arm (position, distance, phase,
        goal), i.e. trained with ``observe_goal=True``.
    :param homes: each arm's rest point (arm ids 1..N), in the observation's frame: the goal of a completed arm.
    :param priors: each arm's goal before its target is estimated (e.g. the shared region's centre), same frame.
    :param inference: one of :data:`INFERENCE_MODES`.
    :param waiting_goal: the env's ``waiting_goal``: with "home" a waiting arm's goal is its home, as the model saw it.
    :param estimator: the estimator of ``inference="learned"`` or ``"gradient"`` (any callable from a waypoint's
        readings so far, ``(points, distances)``, to a target or None); None: the packaged one
        (``LearnedTargetEstimator.load()`` or ``GradientTargetEstimator.load()``).
    """

    def __init__(
        self,
        model: AdaptedPolicy,
        homes: Mapping[int, np.ndarray],
        priors: Mapping[int, np.ndarray],
        inference: str = "probe",
        waiting_goal: str = "target",
        estimator: Estimator | None = None,
    ) -> None:
        self.model = model
        self.arm_ids = tuple(sorted(int(arm) for arm in homes))
        if self.arm_ids != tuple(range(1, len(self.arm_ids) + 1)) or set(priors) != set(self.arm_ids):
            raise ValueError(f"homes and priors must both be keyed by arm ids 1..N, got {list(homes)}, {list(priors)}")
        expected = (len(self.arm_ids) * OBS_PER_ARM_WITH_GOAL,)
        shape = getattr(getattr(model, "observation_space", None), "shape", None)
        if shape != expected:
            raise ValueError(
                f"the model must observe targets ({expected[0]} numbers for {len(self.arm_ids)} arms, "
                f"observe_goal=True), its observation shape is {shape}"
            )
        self.homes = {arm: np.asarray(homes[arm], dtype=np.float64) for arm in self.arm_ids}
        self.priors = {arm: np.asarray(priors[arm], dtype=np.float64) for arm in self.arm_ids}
        if inference not in INFERENCE_MODES:
            raise ValueError(f"inference must be one of {INFERENCE_MODES}, got {inference!r}")
        if estimator is not None and inference not in ESTIMATOR_MODES:
            raise ValueError(f"only inference in {ESTIMATOR_MODES} takes an estimator, not inference={inference!r}")
        self.inference = inference
        if estimator is None and inference in ESTIMATOR_MODES:
            estimator = load_estimator(inference)
        self.estimator = estimator
        #: Whether a newly active arm makes the probe moves.
        self.probes = inference in ("probe", *ESTIMATOR_MODES)
        self.waiting_goal = waiting_goal
        self.reset()

    @staticmethod
    def env_frame(env: gym.Env) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray], str]:
        """``homes``, ``priors`` and ``waiting_goal`` of ``env`` (a hidden-target env, any wrapper, ``history=1``)."""
        base = cast("MultiArmEnv", env.unwrapped)
        if base.observe_goal or base.history != 1:
            raise ValueError(
                f"target inference needs hidden-target observations with history=1, the env has "
                f"observe_goal={base.observe_goal}, history={base.history}"
            )
        centre = np.array([0.0, 0.0, float(np.mean(base.layout.shared_z_range))])
        homes = {arm: base.observed_point(arm, arm_obj.home) for arm, arm_obj in base.arms.items()}
        priors = {arm: base.observed_point(arm, centre) for arm in base.arms}
        return homes, priors, base.waiting_goal

    @classmethod
    def for_env(
        cls, model: AdaptedPolicy, env: gym.Env, inference: str = "probe", estimator: Estimator | None = None
    ) -> TargetInferencePolicy:
        """A policy for ``env`` (a hidden-target :class:`MultiArmEnv`, any wrapper, ``history=1``)."""
        homes, priors, waiting_goal = cls.env_frame(env)
        return cls(model, homes, priors, inference=inference, waiting_goal=waiting_goal, estimator=estimator)

    def reset(self) -> None:
        """Forget every reading and estimate (call at every episode start; ``run_episode`` does)."""
        self._active: int | None = None
        self._points: list[np.ndarray] = []
        self._distances: list[float] = []
        self._estimate: np.ndarray | None = None
        self._previous_distance: float | None = None

    @property
    def estimate(self) -> np.ndarray | None:
        """The active arm's current target estimate (observation frame), or None before the first estimate."""
        return self._estimate

    @property
    def readings(self) -> tuple[int | None, list[np.ndarray], list[float]]:
        """The active arm and its recorded (positions, distances) of the current waypoint (copies)."""
        return self._active, [point.copy() for point in self._points], list(self._distances)

    def _record(self, active: int, position: np.ndarray, distance: float) -> None:
        # A new waypoint starts when the active arm changes or its distance jumps (the same arm reaching again).
        jumped = self._previous_distance is not None and distance > self._previous_distance + 2 * V_MAX * CONTROL_DT
        if active != self._active or jumped:
            self._active, self._points, self._distances, self._estimate = active, [], [], None
        self._previous_distance = distance
        # A held arm (the env holds it until the others are home) repeats its reading: only new points count.
        if self._points and np.linalg.norm(position - self._points[-1]) < MIN_SEPARATION:
            return
        self._points.append(position.copy())
        self._distances.append(distance)
        if self.inference == "none":
            estimate = None
        elif self.inference in ESTIMATOR_MODES:  # one estimate (GradientInferencePolicy refines it)
            estimator = cast("Estimator", self.estimator)  # set by __init__ for these modes
            estimate = estimator(self._points, self._distances) if self._estimate is None else None
        else:
            estimate = trilaterate(self._points, self._distances)
        if estimate is not None:
            self._estimate = estimate

    def goal_observation(self, observation: np.ndarray) -> np.ndarray:
        """The observation the goal-observing model expects, with the current estimates as goals (no recording)."""
        obs = np.asarray(observation, dtype=np.float64)
        blocks = []
        for arm in self.arm_ids:
            block = obs[ArmLayout.block_slice(arm, OBS_PER_ARM)]
            phase = round(block[PHASE_INDEX])
            if phase == PHASE_COMPLETED or (phase == PHASE_WAITING and self.waiting_goal == "home"):
                goal = self.homes[arm]
            elif phase == PHASE_EXECUTING and self._estimate is not None:
                goal = self._estimate
            else:
                goal = self.priors[arm]
            full = np.zeros(OBS_PER_ARM_WITH_GOAL)
            full[POS_SLICE], full[PHASE_INDEX], full[GOAL_SLICE] = block[POS_SLICE], phase, goal
            full[DIST_INDEX] = np.linalg.norm(block[POS_SLICE] - goal)
            blocks.append(full)
        return np.concatenate(blocks).astype(np.float32)

    def act(self, observation: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """The joint action for one observation; records the active arm's reading first."""
        obs = np.asarray(observation, dtype=np.float64)
        blocks = {arm: obs[ArmLayout.block_slice(arm, OBS_PER_ARM)] for arm in self.arm_ids}
        active = next((arm for arm, b in blocks.items() if round(b[PHASE_INDEX]) == PHASE_EXECUTING), None)
        if active is not None:
            self._record(active, blocks[active][POS_SLICE], float(blocks[active][DIST_INDEX]))
        else:  # the instruction is complete: the next waypoint starts afresh
            self._active, self._previous_distance = None, None
        action, _ = self.model.predict(self.goal_observation(obs), deterministic=deterministic)
        action = np.array(action, dtype=np.float32).reshape(-1)
        probe_index = len(self._points) - 1
        probing = self.probes and self._estimate is None and probe_index < len(PROBE_DIRECTIONS)
        if probing and active is not None:
            action[ArmLayout.block_slice(active, ACTION_PER_ARM)] = PROBE_DIRECTIONS[probe_index]
        return action

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """SB3-style ``predict`` for one observation: ``(action, None)``."""
        obs = np.asarray(observation)
        if obs.ndim != 1:
            raise ValueError(f"TargetInferencePolicy keeps per-episode readings: pass one observation, got {obs.shape}")
        return self.act(obs, deterministic=deterministic), None


class GradientInferencePolicy(TargetInferencePolicy):
    """:class:`TargetInferencePolicy` with ``inference="gradient"``, adaptable: ``adapt(k=K)`` sets the gradient steps.

    Its own estimator takes ``steps`` steps (0: the meta-learned start, i.e. this method unadapted). ``adapt`` collects
    no support set: the data each step adapts on are the waypoint's own readings (the probe moves, inside the
    episode), so ``n_support`` is ignored and the adapted policy has ``support = None``. When the estimator has a
    refinement model (the packaged one has), every later reading of the waypoint adds ``refine_steps`` steps of
    ``refine_solver`` on all its readings so far (:meth:`~vafn_sb3.inference.GradientTargetEstimator.refine`);
    with ``steps = 0`` nothing adapts, refinement included.

    :param estimator: a :class:`~vafn_sb3.inference.GradientTargetEstimator`; None: the packaged one.
    :param steps: gradient steps per waypoint of this policy's estimator.
    :param refine_steps: refinement steps per later reading (0, or an estimator without a refinement model: none;
        None: :data:`REFINE_STEPS` of the solver).
    :param refine_solver: one of :data:`REFINE_SOLVERS`.
    """

    #: No support set: the adapted policies adapt on the episode's own readings.
    support = None

    estimator: GradientTargetEstimator

    def __init__(self, model: AdaptedPolicy, homes: Mapping[int, np.ndarray], priors: Mapping[int, np.ndarray],
                 inference: str = "gradient", waiting_goal: str = "target", estimator: Estimator | None = None,
                 steps: int = 0, refine_steps: int | None = None, refine_solver: str = REFINE_SOLVER) -> None:
        if inference != "gradient":
            raise ValueError(f"GradientInferencePolicy infers by gradient steps, not inference={inference!r}")
        if estimator is not None and not callable(getattr(estimator, "with_steps", None)):
            raise ValueError(f"GradientInferencePolicy needs a GradientTargetEstimator (with with_steps), got "
                             f"{type(estimator).__name__}")
        if refine_solver not in REFINE_SOLVERS:
            raise ValueError(f"refine_solver must be one of {REFINE_SOLVERS}, got {refine_solver!r}")
        refine_steps = REFINE_STEPS[refine_solver] if refine_steps is None else refine_steps
        if refine_steps < 0:
            raise ValueError(f"refine_steps must be >= 0, got {refine_steps}")
        super().__init__(model, homes, priors, inference="gradient", waiting_goal=waiting_goal, estimator=estimator)
        self.estimator = self.estimator.with_steps(steps)
        self.refine_steps = int(refine_steps)
        self.refine_solver = refine_solver

    @classmethod
    def for_env(
        cls, model: AdaptedPolicy, env: gym.Env, inference: str = "gradient", estimator: Estimator | None = None,
        steps: int = 0,
        refine_steps: int | None = None, refine_solver: str = REFINE_SOLVER,
    ) -> GradientInferencePolicy:
        """A policy for ``env`` (a hidden-target :class:`MultiArmEnv`, any wrapper, ``history=1``)."""
        homes, priors, waiting_goal = cls.env_frame(env)
        return cls(model, homes, priors, inference=inference, waiting_goal=waiting_goal, estimator=estimator,
                   steps=steps, refine_steps=refine_steps, refine_solver=refine_solver)

    @property
    def refines(self) -> bool:
        """Whether later readings refine the estimate (steps and refine_steps > 0, and a refinement model)."""
        has_model = getattr(self.estimator, "reading_net", None) is not None
        return self.estimator.steps > 0 and self.refine_steps > 0 and has_model

    def _record(self, active: int, position: np.ndarray, distance: float) -> None:
        estimated = self._estimate is not None
        n_points = len(self._points)
        super()._record(active, position, distance)
        # a new reading of a waypoint already estimated (not a repeated point, not a new waypoint) refines it
        if self.refines and estimated and self._estimate is not None and len(self._points) > n_points:
            # Gauss-Newton also restarts from the prior (the shared region's centre): a wild first estimate is dropped
            restarts = (self.priors[active],) if self.refine_solver == "gauss-newton" else ()
            self._estimate = self.estimator.refine(self._points, self._distances, self._estimate, self.refine_steps,
                                                   self.refine_solver, restarts=restarts)

    def adapt(self, env: gym.Env, task: Instruction | None = None, n_support: int = 0, k: int = 1,
              seed: int | None = None) -> GradientInferencePolicy:
        """A copy whose estimator takes ``k`` gradient steps per waypoint (nothing collected; this policy unchanged)."""
        adapted = copy.copy(self)
        adapted.estimator = self.estimator.with_steps(k)
        adapted.reset()
        return adapted


def load_estimator(inference: str, path: str | Path | None = None) -> FirstReadingsEstimator:
    """The estimator ``inference="learned"`` or ``"gradient"`` reads, from ``path`` (None: the packaged one)."""
    if inference == "learned":
        return LearnedTargetEstimator.load(path)
    if inference == "gradient":
        return GradientTargetEstimator.load(path)
    raise ValueError(f"only inference in {ESTIMATOR_MODES} reads an estimator, not inference={inference!r}")


def inference_policy_for_env(
    model: AdaptedPolicy, env: gym.Env, inference: str, estimator: Estimator | None = None,
    steps: int | None = None,
    refine_steps: int | None = None, refine_solver: str = REFINE_SOLVER,
) -> TargetInferencePolicy:
    """The policy of an ``inference`` setting for ``env``: a :class:`GradientInferencePolicy` for ``"gradient"``.

    ``steps``, ``refine_steps`` and ``refine_solver`` concern ``"gradient"`` only; ``steps=None`` takes its estimator's
    own step count, ``refine_steps=None`` the solver's :data:`REFINE_STEPS`.
    """
    if inference != "gradient":
        return TargetInferencePolicy.for_env(model, env, inference=inference, estimator=estimator)
    gradient = cast(GradientTargetEstimator, load_estimator("gradient") if estimator is None else estimator)
    return GradientInferencePolicy.for_env(model, env, estimator=gradient,
                                           steps=gradient.steps if steps is None else steps, refine_steps=refine_steps,
                                           refine_solver=refine_solver)


class _TrilaterationAfter:
    """Trilateration withheld until ``n_readings`` readings: how ``inference="learned"`` moves, with exact estimates."""

    def __init__(self, n_readings: int) -> None:
        self.n_readings = n_readings

    def __call__(self, points: Sequence[np.ndarray], distances: Sequence[float]) -> np.ndarray | None:
        return trilaterate(points, distances) if len(points) >= self.n_readings else None


def collect_waypoint_readings(
    model: AdaptedPolicy, env: gym.Env, tasks: Sequence[Instruction], seed: int, n_readings: int = ESTIMATOR_READINGS,
    progress: bool = True, heading_after: int | None = None,
) -> dict[str, np.ndarray]:
    """Each waypoint's first ``n_readings`` readings of ``model`` on hidden targets, with its true target (the label).

    Runs one episode per task of ``tasks`` on ``env``: the goal-observing ``model`` through a
    :class:`TargetInferencePolicy` that moves as ``inference="learned"`` does (probe moves, then the prior goal until
    ``heading_after`` readings, default ``n_readings``), so the readings are those an estimator will be given, and
    from then on toward the trilaterated target. ``heading_after=ESTIMATOR_READINGS`` with more ``n_readings``: the
    readings of an arm heading for its target after the first ones, as an adapted policy's arm does (what the
    refinement model reads). Each label is read from the env's task, which a deployed policy never sees.

    :return: ``points (N, n_readings, 3)``, ``distances (N, n_readings)``, ``targets (N, 3)`` in the observation
        frame, and ``arms (N,)``; a waypoint reached in fewer readings is left out.
    """
    heading_after = n_readings if heading_after is None else int(heading_after)
    if not ESTIMATOR_READINGS <= heading_after <= n_readings:
        raise ValueError(f"heading_after must be in [{ESTIMATOR_READINGS}, n_readings={n_readings}], got "
                         f"{heading_after}")
    policy = TargetInferencePolicy.for_env(model, env, inference="learned",
                                           estimator=_TrilaterationAfter(heading_after))
    base = cast("MultiArmEnv", env.unwrapped)
    points, distances, targets, arms = [], [], [], []
    for index, task in enumerate(tqdm(tasks, desc="collecting readings", disable=not progress)):
        base.set_task(task)
        policy.reset()
        obs, _ = env.reset(seed=seed + index)
        done, labelled = False, False
        while not done:
            action, _ = policy.predict(obs)
            active, waypoint_points, waypoint_distances = policy.readings
            if len(waypoint_points) < n_readings:  # a waypoint still collecting (a new one starts with one reading)
                labelled = False
            elif not labelled:  # this step completed the waypoint's readings: label them
                labelled = True
                points.append(np.array(waypoint_points))
                distances.append(np.array(waypoint_distances))
                arm = cast(int, active)  # an arm with readings is the active one
                targets.append(base.observed_point(arm, base.task.current_target(arm)))
                arms.append(active)
            obs, _, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
    return {"points": np.array(points), "distances": np.array(distances), "targets": np.array(targets),
            "arms": np.array(arms)}

