"""SB3 zips load without unpickling (issue 61): a zoo run's zip acts as SB3's own load makes it act, a pickle payload
in any of its entries never runs, and ``zoo/enjoy.py -f`` needs no ``--trust-remote-code`` for a fresh run."""

from __future__ import annotations

import base64
import json
import os
import pickle
import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import pytest
import torch as th

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from vafn_sb3.loading import load_model  # noqa: E402

ENV_ID = "VAFN/ThreeArmReach-v1"
ENV_NAME = "VAFN-ThreeArmReach-v1"
SUBPROCESS_ENV = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


class _Payload:
    """Unpickling it creates ``marker``: proof that a file ran code."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return Path.touch, (self.marker,)


def payload(marker: Path, padding: int = 0) -> bytes:
    """A pickle whose unpickling creates ``marker`` (``padding`` bytes longer, to pass size checks)."""
    return pickle.dumps((_Payload(marker), b"x" * padding), protocol=2)


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A zoo log folder with one short SAC run of zoo/train.py (300 steps, 100 policy updates)."""
    from zoo.registry import register_algorithms
    from zoo.train import main as train_main

    th.set_num_threads(1)
    folder = tmp_path_factory.mktemp("logs")
    register_algorithms()
    train_main(["--algo", "sac", "--env", ENV_ID, "-n", "300", "-f", str(folder), "--seed", "0", "--eval-freq", "-1",
                "-params", "learning_starts:200", "batch_size:64", "--env-kwargs", "max_length:1"])
    return folder


def run_zip(logs: Path) -> Path:
    return logs / "sac" / f"{ENV_NAME}_1" / f"{ENV_NAME}.zip"


def rewrite(source: Path, target: Path, change: Any = None, entries: dict[str, bytes] | None = None) -> Path:
    """A copy of the zip ``source`` whose data JSON ``change(data)`` edited and whose ``entries`` are replaced."""
    with zipfile.ZipFile(source) as archive:
        kept = {name: archive.read(name) for name in archive.namelist()}
    if change is not None:
        data = json.loads(kept["data"])
        change(data)
        kept["data"] = json.dumps(data).encode()
    kept.update(entries or {})
    with zipfile.ZipFile(target, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, content in kept.items():
            archive.writestr(name, content)
    return target


def test_a_zoo_run_loads_without_the_flag_and_acts_as_sb3s_load(logs: Path) -> None:
    import gymnasium as gym

    import vafn_gym  # noqa: F401  (registers the env IDs)

    with mock.patch("stable_baselines3.common.save_util.json_to_data", side_effect=AssertionError("unpickled")):
        safe, key = load_model(run_zip(logs))
    trusted, trusted_key = load_model(run_zip(logs), trust_remote_code=True)
    assert key == trusted_key == "sac" and type(safe) is type(trusted) and type(safe.policy) is type(trusted.policy)
    assert safe.num_timesteps == 300 and safe._n_updates == trusted._n_updates > 0
    assert safe.lr_schedule(1.0) == trusted.lr_schedule(1.0) == 1e-3 and safe.batch_size == 64  # the YAML's
    env = gym.make(ENV_ID)
    observations = np.stack([env.observation_space.sample() for _ in range(64)])
    env.close()
    np.testing.assert_array_equal(safe.predict(observations, deterministic=True)[0],
                                  trusted.predict(observations, deterministic=True)[0])
    assert th.equal(safe.log_ent_coef, trusted.log_ent_coef)
    assert safe.actor.optimizer.state_dict()["state"].keys() == trusted.actor.optimizer.state_dict()["state"].keys()


def test_a_pickle_payload_in_any_entry_never_runs(logs: Path, tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    encoded = base64.b64encode(payload(marker)).decode()

    def every_serialized(data: dict) -> None:
        for value in data.values():
            if isinstance(value, dict) and ":serialized:" in value and "__module__" not in value:
                value[":serialized:"] = encoded  # the classes keep their names: the payload rides on the rest

    loaded, _ = load_model(rewrite(run_zip(logs), tmp_path / "values.zip", every_serialized))
    assert loaded.policy is not None and not marker.exists()  # loads: none of those values is ever unpickled

    def policy_class(data: dict) -> None:
        data["policy_class"] = {":type:": "<class 'abc.ABCMeta'>", ":serialized:": encoded}

    with pytest.raises(ValueError, match=r"class\.zip is an SB3 model zip .*policy class.*trust_remote_code=True"):
        load_model(rewrite(run_zip(logs), tmp_path / "class.zip", policy_class))
    with pytest.raises(ValueError, match=r"tensor\.zip: policy\.pth is not plain tensor data"):
        load_model(rewrite(run_zip(logs), tmp_path / "tensor.zip", entries={"policy.pth": payload(marker, 10**5)}))
    with pytest.raises(ValueError, match=r"optimizer\.zip: actor\.optimizer\.pth is not plain tensor data"):
        load_model(rewrite(run_zip(logs), tmp_path / "optimizer.zip", entries={"actor.optimizer.pth": payload(marker)}))

    def activation(data: dict) -> None:  # a class outside the allow-list, named in the JSON beside the pickle
        data["policy_kwargs"] = {":type:": "<class 'dict'>", ":serialized:": encoded, "net_arch": [64, 64],
                                 "activation_fn": "<class 'os.system'>"}

    with pytest.raises(ValueError, match=r"activation\.zip is an SB3 model zip .*activation_fn"):
        load_model(rewrite(run_zip(logs), tmp_path / "activation.zip", activation))
    assert not marker.exists()


def test_a_tampered_size_is_refused_before_the_model_is_built(logs: Path, tmp_path: Path) -> None:
    def huge(data: dict) -> None:
        data["policy_kwargs"]["net_arch"] = [16384, 16384]

    with pytest.raises(ValueError, match=r"huge\.zip: .*net_arch.*refused before building the model"):
        load_model(rewrite(run_zip(logs), tmp_path / "huge.zip", huge))


def test_enjoy_runs_a_fresh_zoo_run_without_the_flag_and_refuses_a_vecnormalize_pickle(logs: Path,
                                                                                        tmp_path: Path) -> None:
    command = [sys.executable, str(REPO_ROOT / "zoo" / "enjoy.py"), "--algo", "sac", "--env", ENV_ID, "-f", str(logs),
               "-n", "20"]
    result = subprocess.run(command, env=SUBPROCESS_ENV, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]

    marker = tmp_path / "pwned"
    stats = logs / "sac" / f"{ENV_NAME}_1" / ENV_NAME / "vecnormalize.pkl"
    stats.write_bytes(payload(marker))
    try:
        result = subprocess.run(command, env=SUBPROCESS_ENV, capture_output=True, text=True, timeout=300)
    finally:
        stats.unlink()
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and "vecnormalize.pkl" in lines[0], result.stderr[-3000:]
    assert "--trust-remote-code" in lines[0] and not marker.exists()
