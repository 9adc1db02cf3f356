"""The reproduction study as data: which methods train on which env, and on which held-out panel they are evaluated.

``zoo/reproduce.py`` runs it: every :class:`StudyMethod` trains with ``benchmarks/learning.py`` (its YAML, the mode's
equal step budget, one process per seed), every :class:`Panel` is one ``benchmarks/adaptation.py`` call (the one
evaluation protocol: the same held-out test instructions, support sets and K for every method, with the scripted
ceiling and the random floor beside them). Adding a method or a panel touches only this file.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

#: The order family: the instruction's order is visible through the phase flags, so K = 0 shows zero-shot
#: generalisation to unseen orders.
ORDER_ENV = "VAFN/ThreeArmReach-v1"
#: The hidden family: one unobserved target per arm per instruction, seen only through the distances.
HIDDEN_ENV = "VAFN/ThreeArmReachHidden-v1"
#: The same world with the targets observed (what a target-inferring policy is trained on).
GOAL_ENV = "VAFN/ThreeArmReachGoal-v1"


@dataclass(frozen=True)
class StudyMethod:
    """One method of a panel: a label, its zoo algorithm, what it trains on and how the panel evaluates it.

    ``evaluation`` is ``"adapt"`` (K adaptation steps on the panel's support sets, every K of the mode), ``"zero-shot"``
    (K = 0: a method that adapts inside the episode, or a panel that only measures generalisation), ``"infer-probe"`` or
    ``"infer-learned"`` (a model trained on observed targets run through ``TargetInferencePolicy`` with trilateration,
    or with the packaged target estimator), ``"infer-gradient"`` (the same with K gradient steps of the packaged
    meta-learned ``GradientTargetEstimator``, refined at every later reading, every K of the mode), ``"identify"`` /
    ``"identify-online"`` (a nominal model whose commands are turned back by ``DynamicsCompensation``, fitted on the
    support set at every K, or on the episode's own steps at K = 0). A method with
    ``models_from`` trains nothing: it evaluates the models of that method of the panel another way.
    """

    label: str
    algo: str
    train_env: str
    evaluation: str = "adapt"
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    hyperparams: dict[str, Any] = field(default_factory=dict)
    models_from: str | None = None

    def method_fields(self, models: str) -> list[str]:
        """The ``--method`` fields of ``benchmarks/adaptation.py`` for this method's models (a glob)."""
        fields = [self.label, self.algo, models]
        if self.env_kwargs:
            fields.append(json.dumps(self.env_kwargs))
        if self.evaluation != "adapt":
            fields.append(self.evaluation)
        return fields


@dataclass(frozen=True)
class Panel:
    """One figure of the study: methods evaluated on held-out test instructions of one env."""

    name: str
    env_id: str
    min_length: int
    max_length: int
    methods: tuple[StudyMethod, ...]
    over_k: bool
    claim: str
    #: Run every task under every variant of this split of ``vafn_gym.dynamics.DYNAMICS_VARIANTS`` (None: the env's).
    dynamics: str | None = None
    #: Held-out instructions (per variant), at most the budget's ``n_tasks``; None: the budget's.
    n_tasks: int | None = None


def support_budget(n_support_steps: int, support_episodes: float, k_max: int, support: str = "episodes") -> str:
    """What one adaptation of a panel spends, as its figure and SUMMARY.md say it: the support set, or none at K = 0."""
    if k_max == 0:
        return "no adaptation (K = 0)"
    shape = ", split over one single-waypoint instruction per arm" if support == "per-arm" else ""
    return f"a support set of {n_support_steps} env steps (~{support_episodes:.1f} episodes{shape}) per task and K"


PAPER_FIG3 = "MAML-SAC reaches success 1.0 by adaptation step 20 with zero collisions and beats MAAC, MAPPO, MADDPG."

#: Hidden family, default control mode: the paper's Fig. 3 comparison where adaptation can matter.
HIDDEN_PANEL = Panel(
    "hidden", HIDDEN_ENV, 1, 4,
    (
        StudyMethod("maml_sac", "maml_sac", HIDDEN_ENV),
        StudyMethod("mtsac", "mtsac", HIDDEN_ENV),
        StudyMethod("mappo", "mappo", HIDDEN_ENV),
        StudyMethod("maddpg", "maddpg", HIDDEN_ENV),
        StudyMethod("maac", "maac", HIDDEN_ENV, hyperparams={"train_freq": 4}),
        StudyMethod("sac_history4", "sac", HIDDEN_ENV, "zero-shot", env_kwargs={"history": 4}),
        StudyMethod("ppo_lstm", "ppo_lstm", HIDDEN_ENV, "zero-shot"),
        # Trained with decoy goals at some waypoints' start, so a wrong early estimate does not strand the arm.
        StudyMethod("goal_mappo_infer_probe", "mappo", GOAL_ENV, "infer-probe",
                    hyperparams={"env_wrapper": "vafn_gym.wrappers.GoalDetours"}),
        StudyMethod("goal_mappo_infer_learned", "mappo", GOAL_ENV, "infer-learned",
                    models_from="goal_mappo_infer_probe"),
        StudyMethod("goal_mappo_infer_gradient", "mappo", GOAL_ENV, "infer-gradient",
                    models_from="goal_mappo_infer_probe"),
        # The same context adaptation for a goal-observing MTSAC (plain goal env, no decoys): its K gradient steps
        # adapt the 3-number target estimate the policy reads, not the policy's weights.
        StudyMethod("goal_mtsac_infer_gradient", "mtsac", GOAL_ENV, "infer-gradient"),
        StudyMethod("goal_mtsac_infer_probe", "mtsac", GOAL_ENV, "infer-probe",
                    models_from="goal_mtsac_infer_gradient"),
    ),
    over_k=True,
    claim=PAPER_FIG3,
)

#: Order family: unseen orders at K = 0 (the phase flags say whose turn it is).
ORDER_PANEL = Panel(
    "order", ORDER_ENV, 1, 10,
    (
        StudyMethod("maml_sac", "maml_sac", ORDER_ENV, "zero-shot"),
        StudyMethod("mtsac", "mtsac", ORDER_ENV, "zero-shot"),
        StudyMethod("sac", "sac", ORDER_ENV, "zero-shot"),
        StudyMethod("mappo", "mappo", ORDER_ENV, "zero-shot"),
        StudyMethod("maddpg", "maddpg", ORDER_ENV, "zero-shot"),
        StudyMethod("maac", "maac", ORDER_ENV, "zero-shot", hyperparams={"train_freq": 4}),
    ),
    over_k=False,
    claim="A policy trained on short instructions follows unseen orders of lengths 1-10 without adaptation.",
)

#: Variants of the robot's dynamics (vafn_gym.dynamics, train / test lists): the weights, not a target, must change.
VARIANTS = {"dynamics": "train"}
#: MAML-SAC's tasks on that family: the variants themselves, each adapted on a 400-step support set.
VARIANT_TASKS = {"env_wrapper": "vafn_gym.wrappers.DynamicsTasks", "n_support": 400}
DYNAMICS_PANEL = Panel(
    "dynamics", ORDER_ENV, 1, 4,
    (
        StudyMethod("maml_sac_variants", "maml_sac", ORDER_ENV, env_kwargs=VARIANTS, hyperparams=VARIANT_TASKS),
        # K = 0: domain randomisation over the train variants; K > 0: fine-tuning it on the support set.
        StudyMethod("mtsac_variants", "mtsac", ORDER_ENV, env_kwargs=VARIANTS),
        StudyMethod("maml_sac_variants_second_order", "maml_sac", ORDER_ENV, env_kwargs=VARIANTS,
                    hyperparams={**VARIANT_TASKS, "second_order": True}),
        StudyMethod("sac_variants_history4", "sac", ORDER_ENV, "zero-shot", env_kwargs={**VARIANTS, "history": 4}),
        # Adapts in its LSTM state, inside the episode, with no gradient step.
        StudyMethod("ppo_lstm_variants", "ppo_lstm", ORDER_ENV, "zero-shot", env_kwargs=VARIANTS),
        StudyMethod("mtsac_nominal", "mtsac", ORDER_ENV),
        StudyMethod("nominal_identify", "mtsac", ORDER_ENV, "identify", models_from="mtsac_nominal"),
        StudyMethod("nominal_identify_online", "mtsac", ORDER_ENV, "identify-online", models_from="mtsac_nominal"),
    ),
    over_k=True,
    claim="Meta-learned weights adapt to a robot whose dynamics changed in K <= 10 steps on <= 500 support steps.",
    dynamics="test",
    n_tasks=3,
)

#: The panels of the study, in the order of SUMMARY.md.
PANELS: tuple[Panel, ...] = (HIDDEN_PANEL, ORDER_PANEL, DYNAMICS_PANEL)
#: The panel whose jobs also evaluate every ``Budget.curve_every`` steps: the learning curves of ``--full``.
CURVES_PANEL = ORDER_PANEL.name


@dataclass(frozen=True)
class PackagedPolicy:
    """One packaged policy of ``vafn_sb3/pretrained``: how ``--full`` trains and exports it again (its note, if it
    ships one, is read from the packaged JSON)."""

    algo: str
    env_id: str
    seed: int
    timesteps: int
    train_max_length: int = 3
    hyperparams: dict[str, Any] = field(default_factory=dict)

    @property
    def label(self) -> str:
        """``<algo>__<EnvName>``, the packaged files' stem."""
        return f"{self.algo}__{self.env_id.replace('/', '-')}"


#: The packaged policies, with the seed and budget each shipped one was trained with.
PACKAGED: tuple[PackagedPolicy, ...] = (
    PackagedPolicy("sac", ORDER_ENV, 0, 30_000),
    PackagedPolicy("maml_sac", ORDER_ENV, 1, 40_000),
    PackagedPolicy("maml_sac", HIDDEN_ENV, 0, 50_000, train_max_length=2),
    PackagedPolicy("mtsac", HIDDEN_ENV, 0, 50_000, train_max_length=2),
    PackagedPolicy("mappo", GOAL_ENV, 2, 100_000, train_max_length=2,
                   hyperparams={"env_wrapper": "vafn_gym.wrappers.GoalDetours"}),
    PackagedPolicy("mtsac", GOAL_ENV, 3, 150_000, train_max_length=2),
)


@dataclass(frozen=True)
class Budget:
    """How much of the study a mode runs."""

    name: str
    seeds: tuple[int, ...]
    timesteps: int
    train_max_length: int
    n_tasks: int
    k_values: tuple[int, ...]
    n_support: int
    #: Also evaluate the packaged pretrained checkpoints of each panel's env (``--quick``).
    pretrained: bool = False
    #: Fig. 4 stream steps.
    fig4_steps: int = 2000
    #: ``benchmarks/instruction_table.py`` arguments (Table 1).
    table1_args: tuple[str, ...] = ()
    #: Env steps between held-out evaluations of the ``CURVES_PANEL`` jobs (None: only the final one).
    curve_every: int | None = None
    #: Train and export the packaged policies (``PACKAGED``) again, with this share of each one's own steps (0: not
    #: at all); Fig. 4 then drives the new ones.
    packaged_share: float = 0.0
    #: Held-out instructions each exported policy is evaluated on (its JSON's number).
    packaged_n_test: int = 100


BUDGETS: dict[str, Budget] = {
    "smoke": Budget("smoke", (0,), 300, 1, 1, (0, 1), 40, pretrained=True, fig4_steps=200,
                    table1_args=("--seeds", "1", "--items", "2", "--in-distribution", "0", "--transfer-items", "0",
                                 "--workers", "1", "--robust-items", "5", "--camera-items", "5"),
                    curve_every=150, packaged_share=0.002, packaged_n_test=1),
    "quick": Budget("quick", (0,), 3000, 2, 5, (0, 1, 10), 200, pretrained=True,
                    table1_args=("--seeds", "1", "--items", "20", "--in-distribution", "0", "--transfer-items", "0")),
    "full": Budget("full", (0, 1, 2, 3, 4), 50_000, 2, 15, (0, 1, 2, 5, 10, 20, 50), 400, curve_every=5_000,
                   packaged_share=1.0),
}
