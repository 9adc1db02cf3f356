"""The rule that chooses the audio path's blank penalty (benchmarks/blank_penalty.py)."""

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "blank_penalty", Path(__file__).resolve().parents[1] / "benchmarks" / "blank_penalty.py")
blank_penalty = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(blank_penalty)


def test_only_engines_the_checkpoint_trained_on_choose():
    metadata = {"args": {"mbrola_probability": 0.3, "pico_probability": 0.0}}
    engines = ["espeak", "flite", "mbrola", "pico", "piper"]
    assert blank_penalty.trained_engines(metadata, engines) == ["espeak", "mbrola"]
    assert blank_penalty.trained_engines({}, engines) == ["espeak"]


def test_choice_ignores_engines_it_may_not_look_at_and_breaks_ties_low():
    exact = {
        "espeak": {0.0: [100, 90, 90, 90, 90], 0.5: [100, 92, 92, 92, 92], 1.0: [100, 92, 92, 92, 92]},
        "piper": {0.0: [70, 60, 60, 60, 60], 0.5: [75, 65, 65, 65, 65], 1.0: [90, 90, 90, 90, 90]},
    }
    assert blank_penalty.engine_score(exact["espeak"][0.5]) == 96.0
    assert blank_penalty.choose_penalty(exact, ["espeak"]) == 0.5  # 0.5 and 1.0 tie: the smaller wins
    assert blank_penalty.choose_penalty(exact, ["espeak", "piper"]) == 1.0
    with pytest.raises(ValueError, match="no engine"):
        blank_penalty.choose_penalty(exact, [])


def test_command_writes_its_choice_into_the_checkpoint(tmp_path, monkeypatch):
    pytest.importorskip("espeakng_loader", reason="speech synthesis needs espeakng-loader ([media] extra)")
    import json
    import shutil
    import sys

    from vafn_media.generator import DEFAULT_CHECKPOINT

    checkpoint = tmp_path / "instruction_model.pt"
    shutil.copy(DEFAULT_CHECKPOINT, checkpoint)
    metadata = json.loads(DEFAULT_CHECKPOINT.with_suffix(".json").read_text())
    metadata.pop("blank_penalty", None)
    metadata.pop("blank_probe", None)
    checkpoint.with_suffix(".json").write_text(json.dumps(metadata))
    out = tmp_path / "table.md"
    monkeypatch.setattr(sys, "argv", ["blank_penalty.py", "--items", "4", "--engines", "espeak", "--checkpoint",
                                      str(checkpoint), "--out", str(out), "--write"])
    blank_penalty.main()
    written = json.loads(checkpoint.with_suffix(".json").read_text())
    assert written["blank_penalty"]["audio"] in blank_penalty.PENALTY_GRID
    assert f"Chosen on the held-out voices of espeak: **{written['blank_penalty']['audio']}**" in out.read_text()
    assert written["blank_probe"].get("audio", 0.0) > written["blank_penalty"]["audio"] or "**None**" in out.read_text()
    assert written["confidence_calibration"] == metadata["confidence_calibration"]  # the rest is kept


@pytest.mark.parametrize("reference, read, dropped, inserted, distance", [
    ((1, 2, 3), (1, 2, 3), [], [], 0),
    ((1, 2, 3, 1), (1, 3, 1), [2], [], 1),  # a swallowed word
    ((2, 2, 2), (2, 2, 2, 2), [], [2], 1),
    ((1, 2, 3), (1, 1, 3), [2], [1], 1),  # a swapped digit counts as both
    ((3, 1), (), [3, 1], [], 2),
])
def test_dropped_and_inserted_digits(reference, read, dropped, inserted, distance):
    from vafn_media.evaluation import dropped_and_inserted, edit_distance

    assert dropped_and_inserted(reference, read) == (dropped, inserted)
    assert edit_distance(reference, read) == distance


def test_probe_is_the_largest_penalty_within_the_flag_budget():
    flagged = {"espeak": {0.75: 0.5, 1.0: 1.0, 2.0: 1.9, 3.0: 4.0}, "mbrola": {0.75: 0.0, 1.0: 0.5, 2.0: 2.0, 3.0: 3.0},
               "piper": {0.75: 9.0, 1.0: 9.0, 2.0: 9.0, 3.0: 9.0}}
    assert blank_penalty.choose_probe(flagged, ["espeak", "mbrola"], chosen=0.5, budget=2.0) == 2.0
    assert blank_penalty.choose_probe(flagged, ["espeak", "mbrola"], chosen=0.5, budget=0.1) is None
    assert blank_penalty.choose_probe(flagged, ["piper"], chosen=0.5, budget=2.0) is None
    assert blank_penalty.choose_probe(flagged, ["espeak"], chosen=2.0, budget=5.0) == 3.0  # only above the penalty


def test_probe_rates_count_right_flagged_and_wrong_caught():
    class Item:
        def __init__(self, arms):
            self.arms = arms

    items = [Item((1, 2)), Item((1, 2)), Item((3,)), Item((2,))]
    chosen = [(1, 2), (1, 2), (1,), None]
    probe = [(1, 2), (1, 2, 2), (1, 3), None]
    assert blank_penalty.probe_rates(chosen, probe, items) == (50.0, 100.0)
