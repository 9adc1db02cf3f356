"""The upstream RL Zoo (``python -m rl_zoo3.train --gym-packages vafn_sb3``) trains vafn's shared per-arm policies.

Importing vafn_sb3 adds our policies to the stock SB3 ``policy_aliases`` (vafn_sb3/aliases.py); these tests check
that only our names are added, that registering again changes nothing, and that a model trained by the unmodified
rl_zoo3 CLI from hyperparams/sac.yml is the zoo's shared per-arm SAC, loaded by ``load_model`` and scored by
zoo/enjoy.py.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import yaml

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

ENV_ID = "VAFN/ThreeArmReach-v1"
ENV_NAME = "VAFN-ThreeArmReach-v1"
SUBPROCESS_ENV = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: The aliases importing vafn_sb3 must add to the stock classes of rl_zoo3's ``ALGOS``, and nothing else.
EXPECTED_ADDITIONS = {
    "sac": {"SharedAgentPolicy": "vafn_sb3.common.agents.SharedAgentSACPolicy"},
    "td3": {"SharedAgentPolicy": "vafn_sb3.maddpg.policies.MADDPGPolicy"},
    "ddpg": {"SharedAgentPolicy": "vafn_sb3.maddpg.policies.MADDPGPolicy"},  # DDPG shares TD3's table
}
#: A fresh interpreter: the stock tables before vafn_sb3 is imported, after, and after registering a second time.
SNAPSHOT_SCRIPT = """
import json
from rl_zoo3.utils import ALGOS

def snapshot():
    def names(table):
        return {name: f"{cls.__module__}.{cls.__qualname__}" for name, cls in table.items()}

    return {key: {"id": id(algo.policy_aliases), "aliases": names(algo.policy_aliases)} for key, algo in ALGOS.items()}

before = snapshot()
import vafn_sb3
after = snapshot()
again = vafn_sb3.register_stock_aliases()
print(json.dumps({"before": before, "after": after, "again": again, "after_again": snapshot()}))
"""


def test_importing_vafn_sb3_adds_only_our_aliases_to_the_stock_tables_once() -> None:
    result = subprocess.run([sys.executable, "-c", SNAPSHOT_SCRIPT], env=SUBPROCESS_ENV, capture_output=True,
                            text=True, timeout=120, check=True)
    tables = json.loads(result.stdout.strip().splitlines()[-1])
    before, after = tables["before"], tables["after"]
    assert not any("vafn" in name for table in before.values() for name in table["aliases"].values())
    assert set(after) == set(before)
    for key, table in before.items():
        assert after[key]["id"] == table["id"], f"{key}: policy_aliases was replaced, not updated in place"
        assert after[key]["aliases"] == {**table["aliases"], **EXPECTED_ADDITIONS.get(key, {})}, key
        assert not set(EXPECTED_ADDITIONS.get(key, {})) & set(table["aliases"]), f"{key}: a stock name was overwritten"
    assert tables["again"] == [] and tables["after_again"] == after


def test_a_taken_stock_name_is_never_overwritten(monkeypatch: pytest.MonkeyPatch) -> None:
    from stable_baselines3 import SAC
    from stable_baselines3.sac.policies import SACPolicy

    from vafn_sb3 import aliases
    from vafn_sb3.common.agents import SharedAgentSACPolicy

    monkeypatch.setattr(aliases, "STOCK_ALIASES", {SAC: {"MlpPolicy": SharedAgentSACPolicy}})
    with pytest.warns(RuntimeWarning, match=r"SAC.policy_aliases\['MlpPolicy'\] is already SACPolicy"):
        assert aliases.register_stock_aliases() == []
    assert SAC.policy_aliases["MlpPolicy"] is SACPolicy
    monkeypatch.undo()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert aliases.register_stock_aliases() == []  # the real table: already registered, silently


def test_upstream_rl_zoo_trains_the_zoos_shared_sac_which_load_model_and_enjoy_run(tmp_path: Path) -> None:
    from rl_zoo3.utils import ALGOS

    from vafn_sb3.common.agents import SharedAgentSACPolicy
    from vafn_sb3.loading import load_model
    from zoo.enjoy import main as enjoy_main
    from zoo.registry import register_algorithms

    command = [
        sys.executable, "-m", "rl_zoo3.train", "--algo", "sac", "--env", ENV_ID, "--gym-packages", "vafn_sb3",
        "--conf-file", str(REPO_ROOT / "hyperparams" / "sac.yml"), "-n", "300", "-f", str(tmp_path),
        "--num-threads", "1", "--eval-freq", "-1", "--seed", "0",
        "-params", "learning_starts:100",  # so that 200 of the 300 steps update the policy
    ]
    result = subprocess.run(command, cwd=tmp_path, env=SUBPROCESS_ENV, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]

    model, algo = load_model(tmp_path / "sac" / f"{ENV_NAME}_1" / f"{ENV_NAME}.zip", trust_remote_code=True)  # ours
    assert algo == "sac" and type(model.policy) is SharedAgentSACPolicy
    assert model.num_timesteps == 300 and model._n_updates == 200

    # The same policy zoo/train.py builds from the same YAML: same class, same parameters and shapes.
    import gymnasium as gym

    register_algorithms()
    config = yaml.safe_load((REPO_ROOT / "hyperparams" / "sac.yml").read_text())[ENV_ID]
    zoo_model = ALGOS["sac"](config["policy"], gym.make(ENV_ID), policy_kwargs=eval(config["policy_kwargs"]))
    assert type(zoo_model.policy) is type(model.policy)
    assert {k: v.shape for k, v in zoo_model.policy.state_dict().items()} == {
        k: v.shape for k, v in model.policy.state_dict().items()}

    episodes = enjoy_main(["--algo", "sac", "--env", ENV_ID, "-f", str(tmp_path), "--n-episodes", "2"])
    assert len(episodes) == 2
    assert all(episode["length"] > 0 and episode["success"] in (0.0, 1.0) for episode in episodes)


@pytest.mark.parametrize("algo_name", ["TD3", "DDPG"])
def test_stock_td3_and_ddpg_train_the_shared_deterministic_actor(algo_name: str) -> None:
    import gymnasium as gym
    import stable_baselines3

    import vafn_sb3  # noqa: F401  (registers the aliases)
    from vafn_sb3.maddpg.policies import MADDPGPolicy

    algo = getattr(stable_baselines3, algo_name)
    model = algo("SharedAgentPolicy", gym.make(ENV_ID, max_length=1), learning_starts=50, batch_size=32, seed=0)
    model.learn(80)
    assert type(model.policy) is MADDPGPolicy and model._n_updates > 0
