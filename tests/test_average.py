"""Checkpoint averaging (``python -m vafn_media.average``): what is averaged, what is kept, what is refused."""

import json

import pytest

torch = pytest.importorskip("torch")

from vafn_media.average import average_state_dicts, main  # noqa: E402


def _state(audio: float, image: float = 5.0, shared: float = 7.0) -> dict:
    return {"encoders.audio.net.0.weight": torch.full((2, 3), audio),
            "encoders.audio.net.1.num_batches_tracked": torch.tensor(int(audio)),
            "adapters.audio.0.bias": torch.full((4,), 2 * audio),
            "encoders.image.net.0.weight": torch.full((2,), image),
            "projection.0.weight": torch.full((3,), shared)}


def test_the_fine_tuned_path_is_averaged_and_every_other_weight_kept():
    soup = average_state_dicts([_state(1.0), _state(3.0), _state(8.0)], "audio", weights=[2, 1, 1])
    assert torch.allclose(soup["encoders.audio.net.0.weight"], torch.full((2, 3), 0.5 * 1 + 0.25 * 3 + 0.25 * 8))
    assert torch.allclose(soup["adapters.audio.0.bias"], torch.full((4,), 2 * 3.25))
    assert int(soup["encoders.audio.net.1.num_batches_tracked"]) == 1  # a counter, taken from the first
    assert torch.equal(soup["encoders.image.net.0.weight"], torch.full((2,), 5.0))
    assert torch.equal(soup["projection.0.weight"], torch.full((3,), 7.0))
    equal = average_state_dicts([_state(1.0), _state(3.0)], "audio")
    assert torch.allclose(equal["encoders.audio.net.0.weight"], torch.full((2, 3), 2.0))


@pytest.mark.parametrize("states, modality, weights, message", [
    ([_state(1.0), _state(2.0, shared=6.0)], "audio", None, "differs from checkpoint 0 in projection.0.weight"),
    ([_state(1.0), _state(2.0)], "image", None, "outside the image path"),
    ([_state(1.0)], "audio", None, "at least two checkpoints"),
    ([_state(1.0), _state(2.0)], "audio", [1.0, 0.0], "one positive weight per checkpoint"),
    ([_state(1.0), _state(2.0)], "audio", [1.0], "one positive weight per checkpoint"),
    ([_state(1.0), _state(2.0)], "text", None, "modality must be one of"),
    ([_state(1.0), {**_state(2.0), "extra": torch.zeros(1)}], "audio", None, "other tensors"),
    ([_state(1.0), {**_state(2.0), "adapters.audio.0.bias": torch.zeros(5)}], "audio", None, "has shape"),
])
def test_checkpoints_that_are_not_fine_tunes_of_one_path_are_refused(states, modality, weights, message):
    with pytest.raises(ValueError, match=message):
        average_state_dicts(states, modality, weights)


def test_the_command_writes_a_loadable_calibrated_checkpoint_that_names_its_ingredients(tmp_path, monkeypatch):
    from vafn_media import InstructionGenerator
    from vafn_media import calibration
    from vafn_media.generator import DEFAULT_CHECKPOINT

    state = torch.load(DEFAULT_CHECKPOINT, map_location="cpu", weights_only=True)
    metadata = json.loads(DEFAULT_CHECKPOINT.with_suffix(".json").read_text())
    paths = []
    for index, scale in enumerate((0.9, 1.1)):
        (tmp_path / str(index)).mkdir()
        path = tmp_path / str(index) / "instruction_model.pt"
        torch.save({n: t * scale if n.startswith("encoders.audio.net.0.") else t for n, t in state.items()}, path)
        path.with_suffix(".json").write_text(json.dumps(metadata))
        paths.append(path)
    calibrated = []
    monkeypatch.setattr(calibration, "main", lambda argv: calibrated.append(argv))  # its own tests cover it
    written = main([str(p) for p in paths] + ["--out", str(tmp_path / "soup")])
    assert calibrated == [["--checkpoint", str(tmp_path / "soup" / "instruction_model.pt")]]
    assert written["command"].startswith("python -m vafn_media.average ")
    assert [entry["checkpoint"] for entry in written["averaged"]] == [str(p) for p in paths]
    assert all(entry["command"] == metadata["command"] for entry in written["averaged"])
    assert "validation" not in written and written["args"] == metadata["args"]  # the runs' records stay theirs
    soup = torch.load(tmp_path / "soup" / "instruction_model.pt", weights_only=True)
    assert torch.allclose(soup["encoders.audio.net.0.weight"], state["encoders.audio.net.0.weight"])  # (0.9 + 1.1) / 2
    generator = InstructionGenerator.load(tmp_path / "soup" / "instruction_model.pt", warm=False)
    assert generator.transcribe(code="2,3").instruction.arms == (2, 3)
    with pytest.raises(SystemExit):  # a checkpoint without its metadata
        paths[1].with_suffix(".json").unlink()
        main([str(p) for p in paths] + ["--out", str(tmp_path / "other")])
