"""Trust boundaries (issue 61): no file a user is handed runs code, every size is checked before the work it costs, and
every command line answers bad input with exit 2 and one line. Each attack is built here and shown to do nothing."""

from __future__ import annotations

import base64
import io
import json
import os
import pickle
import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th

from vafn_sb3.common.serialization import CONFIG_ENTRY, POLICY_ENTRY, load_weights, save_weights
from vafn_sb3.loading import load_model, training_env

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))
ENV_ID = "VAFN/ThreeArmReach-v1"
#: The issue's bounds on any refusal.
MAX_REFUSAL_MB = 200
MAX_REFUSAL_S = 2.0


class _Payload:
    """Unpickling it creates ``marker``: proof that a file ran code."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return Path.touch, (self.marker,)


@pytest.fixture(scope="module")
def weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small, valid weights-only SAC file."""
    import gymnasium as gym

    import vafn_gym  # noqa: F401  (registers the env IDs)
    from vafn_sb3 import SAC

    th.set_num_threads(1)
    env = gym.make(ENV_ID, max_length=1)
    path = save_weights(SAC("MlpPolicy", env, policy_kwargs={"net_arch": [16, 16]}, seed=0),
                        tmp_path_factory.mktemp("weights") / "sac.zip")
    env.close()
    return path


def rewrite(source: Path, target: Path, entries: dict[str, bytes | str]) -> Path:
    """A copy of the zip ``source`` at ``target`` with ``entries`` replaced or added."""
    with zipfile.ZipFile(source) as archive:
        kept = {name: archive.read(name) for name in archive.namelist() if name not in entries}
    with zipfile.ZipFile(target, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, content in {**kept, **entries}.items():
            archive.writestr(name, content)
    return target


def tampered_config(weights: Path, target: Path, change: Any) -> Path:
    """A copy of ``weights`` whose config.json ``change(config)`` edited."""
    with zipfile.ZipFile(weights) as archive:
        config = json.loads(archive.read(CONFIG_ENTRY))
    change(config)
    return rewrite(weights, target, {CONFIG_ENTRY: json.dumps(config)})


def pickled_model(weights: Path, target: Path, marker: Path) -> Path:
    """The issue's attack: a weights-only zip plus an SB3 ``data`` entry whose serialized value runs a payload."""
    payload = base64.b64encode(pickle.dumps(_Payload(marker))).decode()
    data = {"policy_class": {":type:": "<class 'abc.ABCMeta'>", ":serialized:": payload}, "policy_kwargs": {}}
    with zipfile.ZipFile(weights) as archive:
        policy = archive.read(POLICY_ENTRY)
    return rewrite(weights, target, {"data": json.dumps(data), "policy.pth": policy})


def one_error_line(text: str, *needles: str) -> None:
    """``text`` (a command's stderr) is one error line containing every needle, no traceback."""
    lines = text.strip().splitlines()
    assert len(lines) == 1 and "error:" in lines[0] and "Traceback" not in text, text
    assert all(needle in lines[0] for needle in needles), (needles, lines[0])


# --- no file runs code -----------------------------------------------------------------------------------------------


def test_a_pickled_data_entry_is_refused_and_runs_only_behind_the_trust_flag(weights: Path, tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    path = pickled_model(weights, tmp_path / "m.zip", marker)
    with pytest.raises(ValueError, match=r"m\.zip is an SB3 model zip.*trust_remote_code=True"):
        load_model(path)
    assert load_weights(path).policy is not None  # the weights loader reads the weights and never the pickle
    assert not marker.exists()
    with pytest.raises(ValueError):  # the flag is the only gate: behind it SB3 unpickles, and the payload runs
        load_model(path, trust_remote_code=True)
    assert marker.exists()


def test_a_python_tag_in_the_config_yml_beside_a_model_is_refused(weights: Path, tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    run = tmp_path / "sac" / "VAFN-ThreeArmReach-v1_1"
    (run / "VAFN-ThreeArmReach-v1").mkdir(parents=True)
    model = run / "VAFN-ThreeArmReach-v1.zip"
    model.write_bytes(weights.read_bytes())
    config = run / "VAFN-ThreeArmReach-v1" / "config.yml"
    config.write_text(f"env_kwargs: !!python/object/apply:os.system ['touch {marker}']\n")
    with pytest.raises(ValueError, match=r"config\.yml is not a zoo config that loads safely"):
        training_env(model)
    assert not marker.exists()
    config.write_text("- - env_kwargs\n  - max_length: 2\n")  # rl_zoo3's own layout still loads
    assert training_env(model) == ("VAFN/ThreeArmReach-v1", {"max_length": 2})


def test_media_and_estimator_checkpoints_never_unpickle(tmp_path: Path) -> None:
    from vafn_media.generator import InstructionGenerator
    from vafn_sb3 import LearnedTargetEstimator

    marker = tmp_path / "pwned"
    for name in ("model.pt", "estimator.pt"):
        th.save({"state_dict": _Payload(marker)}, tmp_path / name)
    with pytest.raises(ValueError, match=r"model\.pt"):
        InstructionGenerator.load(tmp_path / "model.pt", warm=False)
    with pytest.raises(ValueError, match=r"estimator\.pt"):
        LearnedTargetEstimator.load(tmp_path / "estimator.pt")
    assert not marker.exists()


# --- limits before work ----------------------------------------------------------------------------------------------

#: (case id, change to a weights config, words the refusal must contain).
TAMPERED = [
    ("wide", lambda c: c["policy_kwargs"].update(net_arch=[16384, 16384]), "outside [1, 4096]"),
    ("deep", lambda c: c["policy_kwargs"].update(net_arch=[64] * 20000), "20000 items"),
    ("critics", lambda c: c["policy_kwargs"].update(n_critics=2000), "n_critics"),
    ("buffer", lambda c: c["hyperparameters"].update(buffer_size=1e11), "buffer_size"),
    ("buffer_bytes", lambda c: (c["hyperparameters"].update(buffer_size=10**7), c["observation_space"].update(
        shape=[4096], low=[-1.0] * 4096, high=[1.0] * 4096)), "-byte buffer"),
    ("space", lambda c: c["observation_space"].update(shape=[10**9]), "observation_space has 1,000,000,000 elements"),
    ("undeclared", lambda c: c["policy_kwargs"].update(net_arch=[4096, 4096]), "needs at least"),
]


def _nan_weights(weights: Path, target: Path) -> Path:
    with zipfile.ZipFile(weights) as archive:
        state = th.load(io.BytesIO(archive.read(POLICY_ENTRY)), weights_only=True)
    key = next(iter(state))
    state[key] = state[key].clone().fill_(float("nan"))
    buffer = io.BytesIO()
    th.save(state, buffer)
    return rewrite(weights, target, {POLICY_ENTRY: buffer.getvalue()})


def _spaces_config(weights: Path, target: Path, megabytes: int) -> Path:
    """``weights`` with a config.json of ``megabytes`` MB of spaces (deflated to well under 1 % of that)."""
    with zipfile.ZipFile(weights) as archive:
        entries = {name: archive.read(name) for name in archive.namelist() if name != CONFIG_ENTRY}
    with zipfile.ZipFile(target, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        with archive.open(CONFIG_ENTRY, "w", force_zip64=True) as handle:
            for _ in range(megabytes):
                handle.write(b" " * 2**20)
        for name, content in entries.items():
            archive.writestr(name, content)
    return target


def _strip_png(target: Path, width: int, height: int, suffix: str = ".png", **options: Any) -> Path:
    from PIL import Image

    path = target.with_suffix(suffix)
    image = Image.new("L", (width, height), 255)
    image.paste(0, (0, 0, min(width, 4), height))
    image.save(path, **options)
    return path


#: Run in a fresh interpreter: each case's refusal message, wall time and peak memory above the resident set before it
#: (the kernel's high-water mark, reset before every case), after the libraries are imported and warmed up.
MEASURE = r"""
import json, os, re, sys, time
import numpy as np, torch
torch.set_num_threads(1)
from vafn_sb3 import load_pretrained
from vafn_sb3.common.serialization import load_weights
from vafn_sb3.loading import load_model
import vafn_sb3.registry  # imports every algorithm (sb3-contrib's included) before the measurements
from vafn_media.images import canonical_strip
from vafn_media.strips import render_strip

def status_kb(field):
    return int(re.search(field + r":\s+(\d+)", open("/proc/self/status").read()).group(1))

load_pretrained("sac"); canonical_strip(render_strip([1, 2], np.random.default_rng(0)))
functions = {"model": load_model, "weights": load_weights, "image": canonical_strip, "array": canonical_strip}
results = []
for kind, argument in json.loads(sys.argv[1]):
    argument = np.zeros(argument, np.uint8) if kind == "array" else argument
    with open("/proc/self/clear_refs", "w") as handle:
        handle.write("5")
    before, start = status_kb("VmRSS"), time.perf_counter()
    try:
        functions[kind](argument)
        message = None
    except ValueError as error:
        message = str(error)
    results.append({"message": message, "seconds": time.perf_counter() - start,
                    "peak_mb": (status_kb("VmHWM") - before) / 1024})
print(json.dumps(results))
"""


def measure_refusals(cases: list[tuple[str, Any]]) -> list[dict[str, Any]]:
    """:data:`MEASURE` on ``cases`` ((function kind, path or array shape) pairs) in a subprocess."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    result = subprocess.run([sys.executable, "-c", MEASURE, json.dumps(cases)], capture_output=True, text=True,
                            env=env, timeout=300, cwd=REPO_ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux's resettable peak memory")
def test_every_refusal_is_a_value_error_naming_the_file_within_200_mb_and_2_s(weights: Path, tmp_path: Path) -> None:
    cases, expected = [], []
    for name, change, words in TAMPERED:
        path = tampered_config(weights, tmp_path / f"{name}.zip", change)
        cases += [("weights", str(path)), ("model", str(path))]
        expected += [(path.name, words)] * 2
    for path, words in ((_nan_weights(weights, tmp_path / "nan.zip"), "NaN or infinite"),
                        (_spaces_config(weights, tmp_path / "spaces.zip", 400), "refused without inflating")):
        cases += [("weights", str(path)), ("model", str(path))]
        expected += [(path.name, words)] * 2
    images = [(_strip_png(tmp_path / "strip", 999_999, 8), "a side has at most"),
              (_strip_png(tmp_path / "wide", 1_100_000, 8, ".tif", compression="tiff_deflate"), "a side has at most"),
              (_strip_png(tmp_path / "sliver", 30_000, 8), "more than 32 times")]
    cases += [("image", str(path)) for path, _ in images] + [("array", [8, 2_000_000]), ("array", [8, 30_000])]
    expected += [(path.name, words) for path, words in images]
    expected += [("image", "a side has at most"), ("image", "more than 32 times")]
    assert (tmp_path / "spaces.zip").stat().st_size < 1_000_000 and images[0][0].stat().st_size < 100_000

    for (kind, argument), (name, words), result in zip(cases, expected, measure_refusals(cases)):
        what = f"{kind} {Path(str(argument)).name}: {result}"
        print(f"{kind:8} {Path(str(argument)).name:18} {result['seconds']:.3f} s {result['peak_mb']:6.1f} MB")
        assert result["message"] is not None and name in result["message"] and words in result["message"], what
        assert result["peak_mb"] <= MAX_REFUSAL_MB and result["seconds"] <= MAX_REFUSAL_S, what


@pytest.mark.filterwarnings("ignore:the packaged")  # a policy shipped for a negative result says so
def test_packaged_policies_and_checkpoints_still_load() -> None:
    from vafn_media.generator import InstructionGenerator
    from vafn_sb3 import available_pretrained, load_pretrained

    for algo, env_id in available_pretrained():
        assert load_pretrained(algo, env_id).policy is not None
    assert InstructionGenerator.load(warm=False).model is not None


def test_an_image_opencv_cannot_decode_drops_only_that_modality(tmp_path: Path) -> None:
    from vafn_media.generator import InstructionGenerator
    from vafn_media.images import read_image_file

    speech = pytest.importorskip("vafn_media.speech")
    try:
        audio = speech.speak((2, 3), template=2)
    except (ImportError, OSError, RuntimeError):
        pytest.skip("espeak-ng is not installed")
    wide = _strip_png(tmp_path / "wide", 1_100_000, 8, ".tif", compression="tiff_deflate")
    with pytest.raises(ValueError, match="wide.tif"):
        read_image_file(wide)
    audio = np.concatenate([np.zeros(4000, np.float32), audio, np.zeros(4000, np.float32)])
    result = InstructionGenerator.load(warm=False).transcribe(audio=(audio, speech.ESPEAK_SAMPLE_RATE), image=wide)
    assert result.modalities == ("audio",) and any("wide.tif" in warning for warning in result.warnings)


# --- command lines: exit 2, one line ---------------------------------------------------------------------------------


def test_vafn_demo_bad_input_is_exit_2_and_one_line(weights: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    from vafn_app import demo

    for argv, words in ((["--size", "5000", "300"], "--size 5000 300"), (["--bogus"], "unrecognized arguments")):
        with pytest.raises(SystemExit) as exit_info:
            demo.main(argv)
        assert exit_info.value.code == 2
        one_error_line(capsys.readouterr().err, words)
    assert demo.main(["--code", "1", "--out", "/dev/null/x"]) == 2
    one_error_line(capsys.readouterr().err, "--out /dev/null/x")
    marker = tmp_path / "pwned"
    cases = [(pickled_model(weights, tmp_path / "m.zip", marker), "--trust-remote-code"),
             (tampered_config(weights, tmp_path / "b.zip", lambda c: c["hyperparameters"].update(buffer_size=1e11)),
              "buffer_size")]
    for model, words in cases:
        assert demo.main(["--code", "1", "--model", str(model), "--out", str(tmp_path / "out")]) == 2
        one_error_line(capsys.readouterr().err, model.name, words)
    assert not marker.exists()


def test_online_control_bad_input_is_exit_2_and_one_line(weights: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    from zoo import online_control

    marker = tmp_path / "pwned"
    out = ["--out", str(tmp_path / "out"), "--steps", "5"]
    cases = [
        (["--policy", "scripted", "--schedule", "0:4", *out], "arm"),  # a 3-arm env has no arm 4
        (["--policy", "scripted", "--schedule", "0:1", "--steps", "x"], "invalid int value"),
        (["--model", str(pickled_model(weights, tmp_path / "m.zip", marker)), "--schedule", "0:1", *out],
         "--trust-remote-code"),
    ]
    for argv, words in cases:
        with pytest.raises(SystemExit) as exit_info:
            online_control.main(argv)
        assert exit_info.value.code == 2
        one_error_line(capsys.readouterr().err, words)
    assert not marker.exists()


def test_the_installed_commands_answer_in_one_line_without_a_traceback(tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    bin_dir = Path(sys.executable).parent
    for command in ([str(bin_dir / "vafn-demo"), "--size", "5000", "300"],
                    [str(bin_dir / "vafn-instruct"), "--image", str(tmp_path / "missing.png")],
                    [sys.executable, str(REPO_ROOT / "zoo" / "enjoy.py"), "--frame-skip", "0"]):
        result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
        assert result.returncode == 2, (command, result.stderr[-2000:])
        one_error_line(result.stderr)


# --- bounded fuzz ----------------------------------------------------------------------------------------------------


def test_mutated_model_files_raise_only_value_error(weights: Path, tmp_path_factory: pytest.TempPathFactory) -> None:
    hypothesis = pytest.importorskip("hypothesis")
    from hypothesis import strategies as st

    original = weights.read_bytes()
    folder = tmp_path_factory.mktemp("fuzz")

    @hypothesis.settings(max_examples=40, deadline=None, derandomize=True, database=None)
    @hypothesis.given(st.one_of(
        st.binary(max_size=2000),
        st.lists(st.tuples(st.integers(0, len(original) - 1), st.integers(0, 255)), min_size=1, max_size=8),
        st.dictionaries(st.sampled_from([CONFIG_ENTRY, POLICY_ENTRY, "variables.pt", "data", "policy.pth"]),
                        st.binary(max_size=300), min_size=1, max_size=3),
    ))
    def check(mutation: Any) -> None:
        path = folder / "fuzzed.zip"
        if isinstance(mutation, bytes):
            path.write_bytes(mutation)
        elif isinstance(mutation, list):
            data = bytearray(original)
            for position, value in mutation:
                data[position] = value
            path.write_bytes(bytes(data))
        else:
            rewrite(weights, path, mutation)
        for loader in (load_weights, load_model):
            try:
                loader(path)
            except ValueError:
                pass

    check()
